"""MLV identification: initial match by triangle voting, then pair-angle verification (paper §2.3).

``identify`` is the host shell (chunks, buffer regrowth); ``identify_scene`` is a pure per-scene
function, vmapped over groups of ``Config.map_batch`` scenes (``lax.map`` inside one jit call per
``batch_chunk``) with config, buffer sizes and camera static. Th1, Th2, ε and the side tolerance are
traced per-scene values (:class:`Tuning`), so a grid of them is a batch axis.

Per scene (Algorithm 1):
1. the N brightest valid detections → camera-frame unit vectors (eqs. 5–6);
2. their C(N, 3) triangles → singular values → v̂1, v̂2 (eqs. 1–4);
3. candidate database triangles with |v̂1ˢ − v̂1ᶜ| ≤ Th1, |v̂2ˢ − v̂2ᶜ| ≤ Th2 (eq. 7) in one shared
   buffer of P slots; a triangle with more than K = ``candidate_capacity`` candidates casts no vote
   (flagged; the host retries with a larger K), a scene with more than P is recomputed with a larger
   P (P never changes the result);
4. votes per detection over the reference catalog (one scatter-add); candidate = ``argmax``;
5. verification (eq. 8): the largest cluster of pairwise-agreeing candidates; success with at least
   ``ver_min`` members; only members get ids.

Extensions (on by default, :class:`~jstarid.algorithms.mlv.Config`): side-angle check and vertex
correspondence in step 3; after step 5 a leave-one-out attitude check and a field check.
``Config.paper()`` (``vertex_match=False, attitude_check=False, field_check=False``) is the paper's
algorithm.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.base import check_scenes
from jstarid.algorithms.mlv.config import Config, Tuning
from jstarid.algorithms.mlv.database import Database, window_counts
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
    gather_pool,
    observed_sides,
)
from jstarid.finishing import finish
from jstarid.runtime import (
    call_size,
    chunk_calls,
    device_cache,
    grow_until,
    next_power_of_two,
    on_every_device,
    run_calls,
    static_config,
    take_rows,
)
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Identification, Scene
from jstarid.sky_index import local_stars

__all__ = ["Buffers", "Diagnostics", "SceneResult", "candidate_buffers", "default_pool", "identify",
           "identify_grid", "identify_scene"]


class SceneResult(NamedTuple):
    """What :func:`identify_scene` returns for one scene (a leading batch axis when batched).

    Attributes:
        ids: (N,) int32 catalog rows of the N brightest detections (−1 = not identified).
        ok: () bool. overflow: () bool, some triangle had more than K candidates.
        attitude: (3, 3) float32 C fitted to the named stars (Wahba; NaN when not ``ok``).
        n_overflow: () int32 such triangles. n_candidates: (T,) int32 candidates per triangle.
        candidates: (N,) int32 catalog row voted for each detection (−1 none). votes: (N,) int32.
        cluster_size: () int32 largest verified cluster.
        field_predicted, field_seen: () int32 the field check's counts (0 when off).
        pool_total: () int32 candidates of the voting triangles.
        pool_overflow: () bool, the shared buffer P (or the side-checked buffer Q) overflowed.
    """

    ids: jax.Array
    ok: jax.Array
    overflow: jax.Array
    attitude: jax.Array
    n_overflow: jax.Array
    n_candidates: jax.Array
    candidates: jax.Array
    votes: jax.Array
    cluster_size: jax.Array
    field_predicted: jax.Array
    field_seen: jax.Array
    pool_total: jax.Array
    pool_overflow: jax.Array


class Diagnostics(NamedTuple):
    """Per-scene internals of :func:`identify` (batch axis first).

    Attributes:
        n_candidates: (B,) int32 database triangles matched (eq. 7), summed over the C(N, 3) triangles.
        overflow: (B,) bool, the scene overflowed its capacity or ``candidate_overflow``.
        candidate_overflow: (B,) bool, some triangle had more candidates than the buffer (no votes).
        n_overflow_triangles: (B,) int32 such triangles.
        triangle_candidates: (B, T) int32 candidates of each of the T = C(N, 3) triangles (before the
            buffer), 0 for triangles with a padding vertex.
        candidates: (B, N) int32 catalog row voted for each of the N brightest detections (−1 none).
        votes: (B, N) int32 votes of that candidate.
        cluster_size: (B,) int32 size of the largest verified cluster.
        field_predicted, field_seen: (B,) int32 catalog stars the field check predicted in the frame
            (≤ N) and how many a detection confirmed (0 when off).
        capacity: the candidate buffer K finally used (host int).
    """

    n_candidates: jax.Array
    overflow: jax.Array
    candidate_overflow: jax.Array
    n_overflow_triangles: jax.Array
    triangle_candidates: jax.Array
    candidates: jax.Array
    votes: jax.Array
    cluster_size: jax.Array
    field_predicted: jax.Array
    field_seen: jax.Array
    capacity: int


_REDO = 8  # scenes per recomputation with the full candidate buffer


def default_pool(config: Config, th1_max: int | None = None, th2_max: int | None = None,
                 capacity: int | None = None, n_db_triangles: int | None = None,
                 window_mean: float | None = None) -> int:
    """Default P of the shared per-scene candidate buffer (:func:`~.voting.gather_pool`).

    About 7 slots per query triangle per feature-window cell ((2·Th1 + 1)(2·Th2 + 1) cells; P = 8,192
    for the default database at N = 10, Th = 1, docs/design/mlv.md), scaled by Δv1·Δv2 (the cell's area)
    and by ``n_db_triangles`` relative to the default mlv2021 database's 167,655 (``None``: no scaling);
    at least 1.25 × T × ``window_mean`` (the database's mean window, :func:`candidate_buffers`)
    where given; never more than T·K, which always suffices.

    Args:
        config: the :class:`Config` (``n_stars``, ``dv1``, ``dv2``, ``th1``, ``th2``,
            ``candidate_capacity``, ``candidate_pool``).
        th1_max, th2_max: the largest Th1, Th2 of the batch (bins); ``None``: the config's.
        capacity: K; ``None``: ``config.candidate_capacity`` (256 where that is ``None``).
        n_db_triangles: triangles in the database.
        window_mean: mean candidates per query triangle (:class:`Buffers`).

    Returns:
        P (slots), a multiple of 1,024 unless capped at T·K or set by ``config.candidate_pool``.
    """
    th1 = int(config.th1 if th1_max is None else th1_max)
    th2 = int(config.th2 if th2_max is None else th2_max)
    k = int(capacity if capacity is not None else config.candidate_capacity or CAPACITY_FLOOR)
    t = math.comb(int(config.n_stars), 3)
    if config.candidate_pool is not None:
        return min(int(config.candidate_pool), t * k)
    density = (config.dv1 * config.dv2) / (5e-5 * 5e-4)  # candidates per cell scale with Δv1·Δv2
    if n_db_triangles is not None:  # …and with the size of the database
        density *= n_db_triangles / 167_655
    p = int(7 * t * (2 * th1 + 1) * (2 * th2 + 1) * density)
    if window_mean is not None:  # a dense database: its own windows say how many come
        p = max(p, int(1.25 * t * window_mean))
    return min(-(-p // 1024) * 1024, t * k)


CAPACITY_FLOOR = 256  # K where the database asks for less (the default mlv2021 database: 159 at most)
MAX_CAPACITY_FLOOR = 1024  # … and the largest K of the retries


class Buffers(NamedTuple):
    """The candidate buffers of one :func:`identify` call (host ints).

    Attributes:
        capacity: K of the first pass. max_capacity: the largest K of the retries.
        window_mean: mean candidates per query triangle the database predicts (sizes P); ``None``
            under a set bound (not counted).
    """

    capacity: int
    max_capacity: int
    window_mean: float | None


def candidate_buffers(database: Database, config: Config, th1_max: int | None = None,
                      th2_max: int | None = None) -> Buffers:
    """K, its retry bound and the expected window size, from the config or the database's density.

    ``max_candidate_capacity=None`` (every triangle votes, the paper) sets the bound from the
    database's own triangles (:func:`~jstarid.algorithms.mlv.database.window_counts` at the batch's
    largest Th1, Th2): the power of two above their maximum, at least :data:`MAX_CAPACITY_FLOOR`;
    ``candidate_capacity=None`` then starts K at the power of two above their 99th percentile
    rather than climbing there by recompilations (``tetra3_test``: 4,096), and the shared buffer
    P follows the mean window (:func:`default_pool`). Under a set bound (the default: 256 up to
    1,024) the database is not consulted: the triangles over K cast no vote and take no room, so
    the small K and P of the papers' database are the fastest (narrow twin, 1,000 scenes: 8.3 s;
    13–14 s with P from its windows). On the papers' cameras both give 256 and 1,024. Counted once
    per database and window, on the host.
    """
    k = config.candidate_capacity
    if config.max_candidate_capacity is not None:  # a set bound: the database is not consulted
        k_max = int(config.max_candidate_capacity)
        k = min(CAPACITY_FLOOR, k_max) if k is None else int(k)
        return Buffers(capacity=k, max_capacity=max(k_max, k), window_mean=None)
    th1 = int(config.th1 if th1_max is None else th1_max)
    th2 = int(config.th2 if th2_max is None else th2_max)
    counts = device_cache.cached(database, f"mlv-window-counts-{th1}-{th2}",
                                 lambda: window_counts(database, th1, th2))
    k_max = max(MAX_CAPACITY_FLOOR, next_power_of_two(counts.max()))
    if k is None:  # every triangle votes: start where the database's windows say
        k = min(max(CAPACITY_FLOOR, next_power_of_two(np.percentile(counts, 99))), k_max)
    return Buffers(capacity=int(k), max_capacity=max(k_max, int(k)), window_mean=float(counts.mean()))


def identify_scene(xy, valid, db: Database, config: Config, capacity: int, all_xy=None,
                   all_valid=None, tuning: Tuning | None = None, *, pool: int | None = None,
                   th1_max: int | None = None):
    """Identify one scene (pure, jit-able).

    Args:
        xy: (N, 2) float32 centroids (px) of the N brightest detections, brightest first.
        valid: (N,) bool, a real detection.
        db: :class:`~jstarid.algorithms.mlv.Database` (its camera turns pixels into directions).
        config: :class:`~jstarid.algorithms.mlv.Config` (static).
        capacity: K, the most candidates a triangle may have and still vote (static).
        all_xy, all_valid: (M, 2), (M,) every detection of the scene (the first N being ``xy``), for the
            attitude check's nearest-detection test; ``None``: the N brightest only.
        tuning: traced :class:`Tuning` scalars; ``None``: the config's values.
        pool: static P, the shared candidate buffer; ``None``: T·K (never overflows). With vertex
            matching the side-checked candidates move to a buffer of Q = max(1024, P/8) slots (Q = P
            when P = T·K). Exceeding P or Q sets ``pool_overflow`` (votes incomplete; :func:`identify`
            recomputes with a doubled P, up to T·K).
        th1_max: static bound of ``tuning.th1`` (the window has 2·th1_max + 1 v̂1 rows); ``None``:
            ``config.th1``.

    Returns:
        :class:`SceneResult`.
    """
    n = xy.shape[0]
    n_ref = db.star_rows.shape[0]
    if tuning is None:
        tuning = Tuning(th1=config.th1, th2=config.th2, eps_rad=config.eps_rad,
                        side_tol_rad=config.side_tol_rad)
    th1_max = int(config.th1) if th1_max is None else int(th1_max)
    combos_np = triangle_combinations(n)
    t = combos_np.shape[0]
    pool = t * capacity if pool is None else int(pool)
    vec = db.camera.unproject(xy)  # (N, 3) camera frame, eqs. 5–6
    combos = jnp.asarray(combos_np)  # (T, 3)
    tri_valid = jnp.all(valid[combos], axis=1)
    tri_vec = vec[combos]  # (T, 3, 3)
    sv = singular_values(tri_vec[:, 0], tri_vec[:, 1], tri_vec[:, 2])  # eqs. 1–3
    v1h, v2h = discretize(sv[:, 0], sv[:, 1], db.dv1, db.dv2)  # eq. 4
    start, count = candidate_ranges(db.keys, v1h, v2h, th1=tuning.th1, th2=tuning.th2,
                                    v1_offset=db.v1_offset, stride=db.stride, n_rows=db.n_rows,
                                    th1_max=th1_max)  # eq. 7: (T, R)
    total = jnp.sum(count, axis=1)
    # a triangle with more than K candidates is ambiguous (many matches): flagged, casts no vote
    overflow = tri_valid & (total > capacity)
    votes_ok = tri_valid & ~overflow
    index, tri, cand_valid, pool_total = gather_pool(
        start, jnp.where(votes_ok[:, None], count, 0), pool)  # (P,) each
    if config.vertex_match:  # extension: side check + vertex correspondence
        vertex, obs_sides = observed_sides(tri_vec)  # (T, 3) each
        err = jnp.max(jnp.abs(db.sides[index] - obs_sides[tri]), axis=-1)  # (P,)
        keep = cand_valid & (err <= tuning.side_tol_rad)
        # only a few per cent pass the side check: move them to a buffer of Q slots before the
        # star gather and the vote scatter (Q = P in the full-buffer mode, which cannot overflow)
        q = pool if pool >= t * capacity else min(pool, max(1024, pool // 8))
        n_keep = jnp.sum(keep, dtype=jnp.int32)
        dest = jnp.where(keep, jnp.cumsum(keep, dtype=jnp.int32) - 1, q)
        slot = jnp.zeros((q,), jnp.int32).at[dest].set(
            jnp.arange(pool, dtype=jnp.int32), mode="drop", unique_indices=True)
        kept = jnp.arange(q) < n_keep
        tri_det = jnp.take_along_axis(combos, vertex, axis=1)  # ↔ candidate stars 0, 1, 2
        votes = cast_matched_votes(tri_det[tri[slot]], db.triangles[index[slot]][:, None, :],
                                   kept[:, None], n, n_ref)
        pool_overflow = (pool_total > pool) | (n_keep > q)
    else:  # the paper's voting (Fig. 3)
        votes = cast_votes(combos[tri], db.triangles[index][:, None, :], cand_valid[:, None], n,
                           n_ref)
        pool_overflow = pool_total > pool
    cand, n_votes = best_candidates(votes)
    has_cand = valid & (n_votes >= config.min_votes)
    agree = agreement(vec, db.star_vectors[cand], cand, has_cand, tuning.eps_rad)  # eq. 8
    first, common, size = largest_cluster(agree)
    members = (common if config.require_unique_cluster else first) & has_cand
    if config.attitude_check:
        # the stars near the cluster's field: the check's searches run over these K, not all M
        cluster_att = fit_attitude(vec, members, db.star_rows[cand], db.catalog_vectors)
        near_rows, near_vectors, _ = local_stars(db.sky_cells, db.catalog_vectors, cluster_att[2],
                                                 db.sky_grid)
        members = attitude_check(
            vec, members, db.star_rows[cand], db.catalog_vectors, sigmas=config.residual_sigmas,
            min_tol_rad=math.radians(config.residual_min_deg),
            max_tol_rad=math.radians(config.residual_max_deg),
            ambiguity_rad=math.radians(config.ambiguity_deg),
            scene_vectors=None if all_xy is None else db.camera.unproject(all_xy),
            scene_valid=all_valid,
            outlier_sigmas=config.outlier_sigmas if config.outlier_sigmas > 0 else None,
            outlier_min_others=config.outlier_min_others, nearby=(near_rows, near_vectors))
    ok = jnp.sum(members) >= config.ver_min
    att = fit_attitude(vec, members, db.star_rows[cand], db.catalog_vectors)
    if config.field_check:
        scene_vec = vec if all_xy is None else db.camera.unproject(all_xy)
        scene_ok = valid if all_xy is None else all_valid
        _, field_vectors, _ = local_stars(db.sky_cells, db.catalog_vectors, att[2], db.sky_grid)
        n_pred, n_seen = field_check(att, scene_vec, scene_ok, field_vectors, db.camera, n,
                                     math.radians(config.residual_max_deg))
        ok &= n_seen >= jnp.ceil(config.field_check_fraction * n_pred)
    else:
        n_pred = n_seen = jnp.int32(0)
    ids = jnp.where(ok & members, db.star_rows[cand], -1)
    return SceneResult(
        ids=ids.astype(jnp.int32), ok=ok, overflow=jnp.any(overflow),
        attitude=jnp.where(ok, att, jnp.nan).astype(jnp.float32),
        n_overflow=jnp.sum(overflow, dtype=jnp.int32), n_candidates=jnp.where(tri_valid, total, 0),
        candidates=jnp.where(has_cand, db.star_rows[cand], -1), votes=n_votes, cluster_size=size,
        field_predicted=n_pred, field_seen=n_seen, pool_total=pool_total, pool_overflow=pool_overflow)


@functools.partial(stored_jit, static_argnames=("config", "capacity", "pool", "th1_max"))
def _identify_batch(xy, valid, all_xy, all_valid, tuning, db, config, capacity, pool, th1_max):
    def one(args):
        xy, valid, all_xy, all_valid, tuning = args
        return identify_scene(xy, valid, db, config, capacity, all_xy, all_valid, tuning,
                              pool=pool, th1_max=th1_max)

    args = (xy, valid, all_xy, all_valid, tuning)
    if xy.shape[0] <= config.map_batch:
        return jax.vmap(one)(args)
    # vmapped groups of map_batch scenes in a loop: the (group, P) candidate arrays stay in cache
    return jax.lax.map(one, args, batch_size=config.map_batch)


# the fields the kernel does not read as static (buffers, chunking, database settings, the traced
# Tuning tolerances, the finishing stage): configs that differ only there share a compilation
_NOT_COMPILED = ("candidate_capacity", "max_candidate_capacity", "candidate_pool", "batch_chunk",
                 "n_boresights", "database_roll_deg", "th1", "th2", "eps_deg", "side_tol_deg", "finishing")


def _brightest(scenes: Scene, n: int):
    """(B, n, 2) xy and (B, n) valid of the n brightest detections (padded when capacity < n)."""
    xy, valid = scenes.xy[:, :n], scenes.valid[:, :n]
    if xy.shape[1] < n:
        pad = n - xy.shape[1]
        xy = jnp.pad(xy, ((0, 0), (0, pad), (0, 0)))
        valid = jnp.pad(valid, ((0, 0), (0, pad)))
    return xy.astype(jnp.float32), valid


def _per_scene(value, b: int, dtype):
    """(b,) array of a scalar or (b,) per-scene value."""
    a = jnp.asarray(value, dtype)
    if a.ndim == 0:
        return jnp.full((b,), a, dtype)
    if a.shape != (b,):
        raise ValueError(f"per-scene values must be scalars or ({b},) arrays, got {a.shape}")
    return a


def identify(database: Database, scenes: Scene, config: Config | None = None, *,
             diagnostics: bool = False, tuning: Tuning | None = None):
    """Identify a batch of scenes with the multilayer voting algorithm.

    Chunks of ``config.batch_chunk`` scenes (the last padded: one compilation for any larger batch).
    A chunk with a candidate overflow (a triangle with more than K candidates) is recomputed with a
    doubled K up to the largest K (:func:`candidate_buffers`: the config's bound, whose excess is a
    rule counted in the diagnostics, or, where every triangle votes, what the database's own
    windows hold, whose excess is also warned about); scenes that exceed the shared buffer P
    (:func:`default_pool`) are recomputed with a doubled P up to T·K, so the result never depends
    on P.

    Then the finishing stage (``Config.finishing``, :func:`jstarid.finishing.finish`; off in
    ``Config.paper()``): the scenes left unsolved are tried again under focal lengths 1–2 % off (the
    triangle features are angles, and a focal length off by 1 % moves them past the tolerances), and
    every solved scene's names are checked against a fit of the attitude and the focal length,
    which sets ``focal_scale``. Diagnostics describe the first pass.

    Args:
        database: from :func:`~jstarid.algorithms.mlv.build_database` (same camera as the scenes).
        scenes: :class:`~jstarid.scene.Scene` batch (B, capacity).
        config: :class:`~jstarid.algorithms.mlv.Config`; ``None``: ``Config()``.
        diagnostics: also return the :class:`Diagnostics`.
        tuning: :class:`~jstarid.algorithms.mlv.Tuning` whose leaves are scalars or (B,) arrays (Th1,
            Th2 in bins; ε, side tolerance in rad); ``None``: ``config.tuning()``. Traced: one
            compilation per max Th1 (which sets the window's shape) serves a grid.

    Returns:
        :class:`~jstarid.scene.Identification`: ``ids`` (B, capacity) aligned with the detections (only
        verified cluster members among the N brightest are named, others −1), ``ok`` (B,) and
        ``attitude`` (B, 3, 3) C (ICRS → camera) fitted to the named stars (Wahba, equal weights), NaN
        where not ``ok``; with ``diagnostics``, ``(Identification, Diagnostics)``.
    """
    config = Config() if config is None else config
    check_scenes(scenes)
    out = _identify(database, scenes, config, diagnostics=diagnostics, tuning=tuning)
    result, diag = out if diagnostics else (out, None)
    tuning = config.tuning() if tuning is None else tuning

    def rerun(moved, rows):  # per-scene tolerances (a grid) follow their scenes
        sub = jax.tree.map(lambda t: t[rows] if np.ndim(t) else t, tuning)
        return _identify(database, moved, config, tuning=sub)

    result = finish(result, scenes, config.finishing, rerun=rerun, camera=database.camera,
                    star_vectors=database.catalog_vectors, star_mags=database.catalog_mags).result
    return (result, diag) if diagnostics else result


def _identify(database: Database, scenes: Scene, config: Config, *, diagnostics: bool = False,
              tuning: Tuning | None = None):
    """:func:`identify`'s voting and verification on one set of centroids (no focal search)."""
    # build statistics are static metadata: drop them so cached and fresh databases share a compile
    stripped = dataclasses.replace(database, info=(), key="")
    caller_database = database  # the buffers' counts are kept with the caller's database
    # placed on every device once (kept on the caller's database), not copied on each chunk's call
    database = (on_every_device(database, "mlv_identify", lambda: stripped) if jax.local_device_count() > 1
                else stripped)
    b, cap = scenes.batch_size, scenes.capacity
    if b == 0:  # nothing to identify: an empty result of the usual shapes
        return _empty(cap, config, scenes.overflow, diagnostics)
    tuning = config.tuning() if tuning is None else tuning
    tuning = Tuning(
        th1=_per_scene(tuning.th1, b, jnp.int32), th2=_per_scene(tuning.th2, b, jnp.int32),
        eps_rad=_per_scene(tuning.eps_rad, b, jnp.float32),
        side_tol_rad=_per_scene(tuning.side_tol_rad, b, jnp.float32))
    if bool(jnp.any(tuning.th1 < 0)) or bool(jnp.any(tuning.th2 < 0)):
        raise ValueError("th1 and th2 must be ≥ 0")
    th1_max, th2_max = int(jnp.max(tuning.th1)), int(jnp.max(tuning.th2))
    buffers = candidate_buffers(caller_database, config, th1_max, th2_max)
    xy, valid = _brightest(scenes, config.n_stars)
    all_xy, all_valid = scenes.xy.astype(jnp.float32), scenes.valid
    if all_xy.shape[1] < config.n_stars:
        all_xy, all_valid = xy, valid
    batched = jax.tree.map(np.asarray, (xy, valid, all_xy, all_valid, tuning))
    t = math.comb(config.n_stars, 3)
    chunk = call_size(b, config.batch_chunk)
    static = dict(config=static_config(config, _NOT_COMPILED), th1_max=th1_max)
    per_scene = dict(ids=(config.n_stars,), attitude=(3, 3), n_candidates=(t,),
                     candidates=(config.n_stars,), votes=(config.n_stars,))  # the rest are scalars
    tails = [per_scene.get(field, ()) for field in SceneResult._fields]
    out = None
    capacity_of = np.zeros((b,), np.int64)  # the candidate buffer K each scene was last run with
    pool_of = np.zeros((b,), np.int64)

    def run(rows, k, pool, size):
        nonlocal out
        # the scenes split over every device (one per CPU core after js.use_cpu_cores())
        out = run_calls(_identify_batch, chunk_calls(rows, size), lambda c: take_rows(batched, c),
                        (database,), static=dict(static, capacity=k, pool=pool), n_rows=b,
                        tails=tails, fills=[0] * len(tails), out=out)
        capacity_of[rows], pool_of[rows] = k, pool
        return SceneResult(*out).overflow[rows]

    # a triangle with more than K candidates is flagged: those scenes run again with a doubled K,
    # up to the largest K (K changes nothing for scenes that never overflow it)
    k_used = grow_until(
        lambda k, rows: run(rows, k, default_pool(config, th1_max, th2_max, k, database.n_triangles,
                                                  buffers.window_mean), chunk),
        np.arange(b), buffers.capacity, buffers.max_capacity)
    # rare (≈ 0.2 % of scenes): candidates beyond the shared buffer P; those scenes run again with a
    # doubled P, up to P = T·K (which cannot overflow), _REDO scenes per call
    while True:
        redo = np.flatnonzero(SceneResult(*out).pool_overflow & (pool_of < t * capacity_of))
        if not redo.size:
            break
        for k in np.unique(capacity_of[redo]):
            rows = redo[capacity_of[redo] == k]
            for pool in np.unique(pool_of[rows]):
                sub = rows[pool_of[rows] == pool]
                run(sub, int(k), int(min(2 * pool, t * k)), _REDO)
    out = SceneResult(*(jnp.asarray(value) for value in out))
    # a bound the config sets is a rule (too ambiguous to vote, counted in the diagnostics); the
    # database's own bound should hold every window, so a triangle beyond it is news
    if config.max_candidate_capacity is None and bool(jnp.any(out.overflow)):
        warnings.warn(f"MLV: {int(jnp.sum(out.overflow))} scenes had triangles with more than "
                      f"{buffers.max_capacity} candidates (those triangles cast no vote)",
                      stacklevel=2)
    n = config.n_stars
    ids = jnp.full((b, cap), -1, jnp.int32).at[:, : min(n, cap)].set(out.ids[:, :cap])
    result = Identification(ids=ids, ok=out.ok, attitude=out.attitude)
    if not diagnostics:
        return result
    diag = Diagnostics(n_candidates=jnp.sum(out.n_candidates, axis=1, dtype=jnp.int32),
                       overflow=out.overflow | scenes.overflow,
                       candidate_overflow=out.overflow, n_overflow_triangles=out.n_overflow,
                       triangle_candidates=out.n_candidates, candidates=out.candidates,
                       votes=out.votes, cluster_size=out.cluster_size,
                       field_predicted=out.field_predicted, field_seen=out.field_seen,
                       capacity=k_used)
    return result, diag



def _empty(capacity: int, config: Config, overflow, diagnostics: bool):
    """:func:`identify`'s result for a batch of 0 scenes."""
    result = Identification(ids=jnp.zeros((0, capacity), jnp.int32), ok=jnp.zeros((0,), bool),
                            attitude=jnp.zeros((0, 3, 3), jnp.float32))
    if not diagnostics:
        return result
    n, t = config.n_stars, math.comb(config.n_stars, 3)
    zeros = functools.partial(jnp.zeros, dtype=jnp.int32)
    return result, Diagnostics(
        n_candidates=zeros((0,)), overflow=jnp.asarray(overflow, bool),
        candidate_overflow=jnp.zeros((0,), bool), n_overflow_triangles=zeros((0,)),
        triangle_candidates=zeros((0, t)), candidates=zeros((0, n)), votes=zeros((0, n)),
        cluster_size=zeros((0,)), field_predicted=zeros((0,)), field_seen=zeros((0,)),
        capacity=config.candidate_capacity or CAPACITY_FLOOR)


# the Config fields behind Tuning's leaves (Config.tuning)
_TUNING_FIELDS = ("th1", "th2", "eps_deg", "side_tol_deg")


def identify_grid(database: Database, scenes: Scene, configs) -> list[Identification]:
    """:func:`identify` with each of ``configs`` in one batch: the grid is a batch axis.

    The scenes are repeated once per config and each copy gets its config's :class:`Tuning` as
    per-scene arrays, so one compilation (per largest Th1) and one pass serve the grid. The result
    for each config equals ``identify(database, scenes, config)``.

    Args:
        database: the database (its fields fixed for every config).
        scenes: (B, N) scenes.
        configs: :class:`Config` s that differ only in the traced tolerances (``th1``, ``th2``,
            ``eps_deg``, ``side_tol_deg``).

    Returns:
        One (B, N) :class:`~jstarid.scene.Identification` per config, in order.

    Raises:
        ValueError: configs that differ in another field (run those as separate ``identify`` calls).
    """
    configs = list(configs)
    base = configs[0]
    for config in configs[1:]:
        if dataclasses.replace(config, **{f: getattr(base, f) for f in _TUNING_FIELDS}) != base:
            raise ValueError("identify_grid: configs may differ only in "
                             f"{', '.join(_TUNING_FIELDS)}; run other settings separately")
    g, b = len(configs), scenes.batch_size
    tiled = jax.tree.map(lambda a: np.concatenate([np.asarray(a)] * g), scenes)
    per_config = [c.tuning() for c in configs]
    tuning = Tuning(*(np.repeat(np.asarray([getattr(t, f) for t in per_config]), b)
                      for f in Tuning._fields))
    result = identify(database, tiled, base, tuning=tuning)
    return [result[i * b:(i + 1) * b] for i in range(g)]
