"""The SGM paper's simulation experiments (You et al. 2022, Table 2, Figs. 6–8): which scenes, which
levels, the paper's figures.

Scenes in mode (b): each selected database star is the boresight ("main star") with a random roll, on
the ``sgm2022`` camera (1024², 20°×20°, V ≤ 6). Experiments: position noise σ = 0 … 3 px (step
0.5); the same plus 1 lost star; the same plus 1 fake star (uniform over the image). The scenes of a
level depend on (seed, experiment, σ) alone (:func:`level_key`), so any subset of levels, run in any
order, resumed, or looked at scene by scene (``experiments/probes/diagnose_sgm.py``), draws the same scenes.
"""

from __future__ import annotations

import jax
import numpy as np

import jstarid as js

CAMERA = "sgm2022"
MAG_LIMIT = 6.0
EXPERIMENTS = ("position", "lost", "fake")
SIGMAS = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0)  # position noise σ (px)
CAPACITY = 128  # detections per scene: a 20°×20° field holds > 64 V ≤ 6 stars in dense regions
BATCH = 256  # scenes per simulate / identify call

PAPER = {  # Table 2, "Ours" (%)
    "position": {"MA": 99.71, "stdA": 0.22, "RA": 0.60, "ALN": 99.69},
    "lost": {"MA": 99.26, "stdA": 0.38, "RA": 0.97, "ALN": 99.05},
    "fake": {"MA": 99.42, "stdA": 0.28, "RA": 0.85, "ALN": 99.16},
}


def level_key(seed: int, experiment: str, sigma: float):
    """The level's PRNG key: a function of (seed, experiment, σ) alone."""
    key = jax.random.fold_in(jax.random.key(seed), EXPERIMENTS.index(experiment))
    return jax.random.fold_in(key, round(sigma * 100))


def main_star_rows(n_catalog: int, n_stars: int | None, seed: int) -> np.ndarray:
    """(R,) catalog rows used as main stars: every star (``n_stars`` None), or ``n_stars`` drawn
    with ``seed``."""
    rng = np.random.default_rng(seed)
    return (np.arange(n_catalog) if n_stars is None
            else np.sort(rng.choice(n_catalog, n_stars, replace=False)))


def level_scenes(catalog, camera, rows, experiment: str, sigma: float, *, seed: int, batch: int = BATCH,
                 capacity: int = CAPACITY, batches=None):
    """Yield ``(start, scenes)`` for the batches of a level: the scenes of main stars
    ``rows[start:start + batch]``.

    ``batches``: optional set of batch indices to simulate (the others are skipped, their keys
    still drawn), so a diagnosis can look at one batch of a full-size level.
    """
    noise = js.NoiseConfig(position_sigma_px=float(sigma), n_missing=int(experiment == "lost"),
                           n_false=int(experiment == "fake"))
    key = level_key(seed, experiment, sigma)
    for i, s in enumerate(range(0, rows.size, batch)):
        key, k2 = jax.random.split(key)
        if batches is None or i in batches:
            yield s, js.simulate(k2, catalog, camera, noise, capacity=capacity,
                                 boresight_ids=rows[s:s + batch])
