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
3. **Ambiguity guard.** A named star with other catalog stars within ``max(3·tol, ambiguity_deg)``
   of it (a close pair the match may have swapped) keeps its name only when its own residual clearly
   beats every such rival's: ``d_alt² − d_own² ≥ (ambiguity_k · s)²`` — a log likelihood ratio of
   ``ambiguity_k²`` for isotropic Gaussian noise (RMS s = √2 σ_axis). When another detection lies
   within the window of a rival star, the pair of names is tested jointly as well: the present names
   (this → own star, the other → rival) must beat the exchange (this → rival, other → own star) by
   the same margin in summed squared residuals. The joint test catches a close pair whose two
   detections both drifted towards one star (seen at σ = 1.5 px: the detection named after the wrong
   star of the pair sat 0.015° from it, so the single test alone passed). When the rival star has a
   detection of its own — within the tolerance, nearer to the rival than to any other catalog star,
   and named after the rival or unnamed (e.g. just outside the neighbor circle) — the rival is
   accounted for and the exchange is the only alternative left, so passing the joint test alone
   with the wider margin ``partner_k²`` also clears the name (``partner_joint``, on by default; the other
   detection's present cost is then its own kept name's): for a pair 4 σ apart the single test
   keeps a name ≈ 67 % of the time, the joint test ≈ 96 %. Why both conditions: without the
   nearest-star condition a detection nearer its own star can be taken for the rival's, and with
   the ``amb_k²`` margin a close pair whose two detections both drifted past each other can pass
   the exchange test with the wrong names (docs/design/sgm.md). Optionally (``mag_sigma`` > 0, off
   by default: SGM is a magnitude-free method) both tests add the magnitude term
   ``(m_obs − V)² / (2 σ_m²)`` to each hypothesis' cost. Every margin of this step is measured
   with a high-side s (:func:`_upper_rms`: the kept residuals' χ² with 2n − 3 degrees of freedom,
   too small with probability Φ(−z), 16 % at ``Config.verify_rms_z`` = 1), not the fitted
   tolerance's median-based s, whose chance shortfalls inflate every likelihood ratio. A last
   test looks for a rival *detection*: an unnamed detection whose nearest catalog star is this
   detection's own star (a false star next to a true one, seen once at σ = 3 px with one fake
   star: the fake, 0.063° from the star, took its name) must lose to it by the same margin.
4. **Scene decision.** The scene fails (``ok`` False, every id −1) when the main star was named and
   is unnamed by the check, when fewer than ``min_matched`` stars stay named, or when fewer than half
   of the named stars stay named (the attitude itself is then not trustworthy).
5. **Frame coverage.** The neighbor circle holds only part of the frame: a small graph (3–5 stars)
   matched to the wrong database graph can fit its own stars within the tolerance (δ just under
   ε_δ). The attitude must then also explain the rest of the frame: of the catalog stars it projects
   inside the frame (inset by ``cap_deg``), at least ``min_coverage`` must have a detection within
   ``cap_deg`` (the widest tolerance: the fitted one is too tight after a fit on 3–4 stars), or the
   scene fails. The wrong matches seen covered 11–12 % of the frame, correct scenes 97–100 % (one
   missing star, one false star, σ ≤ 3 px).
   Catalog stars are taken from a sky index (:mod:`jstarid.sky_index`) cell of the boresight, which
   holds every star that can be in the frame.

The caller (:func:`~jstarid.algorithms.sgm.identify.identify`, ``Config.verify_rename``) names the
detections this step left unnamed from the verified attitude and runs the step once more, so a
detection the match paired wrongly can still get its right name — through the same tests.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jstarid.attitude import solve_wahba
from jstarid.geometry import precise
from jstarid.geometry.angles import angle_between
from jstarid.robust import masked_median
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
    """A high-side estimate of the residual RMS s (deg) for the ambiguity margins (step 3).

    The residuals of n stars fitted by a 3-parameter attitude have ν = 2n − 3 degrees of freedom:
    Σ d² ~ (s²/2) χ²_ν. Dividing by the lower z-quantile of χ²_ν (Wilson–Hilferty) instead of its mean
    gives an s that is too small only with probability Φ(−z) (16 % at z = 1). Why: an s that comes out
    low by chance inflates every log likelihood ratio by 1/s² (a median-based s 13 % low let a
    5.3-nat name pass a 6.25-nat margin at σ = 3 px).
    """
    n = jnp.sum(mask)
    nu = jnp.maximum(2.0 * n - 3.0, 1.0)
    c = 2.0 / (9.0 * nu)
    q = nu * jnp.maximum(1.0 - c - z * jnp.sqrt(c), 0.05) ** 3
    return jnp.sqrt(2.0 * jnp.sum(jnp.where(mask, resid ** 2, 0.0)) / q)


def _two_nearest(d):
    """Column and value of the two smallest entries of each row of d (R, N), lowest column first on
    ties — ``lax.top_k(−d, 2)`` by two ``argmin`` passes (a few µs per scene on a CPU, where
    ``top_k`` took ≈ 0.9 ms, over half of the verification).

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

    Costs are negative log likelihoods (nats, up to a constant): ``d² / s²`` for an angular residual
    d (s² = 2 σ_axis²) plus, with ``mag_sigma`` > 0, ``(m_obs − V)² / (2 σ_m²)``. A name is clear
    when the rival hypothesis costs at least ``amb_k²`` more (``partner_k²`` when the joint test
    alone decides, ``partner_joint``).

    Args:
        body: (N, 3) detections (camera frame). mag: (N,) observed magnitudes. ids: (N,) names.
        valid: (N,) bool. ref: (N, 3) ICRS vectors of the names. c: (3, 3) attitude.
        near: (R,) catalog rows searched for rivals; cand (R, 3) their vectors, cand_mag (R,) their V.
        own_mag: (N,) V of each detection's name. resid: (N,) residuals (deg). tol, s: () deg.
        kept: (N,) bool, the names that passed the residual test.
        rows: optional (M,) int detections to test (default: all N). Every other detection still
            serves as a partner or contender; only the named ones need a verdict, and the caller
            (:func:`_verify_one`) passes those: the (N, R) and (N, N) tables of the named rows are
            most of the verification's work.

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


@functools.partial(jax.jit, static_argnames=("camera", "grid", "k", "floor_deg", "cap_deg", "amb_k",
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
        cells: (6·G·G, K) int32 sky-index lists of catalog rows (padding ``M``) covering the frame
            of any boresight in the cell (:func:`~jstarid.sky_index.build_sky_index`).
        xy: (B, N, 2) centroids (px). mag: (B, N) observed magnitudes. valid: (B, N) bool.
        ids: (B, N) int32 catalog rows, −1 unnamed. ok: (B,) bool. main: (B,) int32 main detection.
        camera: static :class:`~jstarid.camera.Camera`. grid: G of the sky index.
        k: tolerance in robust RMS units. floor_deg, cap_deg: bounds on the tolerance (deg).
        amb_k: ambiguity margin in robust RMS units. amb_deg: smallest ambiguity window (deg).
        partner_joint: a name whose rival star has a detection of its own (within the tolerance,
            nearest to the rival, named after it or unnamed) is decided by the joint exchange test
            alone, with the margin ``partner_k`` (robust RMS units) instead of ``amb_k``.
        mag_sigma: assumed σ of observed magnitudes (mag) in the ambiguity tests; 0 = positions
            only.
        rms_z: the margins' s is the residual RMS over the lower ``rms_z`` quantile of its χ²
            (:func:`_upper_rms`), too small with probability Φ(−rms_z).
        min_matched: fewest stars a verified scene keeps.
        min_coverage: fewest of the catalog stars projected inside the frame that must have a
            detection within ``cap_deg`` (fraction; 0 = off).
        n_near: static count of catalog stars (nearest the main star) searched for rivals; must
            cover the neighbor circle plus the window.
        max_named: static largest number of named detections per scene (default N): the ambiguity
            tests run on that many compacted rows instead of all N detections. A scene with more
            named detections fails (it is not verified partly). SGM names only the members of the
            neighbor graph, so its graph capacity K serves.

    Returns:
        ``(ids, ok, main_ambiguous)``: (B, N) int32 verified ids (−1 for unnamed, whole row −1
        where not ok), (B,) bool, and (B,) bool for the scenes that failed only because a close
        rival star contests their main star's name (every other test passed, the main star's
        residual included): another database graph would not settle it.
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
