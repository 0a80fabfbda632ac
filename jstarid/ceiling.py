"""The naming ceiling: how often *any* position-only identifier could name every required star.

Position noise can carry a detection past a close neighbour; then no method reading positions alone
can tell the two stars apart. This module measures that limit on simulated scenes, so a rate can be
compared with what is reachable rather than with 100 %.

**The oracle** knows the true attitude, which detections are false, and which catalog stars produced
the required detections; only the correspondence is hidden. Under conventions §3 position noise
(independent Gaussian x, y, one σ) and exchangeable labels (magnitudes ignored, as in SGM), the
posterior of a correspondence π is ∝ exp(−Σ_i ‖x_i − s_π(i)‖² / 2σ²); its MAP, the least summed squared
pixel distance assignment, most often names *all* of them correctly, whatever σ. A real identifier
knows less, so its rate of fully and correctly named scenes cannot exceed the oracle's: the
*ceiling* under that criterion.

**At a confidence margin** (``margin_nats``): detection i keeps its name when the best correspondence
naming it otherwise costs at least the margin more (a max-marginal log likelihood ratio,
``Δ‖·‖² / 2σ²`` with the true σ); the ceiling is then the share of scenes whose every required star is
named *and* clears it. Accuracy (SGM eq. 9) of an identifier failing a fraction f is at most
``ceiling / (1 − f)`` (:func:`accuracy_bound`).

Host-side NumPy/SciPy analysis (``scipy.optimize.linear_sum_assignment`` per scene), not part of any
identification.
"""

from __future__ import annotations

import numpy as np

from jstarid.metrics import sgm_required
from jstarid.scene import Scene

__all__ = ["naming_ceiling", "accuracy_bound"]

REGIONS = ("sgm", "all")


def naming_ceiling(scenes: Scene, star_vectors, camera, *, region: str = "sgm",
                   radius_deg: float = 6.0, margin_nats: float = 0.0,
                   sigma_px=None) -> np.ndarray:
    """(B,) bool: the oracle's correspondence names every required star of the scene correctly.

    Args:
        scenes: (B, N) simulated scenes (truth and attitude are used).
        star_vectors: (M, 3) ICRS unit vectors indexed by ``scenes.truth``, or a
            :class:`~jstarid.catalog.Catalog`.
        camera: the scenes' camera.
        region: ``"sgm"`` — the true stars in the main star's neighbor circle (the SGM criterion of
            conventions §5, same circle as :func:`jstarid.metrics.scene_outcomes`); ``"all"`` — every true
            detection.
        radius_deg: neighbor-circle radius r (deg) for ``"sgm"``.
        margin_nats: confidence margin (nats); 0 = the MAP ceiling.
        sigma_px: position noise σ per axis (px): a scalar or (B,); needed when ``margin_nats`` > 0.

    Returns:
        (B,) bool; False for a scene without any required star (nothing to name).

    Raises:
        ValueError: unknown ``region``, truths outside ``star_vectors``, or a margin without σ.
    """
    from scipy.optimize import linear_sum_assignment

    if region not in REGIONS:
        raise ValueError(f"unknown region {region!r}; choose one of {REGIONS}")
    if margin_nats > 0 and sigma_px is None:
        raise ValueError("a confidence margin needs sigma_px (the position noise, px)")
    vectors = np.asarray(getattr(star_vectors, "unit_vectors", star_vectors), np.float64)
    truth = np.asarray(scenes.truth)
    if truth.max(initial=-1) >= vectors.shape[0]:
        raise ValueError(f"scene truths reach row {truth.max()}, but only {vectors.shape[0]} star "
                         "vectors were given")
    if region == "sgm":
        required = np.asarray(sgm_required(scenes, camera, radius_deg))
    else:
        required = np.asarray(scenes.valid) & (truth >= 0)
    xy = np.asarray(scenes.xy, np.float64)
    # every detection's true star in pixels (the camera's own projection, the whole batch at once)
    true_vec = np.einsum("bij,bnj->bni", np.asarray(scenes.attitude, np.float64),
                         vectors[np.maximum(truth, 0)])
    stars_xy = np.asarray(camera.project(true_vec)[0], np.float64)  # (B, N, 2)
    met = np.zeros(truth.shape[0], bool)
    if margin_nats > 0:
        two_var = 2.0 * np.broadcast_to(np.asarray(sigma_px, np.float64), truth.shape[:1]) ** 2
    for b in range(truth.shape[0]):
        det = np.nonzero(required[b])[0]
        if det.size == 0:
            continue
        cost = np.sum((xy[b, det][:, None, :] - stars_xy[b, det][None, :, :]) ** 2, axis=-1)  # px²
        rows, cols = linear_sum_assignment(cost)
        # The identity is a MAP choice when no assignment is cheaper (ties, e.g. σ = 0, count as met).
        best = cost[rows, cols].sum()
        met[b] = np.trace(cost) <= best + 1e-9 * max(best, 1.0)
        if met[b] and margin_nats > 0:
            met[b] = _clears_margin(cost, margin_nats * two_var[b])
    return met


def _clears_margin(cost, margin_px2) -> bool:
    """Every detection's best assignment that names it otherwise costs ≥ ``margin_px2`` more."""
    from scipy.optimize import linear_sum_assignment

    n = cost.shape[0]
    if n == 1:
        return True  # a lone star has no alternative among the stars present
    own = np.trace(cost)
    forbid = cost.max() * n + margin_px2 + 1.0  # dearer than any assignment that avoids it
    for i in range(n):
        alt = cost.copy()
        alt[i, i] = forbid
        rows, cols = linear_sum_assignment(alt)
        if alt[rows, cols].sum() - own < margin_px2:
            return False
    return True


def accuracy_bound(ceiling_rate, max_failure_rate: float):
    """Largest accuracy (eq. 9) reachable when failing at most ``max_failure_rate`` of the scenes.

    correct ≤ ceiling · total and answered ≥ (1 − f) · total, so accuracy ≤ ceiling / (1 − f), capped
    at 1.
    """
    if not 0.0 <= max_failure_rate < 1.0:
        raise ValueError(f"max_failure_rate must be in [0, 1), got {max_failure_rate}")
    return np.minimum(1.0, np.asarray(ceiling_rate, np.float64) / (1.0 - max_failure_rate))

