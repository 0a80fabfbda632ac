"""The false-match probability of a solution: could a wrong attitude have matched this many stars?

A solution names n of a scene's N detections, each within some radius r of its catalog star. Under
the null hypothesis the attitude is wrong, and the sky behind each detection is a random patch of
the catalog (local density ρ stars/sr near the boresight). Two matched detections fix an attitude,
so the evidence is the other n − 2 (tetra3's mismatch probability makes the same count): each of the
other N − 2 detections lands within r of some catalog star with probability

    q = 1 − exp(−ρ π r²),

and the chance that a given wrong attitude confirms at least n − 2 of them is the binomial tail

    P₁ = P[Binomial(N − 2, q) ≥ n − 2].

A lost-in-space search tries many attitudes, so P₁ is multiplied by the number of attitudes a
blind search over pairs could have tried (a union bound, as astrometry.net's odds threshold allows
for its many hypotheses): every pair of detections (i, j) at angle θᵢⱼ matched, in both orders, to
every catalog pair whose separation is within δ = 2r of θᵢⱼ. On a catalog of M stars spread at its
mean density that is M² δ sin θᵢⱼ attitudes per detection pair, so

    H = M² δ Σ_{i<j} sin θᵢⱼ,    P = min(1, H · P₁).

The radius r is the largest angle between a named detection and its star under the solution's
attitude (and fitted focal length and k1, where the finishing stage fitted them), but at least
:data:`MIN_RADIUS_PX`: a perfect fit does not make a coincidence impossible. The union bound makes
P an upper bound: among solutions claimed at probability p, at most a fraction p should be wrong
(``tests/test_false_match.py`` checks this on random points and clutter).

``false_match_log10`` is the jit-compiled kernel (batched with ``vmap``); :func:`false_match_probability`
is its host wrapper, and :func:`of_solutions` the probability a sweep reports: the one that decided a
claim (``Identification.false_match``, set by the finishing stage) or, for an algorithm without the
stage, that of its names.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.attitude import estimate_attitude
from jstarid.camera_fit import unproject_scaled
from jstarid.geometry.angles import angle_between, pairwise_angles
from jstarid.geometry.precise import small_matmul

__all__ = ["CALIBRATION_THRESHOLDS", "MIN_RADIUS_PX", "SMALLEST_P", "WRONG_ATTITUDE_PX", "calibrated",
           "false_match_log10", "false_match_probability", "of_solutions", "with_names_attitude"]

MIN_RADIUS_PX = 1.0  # the match radius is never taken below this (px)
CALIBRATION_THRESHOLDS = (1e-9, 1e-6, 1e-3, 1e-2, 0.1)  # the t at which :func:`calibrated` checks
WRONG_ATTITUDE_PX = 10.0  # a claim whose boresight is farther than this from the truth is a wrong attitude
SMALLEST_P = float(np.finfo(np.float32).tiny)  # P is kept as float32: a smaller P reads as this, not 0
DENSITY_GROUP = 64  # scenes per lax.map step of the local-density count (a (group, M) product)


def false_match_probability(scenes, result, star_vectors, camera) -> np.ndarray:
    """The false-match probability of each scene's solution (module docstring).

    Args:
        scenes: (B, N) :class:`~jstarid.scene.Scene` the solution names (pinhole centroids, px).
        result: its :class:`~jstarid.scene.Identification`; ``attitude`` is required, and
            ``focal_scale`` / ``distortion_k1`` are used where present and finite.
        star_vectors: (M, 3) ICRS unit vectors of the catalog rows ``result.ids`` name.
        camera: the nominal :class:`~jstarid.camera.Camera` (pinhole).

    Returns:
        (B,) float64 NumPy in (0, 1]; 1 for scenes not claimed, without an attitude, or with fewer
        than three names.
    """
    if result.attitude is None:
        return np.ones(scenes.batch_size)
    b = scenes.batch_size
    scale = np.ones(b) if result.focal_scale is None else np.asarray(result.focal_scale, np.float64)
    k1 = np.zeros(b) if result.distortion_k1 is None else np.asarray(result.distortion_k1, np.float64)
    scale = np.where(np.isfinite(scale), scale, 1.0).astype(np.float32)
    k1 = np.where(np.isfinite(k1), k1, 0.0).astype(np.float32)
    attitude = np.asarray(result.attitude, np.float32)
    attitude = np.where(np.isfinite(attitude), attitude, np.eye(3, dtype=np.float32))
    log10 = false_match_log10(scenes.xy, scenes.valid, result.ids, result.ok, attitude, scale, k1,
                              jnp.asarray(star_vectors, jnp.float32), camera=camera,
                              half_diagonal=camera.half_diagonal_rad)
    return np.power(10.0, np.asarray(log10, np.float64))


def of_solutions(scenes, result, catalog, camera) -> np.ndarray:
    """The false-match probability of each claim, as a sweep reports it.

    Args:
        scenes: (B, N) :class:`~jstarid.scene.Scene` the solutions name.
        result: their :class:`~jstarid.scene.Identification`.
        catalog: the rows ``result.ids`` name (``unit_vectors``; a :class:`~jstarid.catalog.Catalog`).
        camera: the nominal :class:`~jstarid.camera.Camera`.

    Returns:
        (B,) float64 NumPy: ``result.false_match`` where the algorithm gives it (the probability
        that decided ``ok``: :func:`jstarid.finishing.confirmed_by_the_frame`), else that of its
        names (:func:`false_match_probability`, under the names' Wahba attitude where it gives
        none); 1 where not claimed; at least :data:`SMALLEST_P`.
    """
    ok = np.asarray(result.ok)
    if result.false_match is not None:
        return np.where(ok, np.maximum(np.asarray(result.false_match, np.float64), SMALLEST_P), 1.0)
    located = with_names_attitude(result, scenes, catalog, camera)
    return np.maximum(false_match_probability(scenes, located, catalog.unit_vectors, camera), SMALLEST_P)


def calibrated(p, claimed, wrong, thresholds=CALIBRATION_THRESHOLDS) -> bool:
    """Whether wrong claims are at most a share t of the claims at P ≤ t, for every threshold t.

    Args:
        p: (S,) false-match probability of each scene's claim (NaN counts as claimed at every t: it
            must not pass for calibrated).
        claimed: (S,) bool, the scenes claimed.
        wrong: (S,) bool, the claims that are wrong: a wrong attitude (P speaks of the attitude; a
            sweep's boresight over :data:`WRONG_ATTITUDE_PX` off), or any wrong name where no true
            attitude is known (stricter: a labelled file, ``jstarid score``).
        thresholds: the t checked.
    """
    p, claimed, wrong = np.asarray(p, np.float64), np.asarray(claimed, bool), np.asarray(wrong, bool)
    below = [claimed & ~(p > t) for t in thresholds]
    return all(np.sum(wrong & b) <= t * max(np.sum(b), 1) for t, b in zip(thresholds, below, strict=True))


def with_names_attitude(result, scenes, catalog, camera):
    """``result`` with the Wahba attitude of its names (:func:`jstarid.attitude.estimate_attitude`)
    where it gives none (``None``, or NaN for a claimed scene); NaN where not claimed or named too
    few. ``result`` itself where every claim has an attitude."""
    ok = np.asarray(result.ok)
    given = None if result.attitude is None else np.asarray(result.attitude, np.float32)
    missing = ok if given is None else ok & ~np.isfinite(given).all(axis=(1, 2))
    if not missing.any() and given is not None:
        return result
    attitude, _, have = estimate_attitude(catalog, camera, scenes, result)
    names = np.where((np.asarray(have) & ok)[:, None, None], np.asarray(attitude, np.float32), np.nan)
    merged = names if given is None else np.where(missing[:, None, None], names, given)
    return dataclasses.replace(result, attitude=jax.device_put(merged.astype(np.float32)))


@functools.partial(jax.jit, static_argnames=("camera", "half_diagonal"))
def false_match_log10(xy, valid, ids, ok, attitude, scale, k1, star_vectors, *, camera, half_diagonal):
    """log10 of the false-match probability, (B,) float32 (arguments as in
    :func:`false_match_probability`; ``scale``, ``k1`` (B,) finite; ``half_diagonal`` rad)."""
    m = star_vectors.shape[0]
    cos_field = math.cos(half_diagonal)
    cone_sr = 2.0 * math.pi * (1.0 - cos_field)

    def local_count(att):  # catalog stars within the field's circumscribed cone about the boresight
        return jnp.sum(small_matmul(star_vectors, att[2][:, None])[:, 0] >= cos_field, dtype=jnp.float32)

    counts = jax.lax.map(local_count, attitude, batch_size=DENSITY_GROUP)
    density = jnp.maximum(counts / cone_sr, m / (4.0 * math.pi))  # stars/sr, at least the mean
    per_scene = functools.partial(_scene_log10, star_vectors=star_vectors, camera=camera, n_catalog=m)
    return jax.vmap(per_scene)(xy, valid, ids, ok, attitude, scale, k1, density)


def _scene_log10(xy, valid, ids, ok, att, scale, k1, density, *, star_vectors, camera, n_catalog):
    """One scene's log10 P (module docstring's P = min(1, H · P₁))."""
    rays = unproject_scaled(camera, xy, scale, k1)  # (N, 3) camera frame
    named = valid & (ids >= 0)
    stars_cam = small_matmul(star_vectors[jnp.maximum(ids, 0)], att.T)  # v_cam = C r
    residual = jnp.where(named, angle_between(rays, stars_cam), 0.0)  # exact at sub-pixel angles
    radius = jnp.maximum(jnp.max(residual), MIN_RADIUS_PX / (camera.f_px * scale))
    crowd = density * math.pi * radius**2  # expected stars within r: q = 1 − e^(−crowd)
    log_q, log_not_q = jnp.log(-jnp.expm1(-crowd)), -crowd  # finite even where q rounds to 1

    # P₁: at least n − 2 of the N − 2 detections beyond the attitude's two land within r of a star
    trials = jnp.sum(valid, dtype=jnp.float32) - 2.0
    n_named = jnp.sum(named, dtype=jnp.float32)
    k = jnp.arange(xy.shape[0] + 1, dtype=jnp.float32)
    log_pmf = (jax.lax.lgamma(trials + 1.0) - jax.lax.lgamma(k + 1.0)
               - jax.lax.lgamma(jnp.maximum(trials - k, 0.0) + 1.0)
               + k * log_q + (trials - k) * log_not_q)
    log_tail = jax.nn.logsumexp(jnp.where((k >= n_named - 2.0) & (k <= trials), log_pmf, -jnp.inf))

    # H: attitudes from every detection pair matched to every catalog pair within δ = 2r
    sin_pair = jnp.sin(pairwise_angles(rays))
    pair = valid[:, None] & valid[None, :] & jnp.triu(jnp.ones(sin_pair.shape, bool), 1)
    sin_sum = jnp.sum(jnp.where(pair, sin_pair, 0.0))
    log_hypotheses = (2.0 * math.log(n_catalog) + jnp.log(2.0 * radius)
                      + jnp.log(jnp.maximum(sin_sum, 1e-30)))
    log_p = jnp.minimum(0.0, log_hypotheses + log_tail) / math.log(10.0)
    return jnp.where(ok & (n_named >= 3), log_p, 0.0)
