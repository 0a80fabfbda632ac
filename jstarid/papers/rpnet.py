"""The RpNet paper's experiments (Xu et al., IEEE Access 2019): the noise sweeps of Figs. 8–11, the
figures its text quotes, and the weight-searching weights of Table 5.

Camera ``rpnet2019`` (1024², f = 49.277 mm, 0.012 mm pixels, V ≤ 6.0; simulation list to V 7.0),
each scene with a random guide star at the boresight and a random roll (the paper's test sets, "built
in the same way as the training data set"), one noise family at a time:

- fig8: position σ 0.2–1.6 px (step 0.2);
- fig9: magnitude σ 0–0.969 mag in steps of 0.1615 (the paper's levels 0.323, 0.484, 0.646, 0.807,
  0.969 of §II-C.2 and its text, plus 0 and 0.161), before the V 6.0 limit, simulated from V 7.0;
- fig10: false-star ratio p = N_f / (N_t + N_f) = 0–50 % (step 5 %, eq. 12), uniform over the image,
  magnitudes uniform in the training range (0–6);
- fig11: 0–5 missing stars (the paper: 1–5; 0 as the reference).
"""

from __future__ import annotations

from jstarid.papers import Sweep

CAMERA = "rpnet2019"


SWEEPS = {
    "fig8": Sweep("position_sigma_px", [0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6], {}, "position noise σ (px)"),
    "fig9": Sweep("magnitude_sigma", [0.0, 0.161, 0.323, 0.484, 0.646, 0.807, 0.969], {},
                  "magnitude noise σ (mag)"),
    "fig10": Sweep("false_ratio", [0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5],
                   {"false_mag_min": 0.0, "false_mag_max": 6.0}, "false-star ratio p"),
    "fig11": Sweep("n_missing", [0, 1, 2, 3, 4, 5], {}, "missing stars per image"),
}

# The paper's Figs. 8–11 are curves whose data are not in the text; these are the values its text
# quotes (identification rate, %). "approx" marks values read from a qualitative statement.
PAPER = {
    "fig8": {"note": "near 100 % with no attenuation up to 1 px (approx.); drops to 94 % at 1.6 px",
             "values": {0.2: 100.0, 0.4: 100.0, 0.6: 100.0, 0.8: 100.0, 1.0: 100.0, 1.6: 94.0},
             "approx": {0.2, 0.4, 0.6, 0.8, 1.0}},
    "fig9": {"note": "99.90 % at 0.323 Mv → 98.11 % at 0.969 Mv", "values": {0.323: 99.90, 0.969: 98.11},
             "approx": set()},
    "fig10": {"note": "> 80 % for p < 20 % (a bound, approx.); 35 % at p = 50 %",
              "values": {0.15: 80.0, 0.5: 35.0}, "approx": {0.15}},
    "fig11": {"note": "97.6 % with 1 missing star → 81.09 % with 5", "values": {1: 97.6, 5: 81.09},
              "approx": set()},
}

# Table 5: the weights of eq. 9 (position) and eq. 11 (probability).
TABLE5_POSITION_WEIGHTS = (0.45, 0.30, 0.25)
TABLE5_PROBABILITY_WEIGHTS = (0.60, 0.25, 0.15)
