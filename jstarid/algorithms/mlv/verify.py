"""Verification (paper §2.3.2): pair-angle voting and the largest mutually consistent cluster.

Detections (s_i, s_j) with candidates (c_i, c_j) agree when |θˢ_ij − θᶜ_ij| ≤ ε (eq. 8). The paper's
"largest cluster group" is read as the largest set of candidates that agree *pairwise* (a maximum
clique), found exactly by testing all 2^N subsets of the N ≤ 12 detections (fixed work). A scene
succeeds when it has at least ``ver_min`` members; only members are named. When several clusters
share the largest size, only the detections common to all are named (the scene fails below
``ver_min``): a tie means ambiguous candidates, and a mis-identification is worse than a failure.
"""

from __future__ import annotations

import math
from functools import cache

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.attitude import solve_wahba
from jstarid.geometry import precise
from jstarid.geometry.angles import angle_between, pairwise_angles

__all__ = ["pair_angles", "agreement", "largest_cluster", "subset_masks", "attitude_check",
           "field_check", "fit_attitude"]


def pair_angles(vectors):
    """(..., n, n) angles (rad) between unit vectors (..., n, 3) (shared, small-angle accurate)."""
    return pairwise_angles(vectors)


def agreement(det_vectors, cand_vectors, cand_ids, has_cand, eps_rad: float):
    """Pairs whose candidates reproduce the observed angular distance (eq. 8).

    Args:
        det_vectors: (n, 3) detection directions (camera frame).
        cand_vectors: (n, 3) candidate directions (ICRS).
        cand_ids: (n,) int32 candidate stars (two detections may not share one star).
        has_cand: (n,) bool, the detection has a candidate.
        eps_rad: tolerance ε (rad).

    Returns:
        (n, n) bool symmetric agreement matrix, False on the diagonal.
    """
    n = det_vectors.shape[0]
    diff = jnp.abs(pair_angles(det_vectors) - pair_angles(cand_vectors))
    both = has_cand[:, None] & has_cand[None, :]
    distinct = cand_ids[:, None] != cand_ids[None, :]
    return both & distinct & (diff <= eps_rad) & ~jnp.eye(n, dtype=bool)


@cache
def subset_masks(n: int) -> np.ndarray:
    """(2^n, n) float32 membership of every subset of n items (row b: the bits of b)."""
    bits = (np.arange(2**n)[:, None] >> np.arange(n)[None, :]) & 1
    return bits.astype(np.float32)


def largest_cluster(agree):
    """The largest set of detections whose candidates agree pairwise (a maximum clique).

    Args:
        agree: (n, n) bool symmetric agreement matrix (False on the diagonal).

    Returns:
        ``(first, common, size)``: (n,) bool members of the first largest cluster in subset order, (n,)
        bool detections in *every* largest cluster (= ``first`` when it is unique), and the scalar int32
        largest size (≥ 1: a single detection is a trivial cluster; callers compare with ``ver_min`` ≥ 2).
    """
    n = agree.shape[0]
    masks_np = subset_masks(n)
    member = jnp.asarray(masks_np > 0)  # (2^n, n)
    subsets = jnp.arange(2**n, dtype=jnp.int32)
    bit = jnp.left_shift(1, jnp.arange(n, dtype=jnp.int32))  # (n,)
    # disagree[i] as a bitmask of the detections that detection i disagrees with
    disagree = jnp.sum(jnp.where(~agree & ~jnp.eye(n, dtype=bool), bit[None, :], 0), axis=1)
    # a subset is a clique iff none of its members disagrees with another member (integer bit
    # tests: far cheaper on CPU than the equivalent (2^n, n) × (n, n) float products)
    clash = jnp.any(member & ((subsets[:, None] & disagree[None, :]) != 0), axis=1)
    size = jnp.asarray(masks_np.sum(axis=1), jnp.int32)
    score = jnp.where(clash, -1, size)
    best = jnp.argmax(score)
    best_size = score[best]
    is_best = (score == best_size)[:, None]
    common = jnp.all(jnp.where(is_best, member, True), axis=0)
    return member[best], common, best_size


def _wahba(v_cam, r_icrs, weights):
    """Rotation C (3, 3) minimising Σ w |v − C r|² (the shared SVD solution of Wahba's problem)."""
    return solve_wahba(v_cam, r_icrs, weights)


def attitude_check(det_vectors, members, cand_rows, catalog_vectors, *, sigmas: float,
                   min_tol_rad: float, max_tol_rad: float, ambiguity_rad: float,
                   scene_vectors=None, scene_valid=None, outlier_sigmas: float | None = None,
                   outlier_min_others: int = 5, nearby=None):
    """Final check of a verified cluster against the attitude it implies (extension).

    Each member is predicted from a Wahba fit to the *other* members (leave-one-out: a wrong member
    cannot pull the fit). It keeps its id only when its candidate is then the catalog star nearest the
    detection, within a tolerance, with no other catalog star within ``ambiguity_rad`` (close pairs,
    0.05°–0.2° apart, can swap ids while every pair angle agrees within ε). Tolerance ``sigmas`` × σ̂,
    σ̂ = median member residual under the all-member fit / 1.1774 (median radius of a 2-D Gaussian),
    clipped to [``min_tol_rad``, ``max_tol_rad``]. The member must also be the scene detection nearest
    its star's predicted position and the only one within ``ambiguity_rad`` of it (all detections, not
    only the N brightest), which refuses a false star next to a catalog star detected below the N
    brightest.

    Outlier test (``outlier_sigmas``): the all-member σ̂ is inflated by a wrong member itself, so each
    member is also tested against a *clean* scale σ̂ᵢ from the other members' residuals under the fit
    without it: median radius / 1.1774 / √(1 − 1.5/n') (n' other members; a 3-parameter fit to 2n'
    coordinates shrinks in-sample residuals), within ``outlier_sigmas`` × σ̂ᵢ (same clipping). Being
    tighter, it also drops true stars, so it applies only when n' ≥ ``outlier_min_others``
    (docs/design/mlv.md).

    Args:
        det_vectors: (n, 3) detection directions (camera frame).
        members: (n,) bool cluster members.
        cand_rows: (n,) int32 catalog row of each detection's candidate.
        catalog_vectors: (M, 3) ICRS unit vectors of the whole identification catalog.
        sigmas: tolerance in units of the estimated per-axis position noise σ̂.
        min_tol_rad, max_tol_rad: bounds of the tolerance (rad).
        ambiguity_rad: a second catalog star this close (rad) makes the detection ambiguous.
        scene_vectors: (m, 3) all detections of the scene (camera frame), the first n being
            ``det_vectors``; ``None``: ``det_vectors`` only.
        scene_valid: (m,) bool, real detections among ``scene_vectors``.
        outlier_sigmas: the outlier test's tolerance in units of σ̂ᵢ; ``None``: no outlier test.
        outlier_min_others: the outlier test applies to a member with at least this many others.
        nearby: ``(rows, vectors)``, (K,) int32 catalog rows and (K, 3) ICRS vectors of every star
            that can lie near the field (:func:`jstarid.sky_index.local_stars` around the cluster's
            boresight; padding vectors far from it): the nearest-star and ambiguity tests search
            these instead of the whole catalog (same answer wherever a member can pass: its star
            and every star within the tolerance of it are near the field), K ≪ M on a deep
            catalog. ``None``: the whole catalog.

    Returns:
        (n,) bool members that pass.
    """
    n = det_vectors.shape[0]
    r = catalog_vectors[jnp.maximum(cand_rows, 0)]
    w = members.astype(det_vectors.dtype)
    full = _wahba(det_vectors, r, w)
    resid = angle_between(precise.matmul(det_vectors, full), r)  # (n,)
    big = jnp.asarray(jnp.inf, det_vectors.dtype)
    med = jnp.nanmedian(jnp.where(members, resid, jnp.nan))
    sigma = jnp.where(jnp.isfinite(med), med, big) / 1.1774
    tol = jnp.clip(sigmas * sigma, min_tol_rad, max_tol_rad)
    loo_w = w[None, :] * (1.0 - jnp.eye(n, dtype=w.dtype))  # (n, n): fit without member i
    loo = jax.vmap(_wahba, in_axes=(None, None, 0))(det_vectors, r, loo_w)  # (n, 3, 3)
    pred = precise.einsum("ni,nij->nj", det_vectors, loo)  # rows: C_iᵀ v_i in ICRS
    search_rows, search_vectors = ((jnp.arange(catalog_vectors.shape[0]), catalog_vectors)
                                   if nearby is None else nearby)
    cos = precise.matmul(pred, search_vectors.T)  # (n, K)
    nearest = jnp.argmax(cos, axis=1)  # two argmax passes: cheaper than top_k on CPU
    cos2 = jnp.max(jnp.where(jnp.arange(cos.shape[1])[None, :] == nearest[:, None], -2.0, cos), axis=1)
    ang1 = angle_between(pred, search_vectors[nearest])
    near = search_rows[nearest]
    # cos2 only decides "within ambiguity_rad": compare cosines (no precision needed here)
    if scene_vectors is None:
        scene_vectors, scene_valid = det_vectors, members
    star_cam = precise.einsum("nij,nj->ni", loo, r)  # C_i r_i: where star i should appear (camera)
    to_det = jnp.where(scene_valid[None, :], precise.matmul(star_cam, scene_vectors.T), -2.0)  # (n, m)
    own = jnp.argmax(to_det, axis=1) == jnp.arange(n)
    # …and the only detection within ambiguity_rad of it: two spots on one star's position (a
    # false star on top of it) leave the pairing to chance
    others = jnp.sum(to_det >= math.cos(ambiguity_rad), axis=1) - 1
    own &= others == 0
    if outlier_sigmas is not None:
        # residual of every member k under each leave-one-out fit i: (i, k)
        res_loo = angle_between(precise.einsum("nij,kj->nki", loo, r), det_vectors[None, :, :])
        other = members[None, :] & ~jnp.eye(n, dtype=bool)
        n_other = jnp.sum(other, axis=1)
        med_i = jnp.nanmedian(jnp.where(other, res_loo, jnp.nan), axis=1)
        shrink = jnp.sqrt(1.0 - 1.5 / jnp.maximum(n_other, 2).astype(det_vectors.dtype))
        sigma_i = med_i / 1.1774 / shrink
        sigma_i = jnp.where(jnp.isfinite(sigma_i), sigma_i, big)
        tol_i = jnp.clip(outlier_sigmas * sigma_i, min_tol_rad, max_tol_rad)
        own &= (ang1 <= tol_i) | (n_other < outlier_min_others)
    return (members & own & (near == cand_rows) & (ang1 <= tol)
            & (cos2 < math.cos(ambiguity_rad)))


def fit_attitude(det_vectors, members, cand_rows, catalog_vectors):
    """(3, 3) attitude C (ICRS → camera, v = C r) fitted to the members (Wahba / SVD)."""
    r = catalog_vectors[jnp.maximum(cand_rows, 0)]
    return _wahba(det_vectors, r, members.astype(det_vectors.dtype))


def field_check(att, scene_vectors, scene_valid, catalog_vectors, camera, n: int, tol_rad: float):
    """How many of the n brightest catalog stars predicted in the field are seen (extension).

    Under the right attitude the brightest catalog stars in the frame are nearly all detected; under a
    wrong one (a chance match of one triangle, which a three-member cluster cannot exclude) only the
    cluster's own stars are.

    Args:
        att: (3, 3) attitude C (v = C r).
        scene_vectors: (m, 3) all detections (camera frame); scene_valid: (m,) bool.
        catalog_vectors: (M, 3) ICRS catalog, rows sorted brightest first, or the stars near the
            field in that order (:func:`jstarid.sky_index.local_stars`: same answer, padding behind
            the camera).
        camera: the :class:`~jstarid.camera.Camera` (static).
        n: how many predicted stars to test.
        tol_rad: a detection within this angle (rad) confirms a predicted star.

    Returns:
        ``(n_predicted, n_confirmed)``: scalar int32 counts.
    """
    v = precise.matmul(catalog_vectors, att.T)  # (M, 3) camera frame
    _, in_field = camera.project(v)
    # the n brightest in the frame: the rows where the running in-field count reaches 1, …, n (n
    # binary searches: much cheaper on CPU than jnp.nonzero's scatter over the whole catalog)
    running = jnp.cumsum(in_field, dtype=jnp.int32)
    rows = jnp.searchsorted(running, jnp.arange(1, n + 1, dtype=jnp.int32), side="left")
    predicted = rows < in_field.shape[0]
    rows = jnp.where(predicted, rows, -1)
    cos = precise.matmul(v[jnp.maximum(rows, 0)], scene_vectors.T)  # (n, m)
    seen = jnp.any(scene_valid[None, :] & (cos >= math.cos(tol_rad)), axis=1)
    return jnp.sum(predicted, dtype=jnp.int32), jnp.sum(predicted & seen, dtype=jnp.int32)
