"""A :class:`~jstarid.DetectionModel` fitted to labelled real data: which catalog stars were detected, how
far their measured magnitudes and positions fell from the catalog's.

The input is one record per catalog star that could have been detected (in the field, to a depth past
the detector's limit): its catalog V, whether a detection was that star and, for those that were, the
measured − catalog magnitude and the position residual (px). Solved real frames give these (the
attitude predicts every catalog star's position; ``experiments/detection_model.py``), and so does a
labelled centroid file with its attitude. Three fits, in the model's own terms (x = 10^(0.4 V), the
inverse of a star's relative flux; module :mod:`jstarid.detection_model`):

1. **Magnitude scatter** per 0.5-mag bin (robust variance, bins where ≥ 90 % are detected, so the
   threshold does not truncate it): σ²(V) = σ_m² + (1.0857)² (a x + b x²), non-negative least squares.
   a = 1/S₀ is the shot noise (it fixes the zero point S₀ in electrons unless one is given) and
   b = B/S₀² the background; σ_m is the band floor (``NoiseConfig.magnitude_sigma``). The median
   residual in those bins is the magnitudes' zero-point offset (reported, not modelled: algorithms
   rank by brightness).
2. **Completeness**, every record: maximum likelihood of detected / missed under
   P(V) = Φ((S − T) / √(S + B_d)) averaged over σ_m — the threshold T and the detection background B_d.
3. **Position scatter** per bin: σ²(V) = σ₀² + c² (a x + b_c x²), non-negative least squares: the
   floor σ₀ (``NoiseConfig.position_sigma_px``: attitude, distortion, optics), the scale c and the
   centroid's background B_c.

4. **Unmatched detections** (optional: the measured magnitudes of detections that are no catalog star,
   and the number of frames): their mean count per frame and their brightness distribution, density
   ∝ 10^(s m) between the faintest and brightest (maximum likelihood), as ``NoiseConfig``'s clutter —
   hot pixels, cosmic rays, and real stars past the catalog's depth. An extractor's noise peaks pile
   up just above its threshold under a sparse bright tail, which one slope cannot follow (it would put
   three times too many of them among the brightest detections): a knee with a second slope fainter
   than it is fitted too, and kept when it gains more than :data:`KNEE_GAIN` in log-likelihood.

Vignetting and blends are not fitted (a fitted model has none: their effect on the scatter lands in
the floors); give ``merge_radius_px`` when it is known.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = ["DetectionFit", "fit_detection"]

_MAG_SCALE = 2.5 / math.log(10.0)  # σ_m = 1.0857 ρ for a small relative flux error ρ
_BIN = 0.5


class DetectionFit(NamedTuple):
    """A fitted detection model and the noise floors that go with it.

    Attributes:
        model: :class:`~jstarid.DetectionModel`.
        magnitude_sigma: band floor σ_m (mag): ``NoiseConfig.magnitude_sigma``.
        position_sigma_px: position floor σ₀ (px): ``NoiseConfig.position_sigma_px``.
        magnitude_offset: median measured − catalog magnitude (mag) of the detected stars.
        stars: records fitted; detected: how many of them were detected.
        clutter: :class:`~jstarid.NoiseConfig` clutter fields (``false_mean``, ``false_mag_min``,
            ``false_mag_max``, ``false_mag_slope``, and ``false_mag_knee`` and
            ``false_mag_slope_faint`` where a knee was fitted) of the unmatched detections, in
            catalog V; empty when none were given.
    """

    model: object
    magnitude_sigma: float
    position_sigma_px: float
    magnitude_offset: float
    stars: int
    detected: int
    clutter: dict

    def noise(self, **fields):
        """A :class:`~jstarid.NoiseConfig` with the fitted floors and clutter (and any other ``fields``)."""
        from jstarid.simulator import NoiseConfig

        return NoiseConfig(position_sigma_px=self.position_sigma_px, magnitude_sigma=self.magnitude_sigma,
                           **{**self.clutter, **fields})


def _robust_var(values) -> float:
    values = np.asarray(values, np.float64)
    return float((1.4826 * np.median(np.abs(values - np.median(values)))) ** 2)


def _binned(mag, values, detected_share, *, min_count, min_share, per_axis=False):
    """(x, variance, count) of each 0.5-mag bin with enough records and detections."""
    rows = []
    lo = math.floor(np.min(mag) / _BIN) * _BIN
    while lo <= np.max(mag):
        sel = (mag >= lo) & (mag < lo + _BIN)
        if sel.sum() >= min_count and detected_share(lo) >= min_share:
            v = values[sel]
            var = _robust_var(v.reshape(-1)) if per_axis else _robust_var(v)
            rows.append((10.0 ** (0.4 * float(np.mean(mag[sel]))), var, int(sel.sum())))
        lo += _BIN
    return np.asarray(rows).reshape(-1, 3)


def _nnls(design, target, weight):
    from scipy.optimize import nnls

    solution, _ = nnls(design * weight[:, None], target * weight)
    return solution


def fit_detection(true_mag, detected, measured_mag=None, position_error_px=None, *,
                  zero_point_e: float | None = None, merge_radius_px: float = 0.0,
                  unmatched_mag=None, frames: int | None = None, min_count: int = 8) -> DetectionFit:
    """Fit a :class:`~jstarid.DetectionModel` to labelled records (module docstring).

    Args:
        true_mag: (n,) catalog V of every star that could have been detected (mag).
        detected: (n,) bool, whether a detection was that star.
        measured_mag: (n,) measured magnitude (any zero point; NaN or ignored where not detected).
        position_error_px: (n, 2) measured − predicted position (px; ignored where not detected).
        zero_point_e: electrons from V = 0 when known (a sensor's): only the shape of the curves is
            fitted then; by default the shot-noise term of the magnitude scatter sets it.
        merge_radius_px: the blend radius to put in the model (not fitted).
        unmatched_mag: measured magnitudes of the detections that are no catalog star (same zero
            point as ``measured_mag``), over ``frames`` frames: fitted as clutter.
        frames: how many frames the records and ``unmatched_mag`` come from.
        min_count: fewest records in a magnitude bin used in the scatter fits.

    Returns:
        :class:`DetectionFit`.

    Raises:
        ValueError: mismatched shapes, fewer than 20 detected records, or no star missed (nothing
            to place the threshold by: include stars past the detection limit).
    """
    from scipy.optimize import minimize

    from jstarid.detection_model import DetectionModel

    mag = np.asarray(true_mag, np.float64).reshape(-1)
    found = np.asarray(detected, bool).reshape(-1)
    if found.shape != mag.shape:
        raise ValueError(f"detected has shape {found.shape}, true_mag {mag.shape}")
    if not np.all(np.isfinite(mag)):
        raise ValueError("true_mag must be finite catalog magnitudes")
    if found.sum() < 20:
        raise ValueError(f"need at least 20 detected stars to fit, got {int(found.sum())}")
    if found.all():
        raise ValueError("every star was detected: include catalog stars past the detection limit")

    # the detected share of each 0.5-mag bin, looked up per record or per bin's lower edge
    cell = np.floor(mag / _BIN).astype(np.int64)
    first = int(cell.min())
    totals = np.bincount(cell - first)
    hits = np.bincount(cell - first, weights=found.astype(np.float64), minlength=totals.size)
    shares = np.where(totals > 0, hits / np.maximum(totals, 1), 0.0)
    record_share = shares[cell - first]

    def share(lo):
        i = int(round(lo / _BIN)) - first
        return float(shares[i]) if 0 <= i < shares.size else 0.0

    # 1. magnitude scatter → σ_m, a = 1/S₀, b = B/S₀²
    offset, sigma_m, a, b = 0.0, 0.0, 0.0, 0.0
    if measured_mag is not None:
        resid = np.asarray(measured_mag, np.float64).reshape(-1) - mag
        ok = found & np.isfinite(resid)
        complete = record_share >= 0.9
        offset = float(np.median(resid[ok & complete] if np.any(ok & complete) else resid[ok]))
        bins = _binned(mag[ok], resid[ok], share, min_count=min_count, min_share=0.9)
        if len(bins) >= 3:
            x, var, n = bins.T
            design = np.stack([np.ones_like(x), _MAG_SCALE ** 2 * x, _MAG_SCALE ** 2 * x ** 2], 1)
            sigma_m2, a, b = _nnls(design, var, np.sqrt(n) / np.maximum(var, 1e-12))
            sigma_m = math.sqrt(sigma_m2)
    s0 = float(zero_point_e) if zero_point_e else (1.0 / a if a > 1e-12 else 1e9)
    background = b * s0 ** 2

    # 2. completeness → T, B_d (log-parameters, maximum likelihood)
    order = np.argsort(mag)
    low = record_share[order] < 0.5
    cross = mag[order][np.argmax(low)] if np.any(low) else float(np.max(mag))
    t0 = s0 * 10.0 ** (-0.4 * cross)

    def model_of(params):
        t, bd = np.exp(params)
        return DetectionModel(zero_point_e=s0, background_e2=background, threshold_e=t,
                              detection_background_e2=bd)

    def loss(params):
        p = np.clip(model_of(params).completeness(mag, sigma_m), 1e-9, 1 - 1e-9)
        return -float(np.sum(np.where(found, np.log(p), np.log1p(-p))))

    best = minimize(loss, np.log([t0, (t0 / 5.0) ** 2]), method="Nelder-Mead",
                    options={"xatol": 1e-4, "fatol": 1e-3, "maxiter": 2000})
    threshold, detection_background = (float(v) for v in np.exp(best.x))

    # 3. position scatter → σ₀, c, B_c
    sigma0, scale, position_background = 0.0, 0.0, 0.0
    if position_error_px is not None:
        err = np.asarray(position_error_px, np.float64).reshape(-1, 2)
        ok = found & np.all(np.isfinite(err), axis=1)
        bins = _binned(mag[ok], err[ok], share, min_count=min_count, min_share=0.5, per_axis=True)
        if len(bins) >= 3:
            x, var, n = bins.T
            design = np.stack([np.ones_like(x), x, x ** 2], 1)
            sigma02, shot, back = _nnls(design, var, np.sqrt(n) / np.maximum(var, 1e-12))
            sigma0 = math.sqrt(sigma02)
            if shot > 0 or back > 0:
                # shot = c² / S₀, back = c² B_c / S₀²; a shot term the fit set to 0 is kept a millionth
                # of the background's at the faintest bin (c² S / S² has no exact zero but c = 0)
                shot = max(shot, 1e-6 * back * float(x.max()))
                scale = math.sqrt(shot * s0)
                position_background = back * s0 ** 2 / scale ** 2
    model = DetectionModel(zero_point_e=s0, background_e2=background, threshold_e=threshold,
                           detection_background_e2=detection_background, position_scale_px=scale,
                           position_background_e2=position_background,
                           merge_radius_px=float(merge_radius_px))
    model.validate()
    clutter = {} if unmatched_mag is None else _clutter(np.asarray(unmatched_mag, np.float64) - offset,
                                                        frames)
    return DetectionFit(model, sigma_m, sigma0, offset, int(mag.size), int(found.sum()), clutter)


def _clutter(mags, frames) -> dict:
    """NoiseConfig clutter fields for unmatched detections of magnitudes ``mags`` (catalog V) over
    ``frames`` frames: a Poisson count and a truncated-exponential brightness distribution, with a knee
    (two slopes) where that is likelier by more than :data:`KNEE_GAIN` in log-likelihood."""
    from scipy.optimize import minimize, minimize_scalar

    if not frames or frames < 1:
        raise ValueError("give frames (how many frames the unmatched detections come from)")
    mags = mags[np.isfinite(mags)]
    if mags.size < 2:
        return {"false_mean": mags.size / frames}
    lo, hi = float(mags.min()), float(mags.max())
    slope = float(minimize_scalar(lambda s: _knee_nll(mags, lo, hi, s, s, hi), bounds=(-5.0, 5.0),
                                  method="bounded").x)
    out = {"false_mean": mags.size / frames, "false_mag_min": lo, "false_mag_max": hi,
           "false_mag_slope": slope}
    if mags.size < KNEE_MIN_COUNT:
        return out
    single = _knee_nll(mags, lo, hi, slope, slope, hi)

    def loss(p):
        s1, s2, knee = p
        if not (abs(s1) <= 5 and abs(s2) <= 5 and lo < knee < hi):
            return np.inf
        return _knee_nll(mags, lo, hi, s1, s2, knee)

    best = min((minimize(loss, [slope, slope, float(np.quantile(mags, q))], method="Nelder-Mead",
                         options={"xatol": 1e-4, "fatol": 1e-4, "maxiter": 4000})
                for q in (0.05, 0.25, 0.5, 0.75)), key=lambda r: r.fun)
    if mags.size * (single - best.fun) > KNEE_GAIN:
        s1, s2, knee = (float(v) for v in best.x)
        out.update(false_mag_slope=s1, false_mag_knee=knee, false_mag_slope_faint=s2)
    return out


KNEE_MIN_COUNT = 50  # unmatched detections before a knee is tried
KNEE_GAIN = 3.0  # log-likelihood a knee (two more parameters) must gain


def _mass(b, length):
    """∫₀^length e^(b t) dt."""
    return length if abs(b * length) < 1e-9 else math.expm1(b * length) / b


def _knee_nll(mags, lo, hi, s1, s2, knee) -> float:
    """Mean negative log-likelihood of ``mags`` under density 10^(s₁ (m − k)) brighter than the knee
    k, 10^(s₂ (m − k)) fainter, on [lo, hi] (the simulator's ``_false_magnitudes``)."""
    a1, a2 = s1 * math.log(10.0), s2 * math.log(10.0)
    total = _mass(-a1, knee - lo) + _mass(a2, hi - knee)
    log_density = np.where(mags < knee, a1 * (mags - knee), a2 * (mags - knee))
    return float(math.log(total) - np.mean(log_density))
