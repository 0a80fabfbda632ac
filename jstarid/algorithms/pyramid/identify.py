"""Pyramid identification (Mortari et al. 2004), batched and jit-compiled.

Per scene (:func:`identify_scene`; the T triples of a scene are vmapped, scenes run in groups of
``Config.map_chunk`` inside one jit call per ``Config.batch_chunk`` scenes):

1. the N brightest valid detections → camera-frame unit vectors; triples (i, j, k) in the pyramid's
   order (:func:`pyramid_order`), one after the other until one is identified, at most T;
2. per triple, the catalog triangles (a, b, c) whose three sides match the triple's within ε: the
   k-vector windows of sides ij and ik (every catalog pair in both orientations) are joined on the
   shared star a (the ik list sorted by star, searched per (a, b)), and side jk is checked on the
   star vectors. A triangle must also turn the same way as the triple (the sign of the triple
   product; a rotation keeps it, a mirror image does not). At most ``triangle_capacity`` triangles
   are kept; a triple with more (or with a star in more than ``star_capacity`` pairs of one window)
   is flagged and skipped, never cut;
3. the pyramid: each candidate triangle's attitude (Wahba on its three stars) points every other
   detection r at the sky; the nearest catalog star d confirms the triangle when its three angles to
   a, b, c match r's to i, j, k within ε (the paper's fourth-star check). A triple is identified when
   exactly one of its candidate triangles is confirmed (two confirmed triangles: ambiguity, the next
   triple is tried);
4. the first identified triple names i, j, k and every confirming detection
   (a star claimed by two detections names neither); the attitude is fitted to all of them.

A scene with no identified triple fails (every id −1).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.base import check_scenes, tolerance_rad
from jstarid.algorithms.pyramid.config import Config, Tuning
from jstarid.algorithms.pyramid.database import Database, window_size
from jstarid.attitude import solve_wahba, triad
from jstarid.geometry import precise
from jstarid.geometry.angles import pairwise_angles, turn_sign
from jstarid.geometry.kvector import range_search
from jstarid.runtime import (
    call_size,
    chunk_calls,
    grow_until,
    on_every_device,
    run_calls,
    static_config,
    take_rows,
)
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Identification, Scene
from jstarid.sky_index import local_stars

__all__ = ["Diagnostics", "SceneResult", "candidate_triangles", "identify", "identify_scene", "pyramid_order"]


class SceneResult(NamedTuple):
    """What :func:`identify_scene` returns for one scene (a leading batch axis when batched).

    Attributes:
        ids: (cap,) int32 catalog rows (−1 = not identified). ok: () bool.
        attitude: (3, 3) float32 C of the names (NaN when not ``ok``).
        n_candidates: () int32 candidate triangles over the T triples.
        overflow: () bool, the scene's own overflow or a triple past a buffer (skipped).
        buffer_over: () bool, a triple was skipped for a full buffer (the host reruns the scene with
            the largest buffers).
        triple: () int32 the identified triple's rank in the pyramid order (−1 none).
    """

    ids: jax.Array
    ok: jax.Array
    attitude: jax.Array
    n_candidates: jax.Array
    overflow: jax.Array
    triple: jax.Array
    buffer_over: jax.Array


class Diagnostics(NamedTuple):
    """Per-scene internals (batch axis first).

    Attributes:
        n_candidates: (B,) int32 candidate catalog triangles over the triples tried.
        overflow: (B,) bool, ``Scene.overflow`` or a triple skipped for a full buffer.
        triple: (B,) int32 rank of the identified triple in the pyramid order (−1: none).
        window: the side windows' width (catalog pairs, host int).
    """

    n_candidates: jax.Array
    overflow: jax.Array
    triple: jax.Array
    window: int


def pyramid_order(n: int) -> np.ndarray:
    """(C(n, 3), 3) int32 triples of n brightness-ranked detections in the pyramid's order (Mortari
    et al. 2004): ``for dj in 1…n−2, for dk in 1…n−dj−1, for i: (i, i + dj, i + dj + dk)``, which
    varies the stars of consecutive triples as much as possible (a bad star is left behind fast)."""
    out = [(i, i + dj, i + dj + dk) for dj in range(1, n - 1) for dk in range(1, n - dj)
           for i in range(n - dj - dk)]
    return np.asarray(out, np.int32).reshape(-1, 3)


def _chord2(angle):
    """Squared chord ‖u − v‖² of unit vectors ``angle`` (rad) apart: monotonic in the angle and
    computed from differences of components, so exact at small separations (no cos θ ≈ 1)."""
    half = jnp.sin(0.5 * jnp.clip(angle, 0.0, jnp.pi))
    return 4.0 * half * half


def _sq_dist(u, v):
    d = u - v
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


def _partners_from(database: Database, stars, lower):
    """Index into ``database.partners`` of each star's first partner at angle ≥ ``lower`` (exact
    binary search inside the star's group; the group's end when none)."""
    lo, hi = database.offsets[stars], database.offsets[stars + 1]
    last = database.partner_angles.shape[0] - 1

    def step(_, bounds):
        lo, hi = bounds
        mid = (lo + hi) // 2
        below = (lo < hi) & (database.partner_angles[jnp.minimum(mid, last)] < lower)
        return jnp.where(below, mid + 1, lo), jnp.where((lo < hi) & ~below, mid, hi)

    lo, _ = jax.lax.fori_loop(0, database.search_steps, step, (lo, hi))
    return lo


def candidate_triangles(theta_ij, theta_ik, theta_jk, turn, database: Database, eps_rad, *, window: int,
                        star_capacity: int, capacity: int):
    """Step 2: catalog triangles (a, b, c) matching a triple's sides and turn.

    Side ij's k-vector window gives the pairs (a, b), both ways round; a's partners at the ik angle
    (the pair table grouped by star) give c; side jk is checked on the star vectors.

    Args:
        theta_ij, theta_ik, theta_jk: () measured side angles (rad). turn: () the triple's turn sign.
        database: the :class:`~.database.Database`. eps_rad: () tolerance ε (rad).
        window: static width of side ij's window. star_capacity: static partners of a at the ik angle.
        capacity: static triangles kept.

    Returns:
        ``(abc, has, count, overflow)``: (capacity, 3) int32 catalog rows of the candidates, (capacity,)
        bool real entries, () int32 every match (may exceed the capacity), () bool some buffer was too
        small (the list is incomplete).
    """
    start, stop = range_search(database.kvector, theta_ij - eps_rad, theta_ij + eps_rad)
    window_over = stop - start > window
    slot = start + jnp.arange(window, dtype=jnp.int32)
    pair = database.pairs[jnp.clip(slot, 0, database.pairs.shape[0] - 1)]
    a = jnp.concatenate([pair[:, 0], pair[:, 1]])
    b = jnp.concatenate([pair[:, 1], pair[:, 0]])
    live = jnp.concatenate([slot < stop, slot < stop])
    first = _partners_from(database, a, theta_ik - eps_rad)
    end = database.offsets[a + 1]
    last = database.partners.shape[0] - 1
    at = first[:, None] + jnp.arange(star_capacity + 1, dtype=jnp.int32)[None, :]  # one extra: overflow
    inside = (at < end[:, None]) & (database.partner_angles[jnp.minimum(at, last)] <= theta_ik + eps_rad)
    star_over = jnp.any(live & inside[:, -1])
    at, inside = at[:, :-1], inside[:, :-1]
    c = database.partners[jnp.minimum(at, last)]  # (2W, R)
    vectors = database.star_vectors
    va, vb, vc = vectors[a], vectors[b], vectors[c]
    chord = _sq_dist(vb[:, None, :], vc)
    turns = turn_sign(jnp.broadcast_to(va[:, None, :], vc.shape), jnp.broadcast_to(vb[:, None, :], vc.shape),
                      vc)
    match = (live[:, None] & inside & (c != b[:, None]) & (chord >= _chord2(theta_jk - eps_rad))
             & (chord <= _chord2(theta_jk + eps_rad)) & (turns == turn))
    count = jnp.sum(match).astype(jnp.int32)
    (flat,) = jnp.nonzero(match.reshape(-1), size=capacity, fill_value=0)
    row = flat // star_capacity
    abc = jnp.stack([a[row], b[row], c.reshape(-1)[flat]], -1)
    has = jnp.arange(capacity) < count
    return abc, has, count, window_over | star_over | (count > capacity)


def _confirm(abc, has, tri, body, use, theta, database: Database, eps_rad):
    """Step 3 for one triple: which candidates a fourth detection confirms, and by which stars.

    Returns:
        ``(fits, fourth)``: (C, n) bool detection r confirms candidate triangle c, and (C, n) int32
        the catalog star it was matched to.
    """
    n = body.shape[0]
    vectors = database.star_vectors
    ref = vectors[abc]  # (C, 3, 3)
    att = triad(body[tri[0]][None], body[tri[1]][None], ref[:, 0], ref[:, 1])  # (C, 3, 3)
    sky = precise.einsum("cji,nj->cni", att, body)  # (C, n, 3) each detection's direction in ICRS
    def around(boresight):
        return local_stars(database.cells, vectors, boresight, database.grid)

    rows, vecs, _ = jax.vmap(around)(att[:, 2, :])
    near = jnp.argmin(_sq_dist(sky[:, :, None, :], vecs[:, None, :, :]), axis=-1)  # (C, n)
    d = jnp.take_along_axis(rows, near, axis=1)  # padding rows = S (never confirm)
    vd = vectors[jnp.minimum(d, vectors.shape[0] - 1)]
    fits = (d < vectors.shape[0]) & use[None, :] & ~jnp.isin(jnp.arange(n), tri)[None, :]
    for m in range(3):  # the paper's check: d's angles to a, b, c match r's to i, j, k
        chord = _sq_dist(ref[:, m, None, :], vd)
        measured = theta[tri[m]][None, :]
        fits = fits & (d != abc[:, m:m + 1]) & (chord >= _chord2(measured - eps_rad)) & (
            chord <= _chord2(measured + eps_rad))
    return has[:, None] & fits, d


def identify_scene(xy, valid, mag, overflow, eps_rad, *, database: Database, config: Config,
                   window: int) -> SceneResult:
    """The pyramid on one scene (module docstring).

    Args:
        xy: (cap, 2) float32 centroids (px). valid: (cap,) bool. mag: (cap,) float32 (mag).
        overflow: () bool the scene's own flag. eps_rad: () float32 tolerance ε (rad).
        database: the :class:`~.database.Database`. config: static :class:`Config`.
        window: static width of side ij's k-vector window.
    """
    cap = xy.shape[0]
    n = min(config.n_stars, cap)
    triples = pyramid_order(n)[:config.n_triples] if n >= 3 else np.zeros((1, 3), np.int32)
    _, sel = jax.lax.top_k(-jnp.where(valid, mag, jnp.inf), n)
    use = valid[sel]
    body = database.camera.unproject(xy[sel])
    theta = pairwise_angles(body)
    tri = jnp.asarray(triples)

    def one_triple(t):
        # side ij is the triple's shortest (the fewest catalog pairs in its k-vector window) and ik
        # the next (the fewest partners of a at its angle): i is the vertex opposite the longest side
        sides = jnp.stack([theta[t[1], t[2]], theta[t[0], t[2]], theta[t[0], t[1]]])  # opposite t[m]
        i_at = jnp.argmax(sides)
        j_at = jnp.where(sides[(i_at + 1) % 3] > sides[(i_at + 2) % 3], (i_at + 1) % 3, (i_at + 2) % 3)
        t = jnp.stack([t[i_at], t[j_at], t[3 - i_at - j_at]])
        i, j, k = t[0], t[1], t[2]
        abc, has, count, over = candidate_triangles(
            theta[i, j], theta[i, k], theta[j, k], turn_sign(body[i], body[j], body[k]), database, eps_rad,
            window=window, star_capacity=config.star_capacity, capacity=config.triangle_capacity)
        fits, fourth = _confirm(abc, has, t, body, use, theta, database, eps_rad)
        confirmed = jnp.sum(fits, axis=1) >= config.min_confirm
        win = jnp.argmax(confirmed)
        success = use[i] & use[j] & use[k] & (jnp.sum(confirmed) == 1) & ~over
        names = jnp.where(fits[win], fourth[win], -1).at[t].set(abc[win])
        return success, names, count, over
    # triples in the pyramid's order until one is identified (a vmapped group of scenes runs until
    # each has its triple or the T are spent)
    def searching(carry):
        t, found = carry[0], carry[1]
        return (t < tri.shape[0]) & ~found

    def next_triple(carry):
        t, _, _, total, any_over = carry
        success, names, count, over = one_triple(tri[t])
        return t + 1, success, names, total + count, any_over | over

    start = (jnp.int32(0), jnp.bool_(False), jnp.full((n,), -1, jnp.int32), jnp.int32(0), jnp.bool_(False))
    t_end, found, names, total, over = jax.lax.while_loop(searching, next_triple, start)
    ok = found & (n >= 4)
    # a star claimed by two detections names neither
    clash = jnp.sum((names[:, None] == names[None, :]) & (names[:, None] >= 0), axis=1) > 1
    names = jnp.where(clash | ~ok, -1, names)
    named = names >= 0
    attitude = solve_wahba(body, database.star_vectors[jnp.maximum(names, 0)], named.astype(jnp.float32))
    ok = ok & (jnp.sum(named) >= 3)
    ids = jnp.full((cap,), -1, jnp.int32).at[sel].set(jnp.where(ok, names, -1))
    return SceneResult(ids=ids, ok=ok, attitude=jnp.where(ok, attitude, jnp.nan), n_candidates=total,
                       overflow=overflow | over, triple=jnp.where(ok, t_end - 1, -1).astype(jnp.int32),
                       buffer_over=over)


@functools.partial(stored_jit, static_argnames=("config", "window"))
def _identify_chunk(xy, valid, mag, overflow, eps_rad, database, *, config, window):
    fn = functools.partial(identify_scene, database=database, config=config, window=window)
    return tuple(jax.lax.map(lambda a: fn(*a), (xy, valid, mag, overflow, eps_rad),
                             batch_size=config.map_chunk))


# ε is traced and the call size is the host loop's: neither changes the compiled code
_NOT_COMPILED = ("eps_px", "batch_chunk")


def identify(database: Database, scenes: Scene, config: Config | None = None, *, diagnostics: bool = False,
             tuning: Tuning | None = None):
    """Identify a batch of scenes with the pyramid.

    Args:
        database: :func:`~.database.build_database` for the scenes' camera.
        scenes: (B, N) :class:`~jstarid.scene.Scene`, centroids in the ideal pinhole frame.
        config: :class:`Config` (default ``Config()``).
        diagnostics: also return :class:`Diagnostics`.
        tuning: traced tolerances (default ``config.tuning()``); ``eps_px`` () or (B,).

    Returns:
        :class:`~jstarid.scene.Identification`, and :class:`Diagnostics` with ``diagnostics=True``.

    Raises:
        TypeError, ValueError: a malformed scene batch, or a non-positive ε.
    """
    config = Config() if config is None else config
    check_scenes(scenes)
    tuning = config.tuning() if tuning is None else tuning
    b, cap = scenes.batch_size, scenes.capacity
    camera = database.camera
    eps_rad = tolerance_rad(tuning.eps_px, b, camera)
    # first every scene with buffers for the usual triple (shortest side up to the frame's half
    # diagonal, ``triangle_capacity``), then the scenes that skipped a triple for a full buffer
    # again with the largest: the widest window of the table and 4 × the triangles
    eps_max = float(np.max(eps_rad)) if b else 0.0
    levels = {1: (window_size(database, eps_max, camera.half_diagonal_rad), config.triangle_capacity),
              2: (window_size(database, eps_max), 4 * config.triangle_capacity)} if b else {}
    out = [np.full((b, cap), -1, np.int32), np.zeros((b,), bool), np.full((b, 3, 3), np.nan, np.float32),
           np.zeros((b,), np.int32), np.zeros((b,), bool), np.full((b,), -1, np.int32), np.zeros((b,), bool)]
    if b:
        stripped = dataclasses.replace(database, key="")  # the key must not split compilations
        tables = (on_every_device(database, "pyramid_identify", lambda: stripped)
                  if jax.local_device_count() > 1 else stripped)
        batched = (np.asarray(scenes.xy, np.float32), np.asarray(scenes.valid),
                   np.asarray(scenes.mag, np.float32), np.asarray(scenes.overflow), eps_rad)

        def run(level, rows):
            window, capacity = levels[level]
            kernel_config = dataclasses.replace(static_config(config, _NOT_COMPILED),
                                                triangle_capacity=capacity)
            run_calls(_identify_chunk, chunk_calls(rows, call_size(rows.size, config.batch_chunk)),
                      lambda c: take_rows(batched, c), (tables,),
                      static=dict(config=kernel_config, window=window), n_rows=b, tails=[], fills=[], out=out)
            return out[-1][rows]

        grow_until(run, np.arange(b), 1, 2)
    res = SceneResult(*out)
    result = Identification(ids=jnp.asarray(res.ids), ok=jnp.asarray(res.ok),
                            attitude=jnp.asarray(res.attitude))
    if diagnostics:
        return result, Diagnostics(n_candidates=jnp.asarray(res.n_candidates),
                                   overflow=jnp.asarray(res.overflow), triple=jnp.asarray(res.triple),
                                   window=levels[2][0] if b else 0)
    return result
