"""RpNet identification (§II-E, Fig. 7): three central guides, weight search, then the other stars.

Per scene (written once, batched with ``vmap``):

1. S1, S2, S3: the three valid detections nearest the principal point (eq. 7), or (extension for
   guides thinned per sky cell, ``Config.guide_order = "brightness"``) the three brightest;
2. their initial inputs (eq. 3) → generator → classifier → softmax (eq. 4); the three most probable
   guide stars of each are its candidates, p_i1 > p_i2 > p_i3 (eq. 8);
3. weight search over the 27 candidate pairs S_ij ↔ S_kl (i < k; eqs. 9–11, Table 5 weights): a pair
   is rejected when its catalog angle (eq. 10) exceeds the field's diagonal, when both candidates are
   one star, or (extension, ``Config.pair_tol_px``) when it differs from the observed angle of S_i,
   S_k by more than the tolerance; the best remaining W = po_i·pr_j·p_ij + po_k·pr_l·p_kl is the
   "confident" pair;
4. naming (the paper's unstated "GNSs are identified easily"): attitude from the pair (two-vector
   Wahba ≡ TRIAD); a roll-free first pass by the distances to the pair stars (:func:`anchor_names`)
   and a fit on those; then ``n_refine`` passes of nearest-star naming within ``match_tol_px`` (no
   competing star or detection) and a refit on every name; a trimmed refit (the better half of the
   names, then all within ``trim_sigmas`` σ̂ of it) replaces the fit when its RMS is
   ``outlier_ratio`` times smaller (wrong names present); a last pass with the tolerance
   ``match_sigmas`` × σ̂ (clipped to [``match_tol_min_px``, ``match_tol_px``]; the pair's own
   detections ``pair_sigmas`` × σ̂) and a last refit;
5. verification: ``ok`` when at least ``min_verified`` detections are named and they are at least
   ``min_coverage`` of the catalog stars the final attitude puts inside the frame (in a scene flagged
   ``overflow``, of at most as many as it kept detections). Otherwise, on the unconfirmed scenes
   only, in later passes (extensions): the next-best pairs (``n_pair_trials``), the next triples by
   distance from the centre (``n_guide_triples``), then pairs across those detections
   (``n_pool_pairs``, :func:`_name_pool`); if nothing is confirmed every id is −1.
   ``n_pair_trials = n_guide_triples = 1, n_pool_pairs = 0`` is the paper's single confident pair.

Implementation (same results; docs/design/rpnet.md): the network runs folded
(:mod:`~jstarid.algorithms.rpnet.inference`) on all 3 × chunk inputs of a ``Config.batch_chunk``
chunk at once (:func:`network_candidates`), the naming in ``lax.map`` groups of ``Config.name_chunk``
scenes against the catalog stars of the sky-index cell of the pair's boresight (every nameable star
is in it); scenes are sorted by detection count and each chunk cut to the width it needs
(:data:`WIDTH_STEP`) and split over every JAX device. Kernels compile for :meth:`Config.compiled` and
read tolerances, counts and weights as traced :class:`~jstarid.algorithms.rpnet.config.Tuning`
values: a sweep compiles once.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.base import check_scenes
from jstarid.algorithms.rpnet.config import Config, Tuning
from jstarid.algorithms.rpnet.inference import inference_logits
from jstarid.algorithms.rpnet.model import use_bf16
from jstarid.algorithms.rpnet.pattern import config_kwargs, initial_input
from jstarid.attitude import solve_wahba
from jstarid.camera import tolerance_scales
from jstarid.camera_fit import fit_scaled, project_scaled, unproject_scaled
from jstarid.completion import first_argmax, name_stars
from jstarid.finishing import finish
from jstarid.geometry import precise
from jstarid.geometry.angles import angle_between
from jstarid.robust import masked_median
from jstarid.runtime import call_size, chunk_calls, columns_in_use, on_every_device, run_calls, take_rows
from jstarid.runtime.padding import MIN_CALL_SIZE
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Identification, Scene
from jstarid.sky_index import build_sky_index, local_stars

__all__ = ["PAIRS", "Diagnostics", "anchor_names", "identify", "name_stars", "network_candidates",
           "noise_sigma", "pair_checks", "top3_blocked", "weight_search"]

WIDTH_STEP = 32  # detection columns per scene are cut to a multiple of this in each chunk (identify)

# The 27 candidate pairs (i, j, k, l): detection i's j-th candidate with detection k's l-th, i < k.
PAIRS = np.array([(a, ca, b, cb) for a, b in itertools.combinations(range(3), 2)
                  for ca, cb in itertools.product(range(3), range(3))], np.int32)


def weight_search(probs, pair_ok, position_weights, probability_weights):
    """Eq. 11 scores of the 27 candidate pairs and the best admissible one.

    Args:
        probs: (3, 3) p_ij, probability of detection i's j-th candidate (j by decreasing probability).
        pair_ok: (27,) bool, pair :data:`PAIRS`[q] passed the angle checks (eq. 10 and extensions).
        position_weights: (3,) po_i (Table 5), nearest detection first. probability_weights: (3,) pr_j
            (Table 5), most probable candidate first.

    Returns:
        ``(best, score, found)``: index into :data:`PAIRS` of the highest-scoring admissible pair, (27,)
        scores (−inf where not admissible), and whether any pair is admissible.
    """
    po = jnp.asarray(position_weights, jnp.float32)
    pr = jnp.asarray(probability_weights, jnp.float32)
    i, j, k, m = (jnp.asarray(PAIRS[:, c]) for c in range(4))  # S_ij ↔ S_km
    score = po[i] * pr[j] * probs[i, j] + po[k] * pr[m] * probs[k, m]  # eq. 11
    score = jnp.where(pair_ok, score, -jnp.inf)
    return jnp.argmax(score), score, jnp.any(pair_ok)


def pair_checks(body, valid, near, cand_rows, star_vectors, pair_tol_px, *, camera):
    """Admissibility of the 27 candidate pairs of one scene: both detections exist, two different stars,
    catalog angle (eq. 10) within the field's largest angle, and (extension, ``Config.pair_tol_px``) it
    agrees with the observed angle between S_i and S_k.

    Args:
        body: (N, 3) camera-frame unit vectors of the detections; valid: (N,) bool.
        near: (3,) int32 detection index of S1, S2, S3.
        cand_rows: (3, 3) int32 catalog row of detection i's j-th candidate.
        star_vectors: (M, 3) ICRS catalog unit vectors.
        pair_tol_px: () tolerance on the angle difference (px; ``inf`` = off), float or traced.
        camera: static.

    Returns:
        (27,) bool, in :data:`PAIRS` order.
    """
    near_ok = valid[near]
    cand_vec = star_vectors[cand_rows]  # (3, 3, 3)
    i, j, k, m = (jnp.asarray(PAIRS[:, c]) for c in range(4))  # S_ij ↔ S_km
    return near_ok[i] & near_ok[k] & _admissible(
        cand_rows[i, j], cand_rows[k, m], cand_vec[i, j], cand_vec[k, m], body[near[i]], body[near[k]],
        pair_tol_px, camera=camera)


def _admissible(row_a, row_b, ref_a, ref_b, obs_a, obs_b, pair_tol_px, *, camera):
    """The candidate-pair tests (broadcast over leading axes): two different stars whose catalog angle
    (eq. 10) is within the field's largest angle and agrees within ``pair_tol_px`` (``inf``: not
    tested) with the angle between the observed directions ``obs_a``, ``obs_b`` (…, 3)."""
    d_cat = angle_between(ref_a, ref_b)  # eq. 10
    ok = (row_a != row_b) & (d_cat <= 2.0 * camera.half_diagonal_rad)
    # inf tolerance: always true (both directions are finite unit vectors of valid detections)
    return ok & (jnp.abs(d_cat - angle_between(obs_a, obs_b)) <= pair_tol_px / camera.f_px)


def anchor_names(c, body, valid, obs_a, obs_b, ref_a, ref_b, star_vectors, tol_rad, radius_rad):
    """Name detections by their angular distances to an identified pair (roll-free): j is named after
    catalog star s when |∠(j, a) − ∠(s, A)| and |∠(j, b) − ∠(s, B)| are within ``tol_rad`` (a, b the pair's
    detections, A, B their stars), s lies within ``radius_rad`` of where ``c`` puts j (resolving the
    mirror solution), and no second catalog star passes.

    Args:
        c: (3, 3) attitude from the pair. body: (N, 3) camera-frame unit vectors; valid: (N,) bool.
        obs_a, obs_b: (3,) camera-frame vectors of the pair's detections.
        ref_a, ref_b: (3,) ICRS vectors of their catalog stars.
        star_vectors: (M, 3) ICRS catalog unit vectors.
        tol_rad, radius_rad: distance tolerance and search radius (rad).

    Returns:
        ``(rows, named)`` as :func:`name_stars`.
    """
    d_obs_a, d_obs_b = angle_between(body, obs_a[None]), angle_between(body, obs_b[None])  # (N,)
    d_cat_a, d_cat_b = angle_between(star_vectors, ref_a[None]), angle_between(star_vectors, ref_b[None])
    err = jnp.maximum(jnp.abs(d_obs_a[:, None] - d_cat_a[None]), jnp.abs(d_obs_b[:, None] - d_cat_b[None]))
    # (N, M), a loose radius: cos is enough
    near = precise.small_matmul(precise.small_matmul(body, c), star_vectors.T) >= jnp.cos(radius_rad)
    err = jnp.where(near, err, jnp.inf)
    best = first_argmax(-err)
    e1 = jnp.take_along_axis(err, best[:, None], axis=1)[:, 0]
    e2 = jnp.min(jnp.where(jnp.arange(err.shape[1])[None, :] == best[:, None], jnp.inf, err), axis=1)
    named = valid & (e1 <= tol_rad) & (e2 > tol_rad)
    same = (best[:, None] == best[None, :]) & named[:, None] & named[None, :]
    return best.astype(jnp.int32), named & (jnp.sum(same, axis=1) == 1)


def _candidates(xy, valid, weights, *, camera, config: Config, n_classes: int, triple=0, count: int = 3,
                mag=None):
    """Steps 1–2 for a batch: S1–S3 (eq. 7), their inputs (eq. 3), network, top-3 (eqs. 4, 8).

    S1–S3 are the detections nearest the principal point (eq. 7), or the brightest ones by ``mag``
    ((B, N) mag) under ``Config.guide_order = "brightness"``.

    One matmul chain over all ``3 B`` inputs through the folded network
    (:mod:`~jstarid.algorithms.rpnet.inference`). ``triple = t`` (traced int32: one compilation for
    every t) takes the detections of distance rank 3t … 3t + 2 (t = 0: S1–S3; later triples:
    ``Config.n_guide_triples``); ``count`` (static) detections from there on (the pool pass takes all
    3 · ``n_guide_triples``).

    Returns:
        ``(near, probs, classes)``: (B, C) int32, (B, C, 3) float32, (B, C, 3) int32, C = count.
    """
    kw = config_kwargs(config)
    n = xy.shape[1]
    centre = jnp.array([camera.cx, camera.cy], jnp.float32)
    by_brightness = config.guide_order == "brightness"
    if by_brightness and mag is None:
        raise ValueError('guide_order="brightness" needs the detections\' magnitudes')
    mag = jnp.zeros(xy.shape[:2], jnp.float32) if mag is None else mag

    def one(xy_s, valid_s, mag_s):
        body = camera.unproject(xy_s)  # (N, 3) camera frame
        key = mag_s if by_brightness else jnp.sum((xy_s - centre[None, :]) ** 2, -1)
        d2 = jnp.where(valid_s, key, jnp.inf)
        # S1, S2, S3 (eq. 7) for triple 0; invalid detections come last (an invalid S_i makes its
        # pairs inadmissible). A static top-k over every triple's ranks, not an argsort: XLA's sort
        # is slow on CPU (docs/design/rpnet.md).
        _, order = jax.lax.top_k(-d2, min(n, 3 * config.n_guide_triples))
        near = jax.lax.dynamic_slice(order, (3 * triple,), (min(count, order.shape[0]),))
        inputs = jax.vmap(lambda g: initial_input(body[g], body, valid_s & (jnp.arange(n) != g), **kw))(near)
        return near, inputs

    near, inputs = jax.vmap(one)(xy, valid, mag)
    logits = inference_logits(weights, inputs, bf16=use_bf16(config.network_bf16))  # (B, C, K)
    if logits.shape[-1] != n_classes:
        raise ValueError(f"the network has {logits.shape[-1]} classes, the database {n_classes}")
    p, cls = softmax_top3(logits)
    return near, p, cls


def softmax_top3(logits):
    """The three most probable classes and their softmax probabilities (eqs. 4, 8): top 3 of the logits
    (softmax is monotonic), normalised by the softmax's sum.

    Args:
        logits: (..., K) float32.

    Returns:
        ``(p, classes)``: (..., 3) float32 decreasing, (..., 3) int32.
    """
    top, cls = top3_blocked(logits)
    # The largest logit as a max over the top 3, not the slice top[..., :1] (the same value): XLA
    # folds a slice of a top-k's values into the top-k, which then no longer matches its CPU TopK
    # kernel and runs as a full sort of the picked blocks (≈ 0.3 s per 4,096 scenes).
    peak = jnp.max(top, -1, keepdims=True)
    total = jnp.sum(jnp.exp(logits - peak), -1, keepdims=True)
    # A no-op on float32 that XLA cannot fuse: fused with the division below, the sum over the
    # (B, 3, K) logits ran ≈ 2× slower on CPU (a YNNPACK reduction fusion).
    total = jax.lax.reduce_precision(total, exponent_bits=8, mantissa_bits=23)
    return jnp.exp(top - peak) / total, cls.astype(jnp.int32)


def top3_blocked(x):
    """``jax.lax.top_k(x, 3)`` along the last axis through block maxima (far faster on CPU for large K).

    The axis is cut into blocks of ⌊√K⌋ entries plus a shorter tail; the three largest entries lie in
    the tail or in the three blocks with the largest maxima (at most two entries exceed an entry's
    block maximum), so a top-3 over the block maxima, then over those blocks and the tail, is exact.
    Values equal ``lax.top_k``'s; with exact ties the index may differ. Block maxima by a strided
    ``reduce_window`` and a gather of the three blocks (a reshape into blocks copies the whole array).

    Args:
        x: (..., K) float scores (no NaN).

    Returns:
        ``(values, indices)``: (..., 3) in decreasing order, and their int32 positions in ``x``.
    """
    k = x.shape[-1]
    if k < 3:
        raise ValueError(f"top-3 needs at least 3 classes, got {k}")
    size = max(3, math.isqrt(k))
    n_blocks = k // size
    if n_blocks < 4:  # too short to gain anything
        values, index = jax.lax.top_k(x, 3)
        return values, index.astype(jnp.int32)
    lead = x.shape[:-1]
    window = (1,) * len(lead) + (size,)
    block_max = jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, window, window, "VALID")
    _, which = jax.lax.top_k(block_max, 3)  # (..., 3) blocks holding the top 3 (tail aside)
    offsets = jnp.arange(size).reshape((1,) * which.ndim + (size,))
    columns = (which[..., None] * size + offsets).reshape(*lead, 3 * size)
    picked = jnp.take_along_axis(x, columns, axis=-1)
    values, pos = jax.lax.top_k(jnp.concatenate([picked, x[..., n_blocks * size:]], -1), 3)
    in_block = jnp.take_along_axis(columns, jnp.minimum(pos, 3 * size - 1), axis=-1)
    index = jnp.where(pos < 3 * size, in_block, n_blocks * size + pos - 3 * size)
    return values, index.astype(jnp.int32)


def noise_sigma(resid, named):
    """Centroid noise σ̂ (px per axis) from the residuals of an attitude fit, robust to wrong names: the
    median of the named residuals (a false star named after an undetected catalog star would inflate
    an RMS) / √(2 ln 2) (Rayleigh median), × √(2n / (2n − 3)) for the fit's three degrees of freedom.

    Args:
        resid: (N,) residual distances (px). named: (N,) bool, the detections the fit used.

    Returns:
        () float32 σ̂ (px); 0 when nothing is named.
    """
    nf = jnp.sum(named).astype(jnp.float32)
    sigma = (masked_median(resid, named) / math.sqrt(2.0 * math.log(2.0))
             * jnp.sqrt(2.0 * nf / jnp.maximum(2.0 * nf - 3.0, 1.0)))
    return jnp.where(nf > 0, sigma, 0.0)


def _rms_sigma(resid, named):
    """Centroid noise σ̂ (px per axis): the RMS of the named residual distances over 2n − 3 (the
    fitted attitude's three degrees of freedom). (N,) px, (N,) bool → () px."""
    w = named.astype(jnp.float32)
    return jnp.sqrt(jnp.sum(w * resid**2) / jnp.maximum(2.0 * jnp.sum(w) - 3.0, 1.0))


def _verify_pair(a, b, row_a, row_b, xy, body, valid, star_vectors, cells, th: Tuning, *, camera,
                 config: Config, grid):
    """Steps 4–5 from one pair: detection ``a`` named catalog row ``row_a``, ``b`` named ``row_b``.

    With ``config.finishing.fit_focal`` (extension) every refinement pass fits the focal length with the
    attitude (:func:`jstarid.camera_fit.fit_scaled`) and the later steps use the fitted camera:
    a focal length off by 2 % moves the edge stars of a 20° frame by 10–15 px, beyond the naming
    tolerance, where the nominal camera leaves them unnamed or names them after another star.

    Returns:
        ``(rows, named, attitude, expected)``: (N,) catalog row of each detection, (N,) bool named,
        (3, 3) refined attitude, () number of catalog stars the attitude puts inside the frame.
    """
    tol = th.match_tol_px / camera.f_px
    pair_ref = star_vectors[jnp.stack([row_a, row_b])]
    # attitude from the pair (two-vector Wahba ≡ TRIAD)
    c0 = solve_wahba(jnp.stack([body[a], body[b]]), pair_ref, jnp.ones((2,), jnp.float32))
    # only the catalog stars that can be named matter: those of the sky-index cell of the pair's
    # boresight (every star within reach of the field, see _local_index); padding → the antipode
    # of the boresight, never within any tolerance. Local index → catalog row through `loc`.
    loc, loc_vec, _ = local_stars(cells, star_vectors, c0[2], grid)  # (K,) catalog rows, M = padding
    # anchor pass: a close pair fixes the roll poorly, so distances to the pair (roll-free) name
    # the stars first; the pair attitude only picks the side of the pair axis
    rows_a, named_a = anchor_names(c0, body, valid, body[a], body[b], pair_ref[0], pair_ref[1],
                                   loc_vec, tol, th.anchor_radius_px / camera.f_px)
    c_a = solve_wahba(body, loc_vec[rows_a], named_a.astype(jnp.float32))
    c0 = jnp.where(jnp.sum(named_a) >= 2, c_a, c0)

    def refine(c, s):  # name within the fixed tolerance, refit on every named star (Wahba)
        if not config.finishing.fit_focal:
            rows, named = name_stars(c, body, valid, loc_vec, tol)
            return jnp.where(jnp.sum(named) >= 2, solve_wahba(body, loc_vec[rows],
                                                               named.astype(jnp.float32)), c), s
        rows, named = name_stars(c, unproject_scaled(camera, xy, s), valid, loc_vec, tol / s)
        # one joint Gauss–Newton step of attitude and scale per pass, from the previous pass's
        # fit (the passes iterate). An alternation of Wahba and the scale's closed form was
        # cheaper but crept where the names lie to one side: its partly fitted scale named far
        # edge stars after neighbours of theirs, consistently enough to survive the final check.
        fit, s_fit, _ = fit_scaled(xy, loc_vec[rows], named.astype(jnp.float32), camera, True,
                                   start=(c, s), iterations=1)
        enough = jnp.sum(named) >= 2
        return jnp.where(enough, fit, c), jnp.where(enough, s_fit, s)

    c1, scale = c0, jnp.float32(1.0)
    for _ in range(config.n_refine):  # unrolled: a loop inside vmap runs ≈ 4× slower on CPU
        c1, scale = refine(c1, scale)
    if config.finishing.fit_focal:  # from here on the fitted camera: directions and pixels at f · scale
        body = unproject_scaled(camera, xy, scale)
        tol = tol / scale
    f_px = camera.f_px * scale
    rows0, named0 = name_stars(c1, body, valid, loc_vec, tol)

    def residual_px(c):  # (N,) distance of each detection from its name's predicted position (px)
        return angle_between(body, precise.small_matmul(loc_vec[rows0], c.T)) * f_px

    # centroid noise σ̂ (px per axis) from the residuals of the fit on every name (RMS over 2n − 3)
    resid = residual_px(c1)
    sigma = _rms_sigma(resid, named0)
    # robust refit (least trimmed squares, one step): at ``match_tol_px`` a false star near where
    # the attitude puts an undetected catalog star can be named, and a few such names bias the fit
    # by pixels, so that it keeps naming them. The better half of the names fixes an attitude
    # without them; the names within ``trim_sigmas`` × its median-based σ̂ refit it on all their
    # stars again. It replaces the plain fit only when its σ̂ is ``outlier_ratio`` times smaller
    # (wrong names present): with clean noise both fits agree and the plain one, on every star,
    # is kept (docs/design/rpnet.md).
    better = named0 & (resid <= masked_median(resid, named0))
    c_t = solve_wahba(body, loc_vec[rows0], better.astype(jnp.float32))
    c_t = jnp.where(jnp.sum(better) >= 3, c_t, c1)
    resid_t = residual_px(c_t)
    inlier = named0 & (resid_t <= jnp.clip(th.trim_sigmas * noise_sigma(resid_t, named0), th.match_tol_min_px,
                                           th.match_tol_px))
    c_i = solve_wahba(body, loc_vec[rows0], inlier.astype(jnp.float32))
    resid_i = residual_px(c_i)
    sigma_i = _rms_sigma(resid_i, inlier)
    robust = (jnp.sum(inlier) >= 3) & (sigma > th.outlier_ratio * sigma_i)
    c1 = jnp.where(robust, c_i, c1)
    resid = jnp.where(robust, resid_i, resid)
    sigma = jnp.where(robust, sigma_i, sigma)
    # last pass: the tolerance follows the centroid noise
    tol2 = jnp.clip(th.match_sigmas * sigma, th.match_tol_min_px, th.match_tol_px)
    rows1, named1 = name_stars(c1, body, valid, loc_vec, tol2 / f_px, config.name_isolation)
    # the pair's two detections were named by the network and the pair check, not by proximity:
    # they keep their name out to pair_sigmas · σ̂ (a 3.5 σ̂ radius drops 0.2 % of true stars; at
    # 8 σ̂ none are lost even where σ̂ from ≈ 10 stars comes out low), not further: a false star
    # that took the place of an undetected guide star lies many σ̂ from it at low noise
    pair_tol = jnp.clip(th.pair_sigmas * sigma, th.match_tol_min_px, th.match_tol_px)
    pair_row = jnp.zeros_like(valid).at[a].set(True).at[b].set(True)
    expected = jnp.where(jnp.arange(valid.shape[0]) == a, row_a, row_b)
    keep0 = pair_row & named0 & (loc[rows0] == expected) & ~named1 & (resid <= pair_tol)
    rows1 = jnp.where(keep0, rows0, rows1)
    named1 = named1 | keep0
    c2 = solve_wahba(body, loc_vec[rows1], named1.astype(jnp.float32))
    c2 = jnp.where(jnp.sum(named1) >= 2, c2, c1)
    # coverage: catalog stars the final attitude puts inside the frame (inset by the tolerance)
    xy_pred, in_field = project_scaled(camera, precise.small_matmul(loc_vec, c2.T), scale)
    inside = (loc < star_vectors.shape[0]) & in_field & camera.contains(xy_pred, th.match_tol_px)
    return loc[rows1], named1, c2, jnp.sum(inside)


def _first_confirmed(score, a, b, row_a, row_b, xy, body, valid, overflow, star_vectors, cells,
                     th: Tuning, *, camera, config: Config, grid):
    """Verify the pairs in the given (score) order and keep the first confirmed one (step 5).

    Args:
        score: (T,) score of each pair (−inf: not admissible); a, b, row_a, row_b: (T,) the pairs.
        overflow: () bool, the scene kept only its brightest ``capacity`` detections.

    Returns:
        ``(ids, ok, attitude)``: (N,) int32 catalog rows (−1 unnamed, all −1 unless ok), () bool,
        (3, 3) float32 (NaN unless ok).
    """
    verify = functools.partial(_verify_pair, xy=xy, body=body, valid=valid, star_vectors=star_vectors,
                               cells=cells, th=th, camera=camera, config=config, grid=grid)
    rows_t, named_t, att_t, expected_t = jax.vmap(verify)(a, b, row_a, row_b)
    # a scene cut to its brightest `capacity` detections (overflow) cannot name more stars than it
    # kept: the coverage counts at most that many (a dense real frame kept 24 of its 67 V ≤ 7 stars)
    expected_t = jnp.where(overflow, jnp.minimum(expected_t, jnp.sum(valid)), expected_t)
    n_named = jnp.sum(named_t, axis=1)
    confirmed = (jnp.isfinite(score) & (n_named >= th.min_verified)
                 & (n_named >= th.min_coverage * expected_t))
    pick = jnp.argmax(confirmed)  # the first confirmed pair in score order
    ok = confirmed[pick]
    ids = jnp.where(ok & named_t[pick], rows_t[pick], -1)
    att = jnp.where(ok, att_t[pick], jnp.nan)
    return ids.astype(jnp.int32), ok, att.astype(jnp.float32)


def _name_pool(xy, valid, overflow, near, p, cls, guide_rows, star_vectors, cells, th: Tuning, *, camera,
               config: Config, grid):
    """Pool pass for one scene (extension, ``Config.n_pool_pairs``): pairs across all triples.

    Every pair of candidates of two different detections among ``near`` (the 3 · n_guide_triples
    nearest the centre) is scored like eq. 11 without position weights (Table 5 has them for S1–S3
    only), W = pr_j·p_ij + pr_l·p_kl, under the checks of :func:`pair_checks`; the ``n_pool_pairs`` best
    are verified in score order (two correct detections often sit in different triples).
    """
    body = camera.unproject(xy)
    t = near.shape[0]
    rows = guide_rows[cls].reshape(-1)  # (3T,) candidate j of detection slot s at 3 s + j
    slot = jnp.repeat(jnp.arange(t), 3)
    det = near[slot]
    vec, obs = star_vectors[rows], body[det]
    weight = th.probability_weights[jnp.tile(jnp.arange(3), t)] * p.reshape(-1)
    ok = ((slot[:, None] < slot[None, :]) & valid[det][:, None] & valid[det][None, :]
          & _admissible(rows[:, None], rows[None, :], vec[:, None], vec[None, :], obs[:, None], obs[None, :],
                        th.pair_tol_px, camera=camera))
    score = jnp.where(ok, weight[:, None] + weight[None, :], -jnp.inf).reshape(-1)
    top_score, flat = jax.lax.top_k(score, min(config.n_pool_pairs, score.shape[0]))
    u, v = flat // (3 * t), flat % (3 * t)
    return _first_confirmed(top_score, det[u], det[v], rows[u], rows[v], xy, body, valid, overflow,
                            star_vectors, cells, th, camera=camera, config=config, grid=grid)


def _name_one(xy, valid, overflow, near, p, cls, guide_rows, star_vectors, cells, th: Tuning, *, camera,
              config: Config, grid, trials=(0, 1)):
    """Steps 3–5 for one scene from the network's candidates: verify the admissible pairs of score rank
    ``trials[0]`` … ``trials[0] + trials[1] − 1`` and keep the first confirmed one.
    """
    body = camera.unproject(xy)  # (N, 3) camera frame
    cand_rows = guide_rows[cls]  # (3, 3) catalog rows
    i, j, k, m = (jnp.asarray(PAIRS[:, c]) for c in range(4))  # S_ij ↔ S_km
    pair_ok = pair_checks(body, valid, near, cand_rows, star_vectors, th.pair_tol_px, camera=camera)
    _, score, _ = weight_search(p, pair_ok, th.position_weights, th.probability_weights)
    # the best admissible pair (eq. 11) first; the next ones only when it is not confirmed
    top_score, q = jax.lax.top_k(score, trials[0] + trials[1])
    top_score, q = top_score[trials[0]:], q[trials[0]:]
    return _first_confirmed(top_score, near[i[q]], near[k[q]], cand_rows[i[q], j[q]], cand_rows[k[q], m[q]],
                            xy, body, valid, overflow, star_vectors, cells, th, camera=camera, config=config,
                            grid=grid)


def network_candidates(xy, valid, weights, triple=0, *, camera, config: Config, n_classes: int, mag=None):
    """The network part of identification alone (benchmarks, the weight-grid search).

    Args:
        xy: (B, N, 2) centroids (px); valid: (B, N) bool.
        weights: the folded networks (``database.inference_weights``).
        triple: int32 scalar t: the detections of distance rank 3t … 3t + 2 (0: S1–S3).
        camera, config, n_classes: static.
        mag: (B, N) detection magnitudes (needed under ``Config.guide_order = "brightness"``).

    Returns:
        ``(near, probs, classes)``: (B, 3) int32 detection index of S1, S2, S3 (eq. 7), (B, 3, 3)
        float32 top-3 softmax probabilities p_ij (eq. 8) and (B, 3, 3) int32 their classes.
    """
    return _network_candidates(xy, valid, weights, triple=triple, camera=camera,
                               config=config.compiled(), n_classes=n_classes, mag=mag)


_network_candidates = stored_jit(_candidates, static_argnames=("camera", "config", "n_classes", "count"))


@functools.partial(stored_jit, static_argnames=("camera", "config", "n_classes", "grid", "trials"))
def _identify_chunk(xy, valid, overflow, mag, weights, guide_rows, star_vectors, cells, th, triple, *,
                    camera, config, n_classes, grid, trials):
    near, p, cls = _candidates(xy, valid, weights, camera=camera, config=config, n_classes=n_classes,
                               triple=triple, mag=mag)
    fn = functools.partial(_name_one, guide_rows=guide_rows, star_vectors=star_vectors, cells=cells,
                           th=th, camera=camera, config=config, grid=grid, trials=trials)
    # naming in small vmapped groups: its (N × local stars) intermediates stay in cache
    return jax.lax.map(lambda a: fn(*a), (xy, valid, overflow, near, p, cls),
                       batch_size=config.name_chunk)


@functools.partial(stored_jit, static_argnames=("camera", "config", "n_classes", "grid"))
def _identify_pool_chunk(xy, valid, overflow, mag, weights, guide_rows, star_vectors, cells, th, *, camera,
                         config, n_classes, grid):
    near, p, cls = _candidates(xy, valid, weights, camera=camera, config=config, n_classes=n_classes,
                               count=3 * config.n_guide_triples, mag=mag)
    fn = functools.partial(_name_pool, guide_rows=guide_rows, star_vectors=star_vectors, cells=cells,
                           th=th, camera=camera, config=config, grid=grid)
    return jax.lax.map(lambda a: fn(*a), (xy, valid, overflow, near, p, cls),
                       batch_size=config.name_chunk)


def _triple_kernel_config(config: Config) -> Config:
    """The static config of :func:`_identify_chunk`: ``n_pool_pairs`` (which it does not read) at its
    default, and its guide ranks (``top_k`` over 3 · ``n_guide_triples``) at least the default's, so
    configs that differ only in the pool pass or in fewer triples share its compilations (≈ 5 s each
    per pass, chunk size and width on 2 cores). Triple t's guides, ranks 3t … 3t + 2, are the same
    under any larger ``top_k``."""
    default = Config()
    return dataclasses.replace(config, n_pool_pairs=default.n_pool_pairs,
                               n_guide_triples=max(config.n_guide_triples, default.n_guide_triples))


def _local_index(database, config: Config):
    """Sky index of the catalog stars a pair attitude can name (memoised per catalog and reach).

    Reach about the pair's boresight: half diagonal + anchor radius + match tolerance + 1° for the pair
    attitude's error (≈ 72 px on the papers' cameras; scaled with the pixel scale like the other
    tolerances, :func:`jstarid.camera.tolerance_scales`: 0.32° on the narrow twin, whose lists it
    shortens by a quarter); every star within ``match_tol_px`` or ``anchor_radius_px`` of a
    detection is in the list, so naming against it equals naming against the whole catalog.
    """
    cam = database.camera
    pixel, _ = tolerance_scales(cam)
    margin = (config.anchor_radius_px + config.match_tol_px) / cam.f_px + np.radians(1.0) * pixel
    return build_sky_index(np.asarray(database.star_vectors, np.float64), cam.half_diagonal_rad,
                           margin_rad=float(margin), key=f"rpnet-{database.catalog_fingerprint}")


class Diagnostics(NamedTuple):
    """Per-scene internals of :func:`identify` (host NumPy arrays, batch axis first).

    Attributes:
        n_candidates: (B,) int32 candidate pairs submitted to verification over all passes (an upper
            bound: a pass stops at its first confirmed pair).
        overflow: (B,) bool, ``Scene.overflow`` (the identifier has no buffer of its own).
        n_passes: (B,) int32 identification passes run (1 + the later passes it needed).
    """

    n_candidates: np.ndarray
    overflow: np.ndarray
    n_passes: np.ndarray


def identify(database, scenes: Scene, config: Config | None = None, *, diagnostics: bool = False,
             tuning: Tuning | None = None):
    """Identify a batch of scenes (host loop over fixed-size chunks of one compiled function per width).

    Then the finishing stage (``Config.finishing``, :func:`jstarid.finishing.finish`; off in
    ``Config.paper()``): the scenes left unsolved are tried again under focal lengths 1–2 % off, and
    every solved scene's names are checked against a fit of the attitude and the focal length, which
    sets ``focal_scale``. Diagnostics describe the first call.

    Args:
        database: :class:`~jstarid.algorithms.rpnet.database.Database`.
        scenes: (B, N) :class:`~jstarid.scene.Scene` taken with ``database.camera``.
        config: identification settings; ``None`` uses ``database.config``. Its network-shaping
            settings must match the database's.
        diagnostics: also return the :class:`Diagnostics`.
        tuning: the traced settings (:class:`~jstarid.algorithms.rpnet.Tuning`, scalars shared by the
            batch); ``None``: ``config.tuning()``. Another value reuses the compilation.

    Returns:
        :class:`~jstarid.scene.Identification` with ids (B, N), ok (B,), attitude (B, 3, 3) (NaN where
        not ok); with ``diagnostics``, the tuple ``(Identification, Diagnostics)``.

    Raises:
        ValueError: ``config`` describes another network than the database holds.
    """
    config = database.config if config is None else config
    check_scenes(scenes)
    if config.database_fields() != database.config.database_fields():
        raise ValueError("config's network settings differ from the database's; build a database for it")
    result, diag = _identify(database, scenes, config, tuning)
    result = finish(result, scenes, config.finishing,
                    rerun=lambda moved, rows: _identify(database, moved, config, tuning)[0],
                    camera=database.camera, star_vectors=database.star_vectors,
                    star_mags=database.star_mags).result
    return (result, diag) if diagnostics else result


def _identify(database, scenes: Scene, config: Config, tuning: Tuning | None):
    """:func:`identify` under the nominal camera, without the final camera check: (result, diagnostics)."""
    b, n = scenes.batch_size, scenes.xy.shape[1]
    guide_rows = jnp.asarray(database.guide_rows, jnp.int32)
    index = _local_index(database, config)
    cells = index.device_arrays()[0]
    # Scenes sorted by their last valid detection and cut to the chunk's width (a multiple of
    # WIDTH_STEP): trailing padding columns only cost time, and most scenes hold far fewer
    # detections than the capacity. Results are put back in the input order.
    valid_all, xy_all = np.asarray(scenes.valid), np.asarray(scenes.xy)
    overflow_all = np.asarray(scenes.overflow)
    mag_all = np.asarray(scenes.mag, np.float32)
    last = columns_in_use(valid_all)
    if n < WIDTH_STEP:  # narrower scenes get empty columns: one compiled width serves every small scene
        xy_all, valid_all, mag_all = (np.pad(a, [(0, 0), (0, WIDTH_STEP - n)] + [(0, 0)] * (a.ndim - 2))
                                      for a in (xy_all, valid_all, mag_all))
    n_cols = xy_all.shape[1]
    ids_out = np.full((b, n_cols), -1, np.int32)
    ok_out = np.zeros((b,), bool)
    att_out = np.full((b, 3, 3), np.nan, np.float32)
    n_pairs = np.zeros((b,), np.int32)
    n_passes = np.zeros((b,), np.int32)

    # the kernels compile for config.compiled(); its thresholds travel as traced values, so configs
    # that differ only there (a tolerance or coverage sweep) share every compilation
    tables = (database.inference_weights, guide_rows, database.star_vectors)
    if jax.local_device_count() > 1:  # placed on every device once, not copied on each chunk's call
        tables = on_every_device(database, "rpnet_identify", lambda: tables)
        cells = on_every_device(index, "device_arrays", index.device_arrays)[0]
    replicated = (*tables, cells, config.tuning() if tuning is None else tuning)
    kernel_config = config.compiled()

    common = dict(camera=database.camera, config=kernel_config, n_classes=database.n_classes,
                  grid=index.grid)
    out = [ids_out, ok_out, att_out]

    def args(call):
        # the chunk's columns cut to its widest scene, rounded up to a multiple of WIDTH_STEP; a call
        # of the smallest size keeps them all: one program serves every small batch and retry,
        # where each new width compiled the network's kernel again
        width = int(min(n_cols, max(WIDTH_STEP, -(-int(last[call.rows].max()) // WIDTH_STEP) * WIDTH_STEP)))
        if call.size <= MIN_CALL_SIZE:
            width = n_cols
        return take_rows((xy_all[:, :width], valid_all[:, :width], overflow_all, mag_all[:, :width]), call)

    def run(subset, trials, triple=0, pool=False):
        n_pairs[subset] += config.n_pool_pairs if pool else trials[1] - trials[0]
        n_passes[subset] += 1
        # scenes sorted by their last valid detection, so each chunk's width fits its scenes; every
        # pass over 1–16 scenes runs in calls of 16 (runtime.call_size: one compilation)
        calls = chunk_calls(subset[np.argsort(last[subset], kind="stable")],
                            call_size(subset.size, config.batch_chunk))
        kernel, extra, static = ((_identify_pool_chunk, (), common) if pool else
                                 (_identify_chunk, (jnp.int32(triple),),
                                  dict(common, config=_triple_kernel_config(kernel_config), trials=trials)))
        run_calls(kernel, calls, args, (*replicated, *extra), static=static, n_rows=b,
                  tails=[(n_cols,), (), (3, 3)], fills=[-1, False, np.nan], out=out)

    run(np.arange(b), (0, 1))
    n_valid = valid_all.sum(1)
    for triple in range(config.n_guide_triples):
        # Later passes, only on the scenes still unconfirmed: the same outcome as trying everything
        # at once in order (the first confirmed pair wins) at a fraction of the cost. Triple 0: the
        # next-best pairs of S1–S3 (its best pair is tried again, and fails again, so that every
        # later pass shares one compilation); triple t ≥ 1 (fallback): detections 3t … 3t + 2 by
        # distance from the centre, where the nearer ones confirmed nothing (typically one of them
        # is a false star or a star outside the guide catalog).
        if triple == 0 and config.n_pair_trials == 1:
            continue
        failed = np.nonzero(~ok_out & (n_valid >= 3 * triple + 2))[0]
        if failed.size:
            run(failed, (0, config.n_pair_trials), triple)
    failed = np.nonzero(~ok_out & (n_valid >= 2))[0]
    if config.n_pool_pairs and failed.size:  # last: pairs across the triples (_name_pool)
        run(failed, None, pool=True)
    result = Identification(ids=jnp.asarray(ids_out[:, :n]), ok=jnp.asarray(ok_out),
                            attitude=jnp.asarray(att_out))
    return result, Diagnostics(n_candidates=n_pairs, overflow=overflow_all.copy(), n_passes=n_passes)
