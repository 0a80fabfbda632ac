"""Outcomes and rates of docs/conventions.md §5.

Per scene: ``n_correct`` (ids == truth ≥ 0), ``n_wrong`` (an id given to a false star or to a star not
in the catalog, or an id ≠ truth) and ``n_identified``. The scene outcome is

- ``CORRECT``: ``ok``, ``n_wrong == 0`` and the criterion holds;
- ``WRONG`` (mis-identification): ``ok`` and ``n_wrong > 0``;
- ``FAIL``: not ``ok``;
- ``INCOMPLETE``: ``ok``, nothing wrong, but the criterion does not hold (e.g. only two stars named
  under the strict criterion). It counts against the identification rate, not as a failure.

Criteria (docs/conventions.md §5):

- ``"strict"`` and ``"mlv"``: ≥ 3 correct and none wrong;
- ``"sgm"``: every true star inside the neighbor circle (radius r, default 6°) of the main star — the
  detection nearest the principal point — is identified correctly (You et al. 2022);
- ``"rpnet"``: the main (guide) star — the detection nearest the principal point — is correct when it
  is a catalog star, at least one star is correct, and none is wrong (Xu et al. 2019).

Rates: identification = correct / total; accuracy (SGM eq. 9) = correct / (total − fail); failure =
fail / total; misid = wrong / total.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.attitude import attitude_errors_arcsec
from jstarid.runtime.padding import call_padded
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Identification, Scene

__all__ = ["CORRECT", "WRONG", "FAIL", "INCOMPLETE", "OUTCOME_NAMES", "CRITERIA", "scene_outcomes",
           "evaluate", "main_star_index", "nearest_to_principal_point", "in_neighbor_circle", "sgm_required",
           "wilson_interval"]

CORRECT, WRONG, FAIL, INCOMPLETE = 0, 1, 2, 3
#: Each outcome code's name, as tables and result files spell it.
OUTCOME_NAMES = {CORRECT: "correct", WRONG: "wrong", FAIL: "fail", INCOMPLETE: "incomplete"}
CRITERIA = ("strict", "mlv", "sgm", "rpnet")


def _principal_point_d2(xy, valid, camera):
    """(..., N) squared distance (px²) of each detection to (cx, cy); +inf where not valid."""
    centre = jnp.array([camera.cx, camera.cy], xy.dtype).reshape((1,) * (xy.ndim - 1) + (2,))
    return jnp.where(valid, jnp.sum((xy - centre) ** 2, axis=-1), jnp.inf)


def nearest_to_principal_point(xy, valid, camera):
    """(...,) index of the valid detection nearest (cx, cy) among xy (..., N, 2) (0 if none valid).

    This is the "main star" of SGM and the guide star of RpNet; algorithms and metrics share it so
    both name the same detection.
    """
    return jnp.argmin(_principal_point_d2(xy, valid, camera), axis=-1)


def by_distance_to_principal_point(xy, valid, camera):
    """(..., N) detection indices, nearest (cx, cy) first (ties to the lower index, as
    :func:`nearest_to_principal_point`), the invalid ones last."""
    return jnp.argsort(_principal_point_d2(xy, valid, camera), axis=-1, stable=True)


def main_star_index(scenes: Scene, camera):
    """(B,) index of the valid detection nearest the principal point (0 for an empty scene)."""
    return nearest_to_principal_point(scenes.xy, scenes.valid, camera)


def in_neighbor_circle(scenes: Scene, camera, radius_deg: float = 6.0):
    """(B, N) bool: valid detections whose (noisy) centroid lies within ``radius_deg`` of the main
    star's centroid — the SGM neighbor circle (You et al. 2022), the main star included."""
    rows = jnp.arange(scenes.truth.shape[0])
    main = main_star_index(scenes, camera)
    v = camera.unproject(scenes.xy)  # (B, N, 3)
    cosang = jnp.sum(v * v[rows, main][:, None, :], -1)
    return scenes.valid & (cosang >= math.cos(math.radians(radius_deg)))


def sgm_required(scenes: Scene, camera, radius_deg: float = 6.0):
    """(B, N) bool: the true stars the SGM criterion asks for (catalog stars in the neighbor circle)."""
    return in_neighbor_circle(scenes, camera, radius_deg) & (scenes.truth >= 0)


def scene_outcomes(scenes: Scene, result: Identification, criterion: str = "strict", *,
                   camera=None, radius_deg: float = 6.0) -> dict[str, jax.Array]:
    """Per-scene counts and outcome codes.

    Args:
        scenes: (B, N) scenes with truth.
        result: (B, N) identification.
        criterion: one of :data:`CRITERIA`.
        camera: required for ``"sgm"`` and ``"rpnet"`` (main star and neighbor circle).
        radius_deg: SGM neighbor-circle radius r (deg).

    Returns:
        dict of (B,) arrays: ``n_correct``, ``n_wrong``, ``n_identified`` (int32), ``outcome`` (int32
        code), ``criterion_met`` (bool).

    Raises:
        ValueError: unknown criterion, missing camera, or mismatched shapes.
    """
    if criterion not in CRITERIA:
        raise ValueError(f"unknown criterion {criterion!r}; choose one of {CRITERIA}")
    if criterion in ("sgm", "rpnet") and camera is None:
        raise ValueError(f"criterion {criterion!r} needs the camera (to find the main star)")
    if result.ids.shape != scenes.truth.shape or result.ok.shape != scenes.overflow.shape:
        raise ValueError(f"result shapes {result.ids.shape}/{result.ok.shape} do not match the scenes "
                         f"{scenes.truth.shape}/{scenes.overflow.shape}")
    # at a padded batch: one program for every batch size of a bucket (padding scenes are empty)
    return call_padded(_outcomes, (scenes, result.ids, result.ok), criterion, camera, float(radius_deg))


@functools.partial(stored_jit, static_argnames=("criterion", "camera", "radius_deg"))
def _outcomes(scenes, ids, ok, criterion, camera, radius_deg):
    ided = scenes.valid & (ids >= 0)
    correct = ided & (ids == scenes.truth) & (scenes.truth >= 0)
    wrong = ided & ~correct
    n_correct = jnp.sum(correct, -1, dtype=jnp.int32)
    n_wrong = jnp.sum(wrong, -1, dtype=jnp.int32)
    n_ided = jnp.sum(ided, -1, dtype=jnp.int32)
    if criterion in ("strict", "mlv"):
        met = n_correct >= 3
    else:
        main = main_star_index(scenes, camera)
        rows = jnp.arange(scenes.truth.shape[0])
        main_true = scenes.valid[rows, main] & (scenes.truth[rows, main] >= 0)
        main_ok = ~main_true | correct[rows, main]
        if criterion == "sgm":
            required = sgm_required(scenes, camera, radius_deg)
            met = jnp.all(~required | correct, -1) & main_ok & (n_correct >= 1)
        else:  # rpnet
            met = main_ok & (n_correct >= 1)
    outcome = jnp.where(~ok, FAIL, jnp.where(n_wrong > 0, WRONG, jnp.where(met, CORRECT, INCOMPLETE)))
    return {"n_correct": n_correct, "n_wrong": n_wrong, "n_identified": n_ided,
            "outcome": outcome.astype(jnp.int32), "criterion_met": met}


def evaluate(scenes: Scene, result: Identification, criterion: str = "strict", *, camera=None,
             radius_deg: float = 6.0) -> dict[str, float]:
    """Rates over a batch (conventions §5), plus attitude error statistics when ``result.attitude`` is set.

    Returns:
        dict with ``n_scenes``, ``n_correct``, ``n_wrong``, ``n_fail``, ``n_incomplete`` (scene
        counts), ``identification_rate``, ``accuracy`` (SGM eq. 9; NaN when every scene failed),
        ``failure_rate``, ``misid_rate``, ``incomplete_rate``, ``mean_identified`` (stars per scene),
        ``overflow_rate``, and, with attitudes, ``boresight_err_arcsec_{mean,median,p95,max}`` and
        ``roll_err_arcsec_{mean,median,p95,max}`` over the correct scenes.
    """
    out = scene_outcomes(scenes, result, criterion, camera=camera, radius_deg=radius_deg)
    code = np.asarray(out["outcome"])
    total = code.size
    counts = {name: int(np.sum(code == c)) for name, c in
              (("n_correct", CORRECT), ("n_wrong", WRONG), ("n_fail", FAIL),
               ("n_incomplete", INCOMPLETE))}
    answered = total - counts["n_fail"]
    report: dict[str, float] = {"criterion": criterion, "n_scenes": total, **counts}
    report.update(
        identification_rate=counts["n_correct"] / max(total, 1),
        accuracy=counts["n_correct"] / answered if answered else float("nan"),
        failure_rate=counts["n_fail"] / max(total, 1),
        misid_rate=counts["n_wrong"] / max(total, 1),
        incomplete_rate=counts["n_incomplete"] / max(total, 1),
        mean_identified=float(np.mean(np.asarray(out["n_identified"]))) if total else float("nan"),
        overflow_rate=float(np.mean(np.asarray(scenes.overflow))) if total else float("nan"),
    )
    if result.attitude is not None:
        bore, roll = attitude_errors_arcsec(result.attitude, scenes.attitude)
        use = (code == CORRECT) & np.isfinite(np.asarray(bore)) & np.isfinite(np.asarray(roll))
        for name, err in (("boresight", np.asarray(bore)[use]), ("roll", np.asarray(roll)[use])):
            stats = ((np.mean, "mean"), (np.median, "median"),
                     (lambda a: np.percentile(a, 95), "p95"), (np.max, "max"))
            for fn, label in stats:
                report[f"{name}_err_arcsec_{label}"] = float(fn(err)) if err.size else float("nan")
    return report


def wilson_interval(k, n, z: float = 1.96) -> tuple[np.ndarray, np.ndarray]:
    """Wilson score interval of a binomial rate k / n (Wilson 1927; z = 1.96: 95 %).

    Unlike the normal approximation it stays inside [0, 1] and is not empty at k = 0 or k = n, which
    is where identification (≈ 1) and mis-identification (≈ 0) rates live: 0 wrong in 200 scenes
    gives [0, 1.9 %].

    Args:
        k: successes (scalar or array). n: trials (same shape; 0 gives NaN bounds).
        z: standard-normal quantile of the two-sided level.

    Returns:
        ``(low, high)`` float64 arrays of k's shape.
    """
    k, n = np.asarray(k, np.float64), np.asarray(n, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = k / n
        denom = 1.0 + z * z / n
        centre = (p + z * z / (2 * n)) / denom
        half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
        return np.clip(centre - half, 0.0, 1.0), np.clip(centre + half, 0.0, 1.0)
