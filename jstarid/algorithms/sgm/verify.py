"""Post-match verification of SGM identifications — our addition, not in You et al. (2022).

Under position noise two failure modes survive Algorithm 1's threshold: the stars of a close pair
(0.1–0.2° apart) are swapped, and stars near the circle boundary are paired with a leftover database
vertex. A failure is preferred to a mis-identification, so each scene (vmapped, fixed shapes) checks
every named detection against the attitude of the others:

1. **Attitude fit.** ``C`` by Wahba (SVD) from the named detections; residual ``d_own`` = angle
   between each detection and ``C r_id`` (deg, atan2 of cross and dot: accurate near 0 in float32).
2. **Noise-tied tolerance.** ``s = 1.2 · median(d_own)`` (Rayleigh RMS / median), ``tol = k · s``
   clipped to ``[floor_deg, cap_deg]``; detections with ``d_own > tol`` are unnamed, the attitude
   refitted and the test repeated once (an unnamed one may come back). P(d > k·RMS) = exp(−k²).
3. **Ambiguity guard.** A named star with rival catalog stars within ``max(3·tol, ambiguity_deg)``
   keeps its name only when ``d_alt² − d_own² ≥ (ambiguity_k · s)²`` for each (a log likelihood
   ratio of ``ambiguity_k²`` for isotropic Gaussian noise, s = √2 σ_axis), and, where another
   detection lies in a rival's window, when the present names beat the exchange (this → rival,
   other → own star) by the same margin in summed squared residuals. *Partner rule*
   (``partner_joint``): when the rival has a detection of its own (within the tolerance, nearest to
   the rival among catalog stars, named after it or unnamed), the joint test alone with the wider
   margin ``partner_k²`` also clears the name (docs/design/sgm.md). With ``mag_sigma`` > 0 both tests
   add ``(m_obs − V)² / (2 σ_m²)`` per hypothesis. Margins use a high-side s (:func:`_upper_rms`).
   Last, an unnamed detection whose nearest catalog star is this one's own star must lose to it by
   the same margin.
4. **Scene decision.** The scene fails (``ok`` False, every id −1) when the named main star is
   unnamed, when fewer than ``min_matched`` stars or than half of the named stars stay named.
5. **Frame coverage.** A wrong small-graph match (3–5 stars, δ just under ε_δ) can fit its own
   stars, so at least ``min_coverage`` of the catalog stars the attitude projects inside the frame
   (inset by ``cap_deg``; :mod:`jstarid.sky_index` cell of the boresight) need a detection within
   ``cap_deg`` (the fitted tolerance is too tight after a 3–4-star fit), or the scene fails.

The caller (``Config.verify.rename``) names the detections left unnamed from the verified attitude
and runs the step again, so a wrongly paired detection can get its right name.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jstarid.attitude import solve_wahba
from jstarid.geometry import precise
from jstarid.geometry.angles import angle_between
from jstarid.robust import masked_median
from jstarid.runtime.program_store import stored_jit
from jstarid.sky_index import local_stars

__all__ = ["verify_ids"]

_RMS_PER_MEDIAN = 1.2011  # sqrt(2) / sqrt(2 ln 2): Rayleigh RMS / median


def _angle_deg(a, b):
    """Angle (deg) between unit vectors a (..., 3) and b (..., 3), accurate for small angles."""
    return jnp.degrees(angle_between(a, b))


def _fit(body, ref, named, k, floor_deg, cap_deg):
    """Attitude, residuals (deg), robust RMS s (deg) and tolerance (deg) from the named pairs."""
    c = solve_wahba(body, ref, named.astype(body.dtype))
    resid = _angle_deg(body, precise.matmul(ref, c.T))
    s = jnp.clip(_RMS_PER_MEDIAN * masked_median(resid, named, lower=True), floor_deg / k, cap_deg / k)
    return c, resid, s, k * s


def _upper_rms(resid, mask, z: float):
    """High-side residual RMS s (deg) for the ambiguity margins (step 3).

    With n stars and a 3-parameter attitude, Σ d² ~ (s²/2) χ²_ν, ν = 2n − 3. Dividing by the lower
    z-quantile of χ²_ν (Wilson–Hilferty) instead of its mean gives an s too small only with probability
    Φ(−z) (16 % at z = 1). Why: an s low by chance inflates every log likelihood ratio by 1/s².
    """
    n = jnp.sum(mask)
    nu = jnp.maximum(2.0 * n - 3.0, 1.0)
    c = 2.0 / (9.0 * nu)
    q = nu * jnp.maximum(1.0 - c - z * jnp.sqrt(c), 0.05) ** 3
    return jnp.sqrt(2.0 * jnp.sum(jnp.where(mask, resid ** 2, 0.0)) / q)


def _two_nearest(d):
    """Column and value of the two smallest entries of each row of d (R, N), lowest column first on
    ties: ``lax.top_k(−d, 2)`` as two ``argmin`` passes (much cheaper on a CPU; docs/design/sgm.md).

    Returns:
        ``(first, d_first, second, d_second)``: (R,) int32, (R,) float, (R,) int32, (R,) float.
    """
    rows = jnp.arange(d.shape[0])
    first = jnp.argmin(d, axis=1).astype(jnp.int32)
    rest = jnp.where(jnp.arange(d.shape[1])[None, :] == first[:, None], jnp.inf, d)
    second = jnp.argmin(rest, axis=1).astype(jnp.int32)
    # nothing finite left: top_k's tie order gives the lowest column other than ``first``
    second = jnp.where(jnp.isinf(rest[rows, second]), jnp.where(first == 0, 1, 0), second)
    return first, d[rows, first], second, d[rows, second]


def _ambiguity_clear(body, mag, ids, valid, ref, c, near, cand, cand_mag, own_mag, resid, tol, s,
                     kept, *, amb_k, amb_deg, partner_joint, partner_k, mag_sigma, rows=None):
    """Step 3: (N,) bool, the named stars whose name clearly beats every close rival catalog star.

    Costs are negative log likelihoods (nats): ``d² / s²`` (s² = 2 σ_axis²) plus, with ``mag_sigma``
    > 0, ``(m_obs − V)² / (2 σ_m²)``; a name is clear when the rival costs ``amb_k²`` more
    (``partner_k²`` under the partner rule).

    Args:
        body: (N, 3) detections (camera frame). mag: (N,) observed magnitudes. ids: (N,) names.
        valid: (N,) bool. ref: (N, 3) ICRS vectors of the names. c: (3, 3) attitude.
        near: (R,) catalog rows searched for rivals; cand (R, 3) their vectors, cand_mag (R,) their V.
        own_mag: (N,) V of each detection's name. resid: (N,) residuals (deg). tol, s: () deg.
        kept: (N,) bool, the names that passed the residual test.
        rows: optional (M,) int detections to test (default all N; every detection still serves as
            partner or contender); :func:`_verify_one` passes the named ones.

    Returns:
        (M,) bool, one verdict per entry of ``rows`` (N without ``rows``).
    """
    n = body.shape[0]
    rows = jnp.arange(n) if rows is None else rows
    own = ids[rows]
    ref_rows = ref[rows]  # (M, 3) the tested names' stars
    sep = _angle_deg(ref_rows[:, None, :], cand[None, :, :])  # catalog separation id ↔ candidate
    pred = precise.matmul(cand, c.T)  # (R, 3) candidates in the camera frame
    d_all = _angle_deg(body[:, None, :], pred[None, :, :])  # (N, R) every detection ↔ candidate
    d_rows = d_all[rows]  # (M, R)
    window = jnp.maximum(3.0 * tol, amb_deg)
    rival = (near[None, :] != own[:, None]) & (sep < window)  # (M, R)

    def mag_cost(m, v):
        if mag_sigma <= 0:
            return jnp.zeros(jnp.broadcast_shapes(m.shape, v.shape))
        return jnp.where(jnp.isfinite(m), (m - v) ** 2 / (2.0 * mag_sigma ** 2), 0.0)

    s2 = s ** 2
    margin = amb_k ** 2
    cost_own = resid ** 2 / s2 + mag_cost(mag, own_mag)  # (N,)
    cost_own_rows = cost_own[rows]
    cost_alt = d_rows ** 2 / s2 + mag_cost(mag[rows][:, None], cand_mag[None, :])  # (M, R)
    single = cost_alt - cost_own_rows[:, None] >= margin
    # joint test with the detection j nearest each rival (other than i itself): the exchange
    # (i → rival, j → i's star) against the present names (i → i's star; j → its kept name, or the
    # rival when j is unnamed)
    d_rival_det = jnp.where(valid[:, None], d_all, jnp.inf).T  # (R, N) rival ↔ detection
    near1, d1, near2, d2 = _two_nearest(d_rival_det)  # the two detections nearest each rival
    first_is_i = near1[None, :] == rows[:, None]  # (M, R)
    j = jnp.where(first_is_i, near2[None, :], near1[None, :])
    d_j_rival = jnp.where(first_is_i, d2[None, :], d1[None, :])
    own_pred = precise.matmul(ref_rows, c.T)  # (M, 3) i's own star in the camera frame
    d_j_own = _angle_deg(body[j], own_pred[:, None, :])  # (M, R): j against i's own star
    # j's cost now: the rival it sits next to; with partner_joint, its own kept name if it has one
    cost_j = d_j_rival ** 2 / s2 + mag_cost(mag[j], cand_mag[None, :])
    if partner_joint:
        cost_j = jnp.where(kept[j], cost_own[j], cost_j)
    exchange = (cost_alt + d_j_own ** 2 / s2 + mag_cost(mag[j], own_mag[rows][:, None])
                - (cost_own_rows[:, None] + cost_j))  # (M, R) nats the exchange costs more
    clear = single & ((exchange >= margin) | ~(d_j_rival <= window))
    nearest_row = near[jnp.argmin(d_all, axis=1)]  # (N,) each detection's nearest catalog star
    if partner_joint:
        # the rival has a detection of its own: within the tolerance, nearest to the rival of all
        # catalog stars, and named after it or unnamed (e.g. just outside the neighbor circle).
        # Then i → rival leaves only the exchange as an alternative: passing the exchange test
        # alone, with the wider margin partner_k² (one test instead of two), also clears the name
        partner = ((d_j_rival <= tol) & (nearest_row[j] == near[None, :])
                   & ((ids[j] < 0) | ((ids[j] == near[None, :]) & kept[j])))
        clear |= partner & (exchange >= partner_k ** 2)
    clear = jnp.all(~rival | clear, axis=1)  # every rival within the window
    # rival detection: an unnamed detection whose nearest catalog star is i's own star (a false
    # star, or a star the match left out, next to a named one) could be that star instead of i
    contender = (valid[None, :] & ~kept[None, :] & (rows[:, None] != jnp.arange(n)[None, :])
                 & (nearest_row[None, :] == own[:, None]))  # (M, N): j contends for i's star
    d_own_det = _angle_deg(own_pred[:, None, :], body[None, :, :])  # i's star ↔ detection j
    d_own_det = jnp.where(contender, d_own_det, jnp.inf)
    jc = jnp.argmin(d_own_det, axis=1)
    d_c = jnp.take_along_axis(d_own_det, jc[:, None], axis=1)[:, 0]
    cost_c = d_c ** 2 / s2 + mag_cost(mag[jc], own_mag[rows])
    return clear & (cost_c - cost_own_rows >= margin)


def _frame_coverage(c, body, valid, cat, cells, tol, *, camera, grid):
    """Step 5: catalog stars the attitude puts inside the frame, and how many have a detection.

    Returns:
        ``(hits, expected)``: () int32 each.
    """
    _, vec, real = local_stars(cells, cat, c[2], grid)  # c[2] = Cᵀ ẑ: the boresight (ICRS)
    pred = precise.matmul(vec, c.T)  # (K, 3) camera frame
    xy, in_field = camera.project(pred)
    tol_px = jnp.tan(jnp.radians(tol)) * camera.f_px
    expected = real & in_field & camera.contains(xy, tol_px)
    d = _angle_deg(pred[:, None, :], body[None, :, :])  # (K, N)
    hit = expected & jnp.any(valid[None, :] & (d <= tol), axis=1)
    return jnp.sum(hit), jnp.sum(expected)


def _verify_one(cat, cat_mag, cells, body, mag, valid, ids, ok, main, *, camera, grid, k, floor_deg,
                cap_deg, amb_k, amb_deg, partner_joint, partner_k, mag_sigma, rms_z, min_matched,
                min_coverage, n_near, max_named=None):
    """One scene. cat (M, 3), cat_mag (M,), cells (C, K), body (N, 3), mag/valid/ids (N,), ok,
    main () → (ids, ok, main_ambiguous)."""
    named0 = (ids >= 0) & ok
    rows = jnp.clip(ids, 0, cat.shape[0] - 1)
    ref = cat[rows]
    _, resid, _, tol = _fit(body, ref, named0, k, floor_deg, cap_deg)
    inl = named0 & (resid <= tol)
    c, resid, s, tol = _fit(body, ref, inl, k, floor_deg, cap_deg)
    keep = named0 & (resid <= tol)
    fits = keep
    s_amb = jnp.maximum(s, _upper_rms(resid, keep, rms_z))  # never looser than the fitted tolerance's s
    # ambiguity guard: catalog stars near the main star's sky direction (fixed count)
    sky_main = precise.matmul(body[main], c)  # Cᵀ b, ICRS
    _, near = jax.lax.top_k(precise.matmul(cat, sky_main), n_near)
    # only the named detections need a verdict: test those (at most max_named of them)
    n_det = body.shape[0]
    n_rows = n_det if max_named is None else min(int(max_named), n_det)
    tested = jnp.nonzero(named0, size=n_rows, fill_value=0)[0]
    live = jnp.arange(n_rows) < jnp.sum(named0)
    verdict = _ambiguity_clear(body, mag, ids, valid, ref, c, near, cat[near], cat_mag[near],
                               cat_mag[rows], resid, tol, s_amb, keep, amb_k=amb_k,
                               amb_deg=amb_deg, partner_joint=partner_joint, partner_k=partner_k,
                               mag_sigma=mag_sigma, rows=tested)
    # a padding entry repeats detection 0: OR-ing keeps detection 0's own verdict
    keep &= jnp.zeros(n_det, bool).at[tested].max(verdict & live)
    # more named detections than max_named: the ones left over were not tested, the scene fails
    overflow = jnp.sum(named0) > n_rows
    # the widest tolerance: the fitted one can be tight (a 3-star fit leaves tiny residuals) while
    # a wrong attitude meets a detection within 0.3° by chance for only ≈ 3 % of catalog stars
    hits, expected = _frame_coverage(c, body, valid, cat, cells, cap_deg, camera=camera,
                                     grid=grid)
    n0, n1 = jnp.sum(named0), jnp.sum(keep)
    sound = ok & ~overflow & (n1 >= min_matched) & (2 * n1 >= n0) & (hits >= min_coverage * expected)
    ok_new = sound & (keep[main] | ~named0[main])
    # the attitude passed every test and the main star fits it, but a close rival star contests
    # its name: the match is not in doubt, only the main star's name
    main_ambiguous = sound & fits[main] & ~keep[main]
    return jnp.where(keep & ok_new, ids, -1), ok_new, main_ambiguous


@functools.partial(stored_jit, static_argnames=("camera", "grid", "k", "floor_deg", "cap_deg", "amb_k",
                                             "amb_deg", "partner_joint", "partner_k", "mag_sigma",
                                             "rms_z", "min_matched", "min_coverage", "n_near",
                                             "max_named"))
def verify_ids(cat, cat_mag, cells, xy, mag, valid, ids, ok, main, *, camera, grid: int, k: float,
               floor_deg: float, cap_deg: float, amb_k: float, amb_deg: float,
               partner_joint: bool, partner_k: float, mag_sigma: float, rms_z: float,
               min_matched: int, min_coverage: float, n_near: int, max_named: int | None = None):
    """Verify a batch of SGM identifications against the attitude of the named stars (module doc).

    Args:
        cat: (M, 3) catalog ICRS unit vectors (rows as in ``ids``). cat_mag: (M,) their V (mag).
        cells: (6·G·G, K) int32 sky-index lists of catalog rows (padding ``M``) covering the frame of
            any boresight in the cell (:func:`~jstarid.sky_index.build_sky_index`).
        xy: (B, N, 2) centroids (px). mag: (B, N) observed magnitudes. valid: (B, N) bool.
        ids: (B, N) int32 catalog rows, −1 unnamed. ok: (B,) bool. main: (B,) int32 main detection.
        camera: static :class:`~jstarid.camera.Camera`. grid: G of the sky index.
        k: tolerance in robust RMS units. floor_deg, cap_deg: bounds on the tolerance (deg).
        amb_k: ambiguity margin in robust RMS units. amb_deg: smallest ambiguity window (deg).
        partner_joint: apply the partner rule (step 3) with margin ``partner_k`` (robust RMS units).
        mag_sigma: assumed σ of observed magnitudes (mag) in the ambiguity tests; 0 = positions only.
        rms_z: the margins' s is too small with probability Φ(−rms_z) (:func:`_upper_rms`).
        min_matched: fewest stars a verified scene keeps.
        min_coverage: fraction of the catalog stars projected in the frame that need a detection within
            ``cap_deg`` (0 = off).
        n_near: static count of catalog stars (nearest the main star) searched for rivals; must cover
            the neighbor circle plus the window.
        max_named: static most named detections per scene (default N) tested, as compacted rows; a scene
            with more fails (SGM's graph capacity K serves).

    Returns:
        ``(ids, ok, main_ambiguous)``: (B, N) int32 verified ids (−1 unnamed, whole row −1 where not
        ok), (B,) bool, and (B,) bool for the scenes failed only because a close rival star contests
        their main star's name (another database graph would not settle it).
    """
    body = camera.unproject(xy)
    ids = jnp.where(valid, ids, -1)
    fn = functools.partial(_verify_one, camera=camera, grid=grid, k=k, floor_deg=floor_deg,
                           cap_deg=cap_deg, amb_k=amb_k, amb_deg=amb_deg,
                           partner_joint=partner_joint, partner_k=partner_k, mag_sigma=mag_sigma,
                           rms_z=rms_z, min_matched=min_matched, min_coverage=min_coverage, n_near=n_near,
                           max_named=max_named)
    return jax.vmap(fn, in_axes=(None, None, None, 0, 0, 0, 0, 0, 0))(
        cat, cat_mag, cells, body, mag, valid, ids, ok, main)
