"""Post-match verification of SGM identifications — our addition, not in You et al. (2022).

The spectral match names every vertex pair that greedy binarization produces. Under position noise
two failure modes survive Algorithm 1's error threshold: stars of a close pair (0.1–0.2° apart) are
swapped, and stars near the neighbor-circle boundary are paired with a leftover database vertex. Both
give a mis-identification, and the project prefers a failure. The step below, run per scene (vmapped,
fixed shapes, masks), checks every named detection against the attitude of the others:

1. **Attitude fit.** ``C`` by Wahba (SVD) from the named detections; residual ``d_own`` = angle between
   each detection and ``C r_id`` (deg, via atan2 of cross and dot, accurate near 0 in float32).
2. **Noise-tied tolerance.** Robust RMS ``s = 1.2 · median(d_own)`` (for a 2-D Gaussian the residual
   is Rayleigh: median = 1.177 σ_axis, RMS = 1.414 σ_axis, ratio 1.20), clipped so that
   ``tol = k · s`` lies in ``[floor_deg, cap_deg]``; named detections with ``d_own > tol`` are
   unnamed, the attitude is refitted from the rest and the test repeated once (a detection unnamed
   in the first pass may come back). For a Rayleigh residual P(d > k·RMS) = exp(−k²): k = 3.5 unnames
   a true star with probability 5·10⁻⁶.
3. **Ambiguity guard.** A named star with another catalog star within ``max(3·tol, ambiguity_deg)``
   of it (a close pair the match may have swapped) keeps its name only when its own residual clearly
   beats the alternative's: ``d_alt² − d_own² ≥ (ambiguity_k · s)²`` — a log likelihood ratio of
   ``ambiguity_k²`` for isotropic Gaussian noise (RMS s = √2 σ_axis).
4. **Scene decision.** The scene fails (``ok`` False, every id −1) when the main star was named and
   is unnamed by the check, when fewer than ``min_matched`` stars stay named, or when fewer than half
   of the named stars stay named (the attitude itself is then not trustworthy).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jstarid.attitude import solve_wahba
from jstarid.geometry.angles import angle_between

__all__ = ["verify_ids"]

_RMS_PER_MEDIAN = 1.2011  # sqrt(2) / sqrt(2 ln 2): Rayleigh RMS / median


def _angle_deg(a, b):
    """Angle (deg) between unit vectors a (..., 3) and b (..., 3), accurate for small angles."""
    return jnp.degrees(angle_between(a, b))


def _masked_median(x, mask):
    """Lower median of x (N,) over mask (N,) bool (inf when the mask is empty)."""
    srt = jnp.sort(jnp.where(mask, x, jnp.inf))
    n = jnp.sum(mask)
    return srt[jnp.clip((n - 1) // 2, 0, x.shape[0] - 1)]


def _fit(body, ref, named, k, floor_deg, cap_deg):
    """Attitude, residuals (deg), robust RMS s (deg) and tolerance (deg) from the named pairs."""
    c = solve_wahba(body, ref, named.astype(body.dtype))
    resid = _angle_deg(body, ref @ c.T)
    s = jnp.clip(_RMS_PER_MEDIAN * _masked_median(resid, named), floor_deg / k, cap_deg / k)
    return c, resid, s, k * s


def _verify_one(cat, body, ids, ok, main, *, k, floor_deg, cap_deg, amb_k, amb_deg, min_matched,
                n_near):
    """One scene. cat (M, 3), body (N, 3), ids (N,), ok (), main () → (ids (N,), ok ())."""
    named0 = (ids >= 0) & ok
    ref = cat[jnp.clip(ids, 0, cat.shape[0] - 1)]
    _, resid, _, tol = _fit(body, ref, named0, k, floor_deg, cap_deg)
    inl = named0 & (resid <= tol)
    c, resid, s, tol = _fit(body, ref, inl, k, floor_deg, cap_deg)
    keep = named0 & (resid <= tol)
    # ambiguity guard: catalog stars near the main star's sky direction (fixed count)
    sky_main = body[main] @ c  # Cᵀ b, ICRS
    _, near = jax.lax.top_k(cat @ sky_main, n_near)
    cand = cat[near]  # (n_near, 3)
    sep = _angle_deg(ref[:, None, :], cand[None, :, :])  # catalog separation id ↔ candidate
    d_alt = _angle_deg(body[:, None, :], (cand @ c.T)[None, :, :])  # (N, n_near)
    window = jnp.maximum(3.0 * tol, amb_deg)
    rival = (near[None, :] != ids[:, None]) & (sep < window)
    d_alt = jnp.min(jnp.where(rival, d_alt, jnp.inf), axis=1)
    clear = d_alt ** 2 - resid ** 2 >= (amb_k * s) ** 2
    keep &= clear
    n0, n1 = jnp.sum(named0), jnp.sum(keep)
    ok_new = ok & (n1 >= min_matched) & (2 * n1 >= n0) & (keep[main] | ~named0[main])
    return jnp.where(keep & ok_new, ids, -1), ok_new


@functools.partial(jax.jit, static_argnames=("camera", "k", "floor_deg", "cap_deg", "amb_k",
                                             "amb_deg", "min_matched", "n_near"))
def verify_ids(cat, xy, valid, ids, ok, main, *, camera, k: float, floor_deg: float, cap_deg: float,
               amb_k: float, amb_deg: float, min_matched: int, n_near: int):
    """Verify a batch of SGM identifications against the attitude of the named stars (module doc).

    Args:
        cat: (M, 3) catalog ICRS unit vectors (rows as in ``ids``).
        xy: (B, N, 2) centroids (px). valid: (B, N) bool.
        ids: (B, N) int32 catalog rows, −1 unnamed. ok: (B,) bool. main: (B,) int32 main detection.
        camera: static :class:`~jstarid.camera.Camera`.
        k: tolerance in robust RMS units. floor_deg, cap_deg: bounds on the tolerance (deg).
        amb_k: ambiguity margin in robust RMS units. amb_deg: smallest ambiguity window (deg).
        min_matched: fewest stars a verified scene keeps. n_near: static count of catalog stars
            (nearest the main star) searched for rivals; must cover the neighbor circle plus the window.

    Returns:
        ``(ids, ok)``: (B, N) int32 verified ids (−1 for unnamed, whole row −1 where not ok), (B,) bool.
    """
    body = camera.unproject(xy)
    ids = jnp.where(valid, ids, -1)
    fn = functools.partial(_verify_one, k=k, floor_deg=floor_deg, cap_deg=cap_deg, amb_k=amb_k,
                           amb_deg=amb_deg, min_matched=min_matched, n_near=n_near)
    return jax.vmap(fn, in_axes=(None, 0, 0, 0, 0))(cat, body, ids, ok, main)
