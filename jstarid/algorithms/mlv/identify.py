"""MLV identification: initial match by triangle voting, then pair-angle verification (paper §2.3).

``identify`` is the thin host shell (chunking over the batch, candidate-buffer reallocation); the
core ``identify_scene`` is a pure per-scene function of arrays, vmapped over scenes and jit-compiled
with the config, buffer size and camera static.

Per scene (Algorithm 1):
1. the N brightest valid detections (scenes are sorted brightest first) → camera-frame unit
   vectors (eqs. 5–6, via the camera's pinhole model);
2. their C(N, 3) triangles → singular values → v̂1, v̂2 (eqs. 1–4);
3. candidate database triangles with |v̂1ˢ − v̂1ᶜ| ≤ Th1, |v̂2ˢ − v̂2ᶜ| ≤ Th2 (eq. 7) in a buffer
   of K per triangle; a triangle with more than K candidates is flagged and casts no vote;
4. vote counters per detection over the reference catalog; candidate = most votes;
5. verification (eq. 8): largest cluster of pairwise-agreeing candidates; success when it has at
   least ``ver_min`` members; only its members get ids.

Extensions (on by default, see :class:`~jstarid.algorithms.mlv.Config`): in step 3 a side-angle
check and vertex correspondence (each detection votes only for its corresponding star); after step 5
a leave-one-out attitude check of every member and a check that the brightest catalog stars the
attitude puts in the frame are seen. ``vertex_match=False, attitude_check=False,
field_check=False`` runs the paper's algorithm alone.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jstarid.algorithms.mlv.config import Config
from jstarid.algorithms.mlv.database import Database
from jstarid.algorithms.mlv.features import discretize, singular_values, triangle_combinations
from jstarid.algorithms.mlv.verify import (
    agreement,
    attitude_check,
    field_check,
    fit_attitude,
    largest_cluster,
)
from jstarid.algorithms.mlv.voting import (
    best_candidates,
    candidate_ranges,
    cast_matched_votes,
    cast_votes,
    gather_candidates,
    match_vertices,
)
from jstarid.scene import Identification, Scene

__all__ = ["Diagnostics", "identify", "identify_with_diagnostics", "identify_scene"]


class Diagnostics(NamedTuple):
    """Per-scene internals of :func:`identify_with_diagnostics` (batch axis first).

    Attributes:
        candidate_overflow: (B,) bool, some triangle had more candidates than the buffer held (it
            cast no votes).
        n_overflow_triangles: (B,) int32 such triangles.
        n_candidates: (B, T) int32 candidate count of each of the T = C(N, 3) triangles (before
            the buffer), 0 for triangles with a padding vertex.
        candidates: (B, N) int32 catalog row voted for each of the N brightest detections (−1 none).
        votes: (B, N) int32 votes of that candidate.
        cluster_size: (B,) int32 size of the largest verified cluster.
        field_predicted, field_seen: (B,) int32 catalog stars the field check predicted in the
            frame (≤ N) and how many of them a detection confirmed (0 when the check is off).
        capacity: the candidate buffer K finally used (host int).
    """

    candidate_overflow: jax.Array
    n_overflow_triangles: jax.Array
    n_candidates: jax.Array
    candidates: jax.Array
    votes: jax.Array
    cluster_size: jax.Array
    field_predicted: jax.Array
    field_seen: jax.Array
    capacity: int


def identify_scene(xy, valid, db: Database, config: Config, capacity: int, all_xy=None,
                   all_valid=None):
    """Identify one scene (pure, jit-able).

    Args:
        xy: (N, 2) float32 centroids (px) of the N brightest detections, brightest first.
        valid: (N,) bool, a real detection.
        all_xy, all_valid: (M, 2), (M,) every detection of the scene (the first N being ``xy``),
            for the attitude check's nearest-detection test; ``None``: the N brightest only.
        db: :class:`~jstarid.algorithms.mlv.Database` (its camera turns pixels into directions).
        config: :class:`~jstarid.algorithms.mlv.Config` (static).
        capacity: K, candidate buffer per triangle (static).

    Returns:
        dict of per-scene arrays: ``ids`` (N,) int32 catalog rows (−1 = not identified), ``ok``,
        ``attitude`` (3, 3) C fitted to the named stars (Wahba; NaN when not ``ok``),
        ``overflow``, ``n_overflow``, ``n_candidates`` (T,), ``candidates`` (N,), ``votes`` (N,),
        ``cluster_size``.
    """
    n = xy.shape[0]
    n_ref = db.star_rows.shape[0]
    vec = db.camera.unproject(xy)  # (N, 3) camera frame, eqs. 5–6
    combos = jnp.asarray(triangle_combinations(n))  # (T, 3)
    tri_valid = jnp.all(valid[combos], axis=1)
    sv = singular_values(vec[combos[:, 0]], vec[combos[:, 1]], vec[combos[:, 2]])  # eqs. 1–3
    v1h, v2h = discretize(sv[:, 0], sv[:, 1], db.dv1, db.dv2)  # eq. 4
    start, count = candidate_ranges(db.keys, v1h, v2h, th1=config.th1, th2=config.th2,
                                    v1_offset=db.v1_offset, stride=db.stride, n_rows=db.n_rows)
    index, cand_valid, overflow, total = jax.vmap(gather_candidates, in_axes=(0, 0, None))(
        start, count, capacity)  # eq. 7
    overflow &= tri_valid
    # overflowing triangles are ambiguous (many matches) and would vote for an arbitrary subset
    cand_valid &= (tri_valid & ~overflow)[:, None]
    cand_stars = db.triangles[index]  # (T, K, 3)
    if config.vertex_match:  # extension: side check + vertex correspondence
        vertex, side_ok = match_vertices(vec[combos], db.sides[index], config.side_tol_rad)
        tri_det = jnp.take_along_axis(combos, vertex, axis=1)  # ↔ candidate stars 0, 1, 2
        votes = cast_matched_votes(tri_det, cand_stars, cand_valid & side_ok, n, n_ref)
    else:  # the paper's voting (Fig. 3)
        votes = cast_votes(combos, cand_stars, cand_valid, n, n_ref)
    cand, n_votes, _ = best_candidates(votes)
    has_cand = valid & (n_votes >= config.min_votes)
    agree = agreement(vec, db.star_vectors[cand], cand, has_cand, config.eps_rad)  # eq. 8
    first, common, size = largest_cluster(agree)
    members = (common if config.require_unique_cluster else first) & has_cand
    if config.attitude_check:
        members = attitude_check(
            vec, members, db.star_rows[cand], db.catalog_vectors, sigmas=config.residual_sigmas,
            min_tol_rad=math.radians(config.residual_min_deg),
            max_tol_rad=math.radians(config.residual_max_deg),
            ambiguity_rad=math.radians(config.ambiguity_deg),
            scene_vectors=None if all_xy is None else db.camera.unproject(all_xy),
            scene_valid=all_valid)
    ok = jnp.sum(members) >= config.ver_min
    att = fit_attitude(vec, members, db.star_rows[cand], db.catalog_vectors)
    if config.field_check:
        scene_vec = vec if all_xy is None else db.camera.unproject(all_xy)
        scene_ok = valid if all_xy is None else all_valid
        n_pred, n_seen = field_check(att, scene_vec, scene_ok, db.catalog_vectors, db.camera, n,
                                     math.radians(config.residual_max_deg))
        ok &= n_seen >= jnp.ceil(config.field_check_fraction * n_pred)
    else:
        n_pred = n_seen = jnp.int32(0)
    ids = jnp.where(ok & members, db.star_rows[cand], -1)
    return {
        "ids": ids.astype(jnp.int32), "ok": ok, "overflow": jnp.any(overflow),
        "attitude": jnp.where(ok, att, jnp.nan).astype(jnp.float32),
        "n_overflow": jnp.sum(overflow, dtype=jnp.int32),
        "n_candidates": jnp.where(tri_valid, total, 0),
        "candidates": jnp.where(has_cand, db.star_rows[cand], -1), "votes": n_votes,
        "cluster_size": size, "field_predicted": n_pred, "field_seen": n_seen,
    }


@functools.partial(jax.jit, static_argnames=("config", "capacity"))
def _identify_batch(xy, valid, all_xy, all_valid, db, config, capacity):
    return jax.vmap(identify_scene, in_axes=(0, 0, None, None, None, 0, 0))(
        xy, valid, db, config, capacity, all_xy, all_valid)


def _kernel_config(config: Config) -> Config:
    """The config with the fields the compiled kernel does not read set to their defaults, so that
    configs differing only in buffers, chunking or database settings share one compilation."""
    return dataclasses.replace(config, candidate_capacity=256, max_candidate_capacity=1024,
                               batch_chunk=500, n_boresights=100_000, database_roll_deg=None)


def _brightest(scenes: Scene, n: int):
    """(B, n, 2) xy and (B, n) valid of the n brightest detections (padded when capacity < n)."""
    xy, valid = scenes.xy[:, :n], scenes.valid[:, :n]
    if xy.shape[1] < n:
        pad = n - xy.shape[1]
        xy = jnp.pad(xy, ((0, 0), (0, pad), (0, 0)))
        valid = jnp.pad(valid, ((0, 0), (0, pad)))
    return xy.astype(jnp.float32), valid


def identify_with_diagnostics(database: Database, scenes: Scene,
                              config: Config | None = None):
    """:func:`identify` plus its :class:`Diagnostics`.

    Scenes are processed in chunks of ``config.batch_chunk`` (the last chunk padded, so one
    compilation serves any batch size above it). When a chunk flags a candidate overflow, it is
    recomputed with a doubled buffer, up to ``config.max_candidate_capacity``; overflow remaining at
    that bound is reported in the diagnostics and with a warning.
    """
    config = Config() if config is None else config
    # build statistics are static metadata: drop them so cached and fresh databases share a compile
    database = dataclasses.replace(database, info=())
    b, cap = scenes.batch_size, scenes.capacity
    xy, valid = _brightest(scenes, config.n_stars)
    all_xy, all_valid = scenes.xy.astype(jnp.float32), scenes.valid
    if all_xy.shape[1] < config.n_stars:
        all_xy, all_valid = xy, valid
    chunk = min(config.batch_chunk, b)
    outs, k_used = [], config.candidate_capacity
    for lo in range(0, b, chunk):
        hi = min(lo + chunk, b)
        cxy, cvalid = xy[lo:hi], valid[lo:hi]
        axy, avalid = all_xy[lo:hi], all_valid[lo:hi]
        if hi - lo < chunk:  # pad the last chunk to the compiled shape with empty scenes
            pad = chunk - (hi - lo)
            cxy = jnp.pad(cxy, ((0, pad), (0, 0), (0, 0)))
            cvalid = jnp.pad(cvalid, ((0, pad), (0, 0)))
            axy = jnp.pad(axy, ((0, pad), (0, 0), (0, 0)))
            avalid = jnp.pad(avalid, ((0, pad), (0, 0)))
        k = config.candidate_capacity
        while True:
            out = _identify_batch(cxy, cvalid, axy, avalid, database, _kernel_config(config), k)
            if not bool(jnp.any(out["overflow"])) or k >= config.max_candidate_capacity:
                break
            k = min(2 * k, config.max_candidate_capacity)
        k_used = max(k_used, k)
        outs.append(jax.tree_util.tree_map(lambda a, n=hi - lo: a[:n], out))
    out = {key: jnp.concatenate([o[key] for o in outs]) for key in outs[0]}
    if bool(jnp.any(out["overflow"])):
        warnings.warn(f"MLV: {int(jnp.sum(out['overflow']))} scenes had triangles with more than "
                      f"{config.max_candidate_capacity} candidates (those triangles cast no vote)",
                      stacklevel=2)
    n = config.n_stars
    ids = jnp.full((b, cap), -1, jnp.int32).at[:, : min(n, cap)].set(out["ids"][:, :cap])
    result = Identification(ids=ids, ok=out["ok"], attitude=out["attitude"])
    diag = Diagnostics(candidate_overflow=out["overflow"], n_overflow_triangles=out["n_overflow"],
                       n_candidates=out["n_candidates"], candidates=out["candidates"],
                       votes=out["votes"], cluster_size=out["cluster_size"],
                       field_predicted=out["field_predicted"], field_seen=out["field_seen"],
                       capacity=k_used)
    return result, diag


def identify(database: Database, scenes: Scene, config: Config | None = None) -> Identification:
    """Identify a batch of scenes with the multilayer voting algorithm (SPEC §4).

    Args:
        database: from :func:`~jstarid.algorithms.mlv.build_database` (same camera as the scenes).
        scenes: :class:`~jstarid.scene.Scene` batch (B, capacity).
        config: :class:`~jstarid.algorithms.mlv.Config`; the default is the paper's parameters.

    Returns:
        :class:`~jstarid.scene.Identification` with ``ids`` (B, capacity) aligned with the scene's
        detections (only verified cluster members among the N brightest are named, others −1),
        ``ok`` (B,) and ``attitude`` (B, 3, 3): the rotation C (ICRS → camera) fitted to the named
        stars (Wahba / SVD, equal weights), NaN where not ``ok``.
    """
    return identify_with_diagnostics(database, scenes, config)[0]


