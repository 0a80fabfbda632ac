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
   ``ambiguity_k²`` for isotropic Gaussian noise (RMS s = √2 σ_axis). When another detection lies
   within the window of that rival star, the pair of names is tested jointly as well: keeping
   (this → own star, other → rival) must beat the exchange (this → rival, other → own star) by the
   same margin in summed squared residuals. The joint test catches a close pair whose two detections
   both drifted towards one star (seen at σ = 1.5 px: the detection named after the wrong star of the
   pair sat 0.015° from it, so the single test alone passed).
4. **Scene decision.** The scene fails (``ok`` False, every id −1) when the main star was named and
   is unnamed by the check, when fewer than ``min_matched`` stars stay named, or when fewer than half
   of the named stars stay named (the attitude itself is then not trustworthy).
5. **Frame coverage.** The neighbor circle holds only part of the frame: a small graph (3–5 stars)
   matched to the wrong database graph can fit its own stars within the tolerance (seen twice in
   4,200 noisy scenes, δ just under ε_δ). The attitude must then also explain the rest of the frame:
   of the catalog stars it projects inside the frame (inset by the tolerance), at least
   ``min_coverage`` must have a detection within ``cap_deg`` (the widest tolerance: the fitted one
   is too tight after a fit on 3–4 stars), or the scene fails. On those two
   scenes 11–12 % did; on correct scenes 97–100 % (one missing star, one false star, σ ≤ 3 px).
   Catalog stars are taken from a sky index (:mod:`jstarid.sky_index`) cell of the boresight, which
   holds every star that can be in the frame.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jstarid.attitude import solve_wahba
from jstarid.geometry.angles import angle_between
from jstarid.sky_index import cell_of

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


def _ambiguity_clear(body, ids, valid, ref, c, near, cand, resid, tol, s, amb_k, amb_deg):
    """Step 3: (N,) bool, the named stars whose name clearly beats every close rival catalog star."""
    sep = _angle_deg(ref[:, None, :], cand[None, :, :])  # catalog separation id ↔ candidate
    pred = cand @ c.T  # (n_near, 3) candidates in the camera frame
    d_alt_all = _angle_deg(body[:, None, :], pred[None, :, :])  # (N, n_near)
    window = jnp.maximum(3.0 * tol, amb_deg)
    rival = (near[None, :] != ids[:, None]) & (sep < window)
    d_alt_all = jnp.where(rival, d_alt_all, jnp.inf)
    r = jnp.argmin(d_alt_all, axis=1)  # nearest rival of each detection
    d_alt = jnp.take_along_axis(d_alt_all, r[:, None], axis=1)[:, 0]
    margin = (amb_k * s) ** 2
    single = d_alt ** 2 - resid ** 2 >= margin
    # joint test with the other detection nearest the rival (within the window)
    n = body.shape[0]
    d_other = _angle_deg(pred[r][:, None, :], body[None, :, :])  # (N, N): rival of i ↔ detection j
    d_other = jnp.where(valid[None, :] & ~jnp.eye(n, dtype=bool), d_other, jnp.inf)
    j = jnp.argmin(d_other, axis=1)
    d_j_rival = jnp.take_along_axis(d_other, j[:, None], axis=1)[:, 0]
    d_j_own = _angle_deg(body[j], ref @ c.T)  # detection j against i's own star
    joint = (d_alt ** 2 + d_j_own ** 2) - (resid ** 2 + d_j_rival ** 2) >= margin
    has_rival = jnp.isfinite(d_alt)
    return ~has_rival | (single & (joint | ~(d_j_rival <= window)))


def _frame_coverage(c, body, valid, cat, cells, tol, *, camera, grid):
    """Step 5: catalog stars the attitude puts inside the frame, and how many have a detection.

    Returns:
        ``(hits, expected)``: () int32 each.
    """
    loc = cells[cell_of(c[2], grid)]  # c[2] = Cᵀ ẑ: the boresight (ICRS)
    real = loc < cat.shape[0]
    vec = jnp.where(real[:, None], cat[jnp.minimum(loc, cat.shape[0] - 1)], -c[2][None, :])
    pred = vec @ c.T  # (K, 3) camera frame
    xy, in_field = camera.project(pred)
    tol_px = jnp.tan(jnp.radians(tol)) * camera.f_px
    expected = real & in_field & camera.contains(xy, tol_px)
    d = _angle_deg(pred[:, None, :], body[None, :, :])  # (K, N)
    hit = expected & jnp.any(valid[None, :] & (d <= tol), axis=1)
    return jnp.sum(hit), jnp.sum(expected)


def _verify_one(cat, cells, body, valid, ids, ok, main, *, camera, grid, k, floor_deg, cap_deg,
                amb_k, amb_deg, min_matched, min_coverage, n_near):
    """One scene. cat (M, 3), cells (C, K), body (N, 3), valid/ids (N,), ok, main () → (ids, ok)."""
    named0 = (ids >= 0) & ok
    ref = cat[jnp.clip(ids, 0, cat.shape[0] - 1)]
    _, resid, _, tol = _fit(body, ref, named0, k, floor_deg, cap_deg)
    inl = named0 & (resid <= tol)
    c, resid, s, tol = _fit(body, ref, inl, k, floor_deg, cap_deg)
    keep = named0 & (resid <= tol)
    # ambiguity guard: catalog stars near the main star's sky direction (fixed count)
    sky_main = body[main] @ c  # Cᵀ b, ICRS
    _, near = jax.lax.top_k(cat @ sky_main, n_near)
    keep &= _ambiguity_clear(body, ids, valid, ref, c, near, cat[near], resid, tol, s, amb_k,
                             amb_deg)
    # the widest tolerance: the fitted one can be tight (a 3-star fit leaves tiny residuals) while
    # a wrong attitude meets a detection within 0.3° by chance for only ≈ 3 % of catalog stars
    hits, expected = _frame_coverage(c, body, valid, cat, cells, cap_deg, camera=camera,
                                     grid=grid)
    n0, n1 = jnp.sum(named0), jnp.sum(keep)
    ok_new = (ok & (n1 >= min_matched) & (2 * n1 >= n0) & (keep[main] | ~named0[main])
              & (hits >= min_coverage * expected))
    return jnp.where(keep & ok_new, ids, -1), ok_new


@functools.partial(jax.jit, static_argnames=("camera", "grid", "k", "floor_deg", "cap_deg", "amb_k",
                                             "amb_deg", "min_matched", "min_coverage", "n_near"))
def verify_ids(cat, cells, xy, valid, ids, ok, main, *, camera, grid: int, k: float,
               floor_deg: float, cap_deg: float, amb_k: float, amb_deg: float, min_matched: int,
               min_coverage: float, n_near: int):
    """Verify a batch of SGM identifications against the attitude of the named stars (module doc).

    Args:
        cat: (M, 3) catalog ICRS unit vectors (rows as in ``ids``).
        cells: (6·G·G, K) int32 sky-index lists of catalog rows (padding ``M``) covering the frame
            of any boresight in the cell (:func:`~jstarid.sky_index.build_sky_index`).
        xy: (B, N, 2) centroids (px). valid: (B, N) bool.
        ids: (B, N) int32 catalog rows, −1 unnamed. ok: (B,) bool. main: (B,) int32 main detection.
        camera: static :class:`~jstarid.camera.Camera`. grid: G of the sky index.
        k: tolerance in robust RMS units. floor_deg, cap_deg: bounds on the tolerance (deg).
        amb_k: ambiguity margin in robust RMS units. amb_deg: smallest ambiguity window (deg).
        min_matched: fewest stars a verified scene keeps.
        min_coverage: fewest of the catalog stars projected inside the frame that must have a
            detection within the tolerance (fraction; 0 = off).
        n_near: static count of catalog stars (nearest the main star) searched for rivals; must
            cover the neighbor circle plus the window.

    Returns:
        ``(ids, ok)``: (B, N) int32 verified ids (−1 for unnamed, whole row −1 where not ok), (B,) bool.
    """
    body = camera.unproject(xy)
    ids = jnp.where(valid, ids, -1)
    fn = functools.partial(_verify_one, camera=camera, grid=grid, k=k, floor_deg=floor_deg,
                           cap_deg=cap_deg, amb_k=amb_k, amb_deg=amb_deg, min_matched=min_matched,
                           min_coverage=min_coverage, n_near=n_near)
    return jax.vmap(fn, in_axes=(None, None, 0, 0, 0, 0, 0))(cat, cells, body, valid, ids, ok, main)
