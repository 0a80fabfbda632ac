"""Geometric voting identification (Kolomenkin et al. 2008, §III–IV), batched and jit-compiled.

Per scene (:func:`identify_scene`, vmapped in groups of ``Config.map_chunk`` inside one jit call per
``Config.batch_chunk`` scenes):

1. the N brightest valid detections → camera-frame unit vectors; their C(N, 2) pair angles θ;
2. voting: for each pair, the catalog pairs with angle in [θ − ε, θ + ε] (k-vector range search);
   each votes for both of its stars as the identity of both detections (one scatter-add into an
   (N, S) table of votes). The buffer holds the widest window the table can produce
   (:func:`~.database.window_size`), so no window is ever cut;
3. each detection is named after its most-voted star; a tie for the most votes leaves it unnamed
   (our choice: a tie is ambiguity, and a failure is better than a wrong name);
4. verification: a pair of named detections agrees when their stars' angle is within ε of the
   measured one. The paper keeps the names with the most agreement votes; we read that as the
   largest mutually consistent set, found greedily: while some name disagrees with another, the name
   with the fewest agreements (then the fewest first-round votes) is dropped. The scene is claimed
   with at least ``Config.min_verified`` names left.

Extension (``Config()``, off in ``Config.paper()``): an attitude check — the Wahba attitude of the
verified names must place each within ε of its detection; names it cannot place are taken back.
Every scene gets the attitude of its names (Wahba, SVD), NaN when it is not claimed.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.base import check_scenes, tolerance_rad
from jstarid.algorithms.voting.config import Config, Tuning
from jstarid.algorithms.voting.database import Database, window_size
from jstarid.attitude import solve_wahba
from jstarid.completion import first_argmax
from jstarid.geometry import precise
from jstarid.geometry.angles import angle_between, pairwise_angles
from jstarid.geometry.consistency import most_consistent
from jstarid.geometry.kvector import range_search
from jstarid.runtime import call_size, chunk_calls, on_every_device, run_calls, static_config, take_rows
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Identification, Scene

__all__ = ["Diagnostics", "SceneResult", "cast_votes", "identify", "identify_scene"]


class SceneResult(NamedTuple):
    """What :func:`identify_scene` returns for one scene (a leading batch axis when batched).

    Attributes:
        ids: (cap,) int32 catalog rows of the scene's detections (−1 = not identified).
        ok: () bool, the scene is claimed.
        attitude: (3, 3) float32 C of the names (NaN when not ``ok``).
        n_candidates: () int32 catalog pairs that voted (summed over the pair windows).
        overflow: () bool, the scene's own overflow, or some window held more pairs than the buffer
            (never with the table's own bound, :func:`~.database.window_size`).
        n_verified: () int32 names left after verification (and the attitude check).
    """

    ids: jax.Array
    ok: jax.Array
    attitude: jax.Array
    n_candidates: jax.Array
    overflow: jax.Array
    n_verified: jax.Array


class Diagnostics(NamedTuple):
    """Per-scene internals (batch axis first).

    Attributes:
        n_candidates: (B,) int32 catalog pairs that voted, over all the scene's pair windows.
        overflow: (B,) bool, the scene's own ``Scene.overflow`` or a cut voting window.
        n_verified: (B,) int32 mutually consistent names.
        window: the voting buffer's width (pairs per window, host int).
    """

    n_candidates: jax.Array
    overflow: jax.Array
    n_verified: jax.Array
    window: int


def cast_votes(theta, asked, first, second, kvector, pairs, eps_rad, *, n: int, n_cat: int, window: int):
    """Step 2: each catalog pair in a detection pair's window votes for both of its stars as the
    identity of both detections.

    Args:
        theta: (M,) float32 measured angles (rad) of the M detection pairs.
        asked: (M,) bool, the pair is between two valid detections.
        first, second: (M,) int32 the pair's detections (indices < n).
        kvector, pairs: the database's k-vector over the pair angles and its (P, 2) catalog rows.
        eps_rad: () tolerance ε (rad).
        n: detections (static). n_cat: catalog stars (static). window: buffer width (static).

    Returns:
        ``(votes, count)``: (n, n_cat) int32 votes, (M,) int32 catalog pairs in each window (0 for a
        pair not asked; more than ``window`` means the window was cut).
    """
    start, stop = jax.vmap(lambda t: range_search(kvector, t - eps_rad, t + eps_rad))(theta)
    count = jnp.where(asked, stop - start, 0)
    slot = start[:, None] + jnp.arange(window, dtype=jnp.int32)[None, :]
    live = asked[:, None] & (slot < stop[:, None])
    star = pairs[jnp.clip(slot, 0, pairs.shape[0] - 1)]  # (M, window, 2)
    det = jnp.stack([first, second], -1)[:, None, :, None]  # (M, 1, 2, 1)
    flat = det * n_cat + star[:, :, None, :]  # every detection of the pair × every star of the pair
    flat = jnp.where(live[:, :, None, None], flat, n * n_cat)  # out of range: dropped
    votes = jnp.zeros((n * n_cat,), jnp.int32).at[flat.reshape(-1)].add(1, mode="drop")
    return votes.reshape(n, n_cat), count


def identify_scene(xy, valid, mag, overflow, eps_rad, *, kvector, pairs, star_vectors, camera,
                   config: Config, window: int) -> SceneResult:
    """Geometric voting on one scene (module docstring).

    Args:
        xy: (cap, 2) float32 centroids (px). valid: (cap,) bool. mag: (cap,) float32 (mag).
        overflow: () bool, the scene's own overflow flag.
        eps_rad: () float32 tolerance ε (rad).
        kvector, pairs, star_vectors: the :class:`~.database.Database` tables.
        camera: static :class:`~jstarid.camera.Camera`. config: static :class:`Config`.
        window: static voting buffer width (catalog pairs per window).

    Returns:
        The scene's :class:`SceneResult`.
    """
    cap = xy.shape[0]
    n = min(config.n_stars, cap)
    n_cat = star_vectors.shape[0]
    # 1. the N brightest valid detections and their pair angles
    _, sel = jax.lax.top_k(-jnp.where(valid, mag, jnp.inf), n)
    use = valid[sel]
    body = camera.unproject(xy[sel])
    first, second = (jnp.asarray(a, jnp.int32) for a in np.triu_indices(n, 1))
    theta = angle_between(body[first], body[second])
    asked = use[first] & use[second]
    # 2. votes (one scatter-add)
    votes, count = cast_votes(theta, asked, first, second, kvector, pairs, eps_rad, n=n, n_cat=n_cat,
                              window=window)
    # 3. the most-voted star of each detection; a tie names nothing
    cand = first_argmax(votes)
    best = jnp.max(votes, axis=1)
    unique = jnp.sum(votes == best[:, None], axis=1) == 1
    named = use & (best > 0) & unique
    # 4. verification: the largest mutually consistent set of names
    cand_vec = star_vectors[cand]
    agree = (named[:, None] & named[None, :] & (cand[:, None] != cand[None, :])
             & (jnp.abs(pairwise_angles(body) - pairwise_angles(cand_vec)) <= eps_rad)
             & ~jnp.eye(n, dtype=bool))
    members = most_consistent(agree, best, named)
    attitude = solve_wahba(body, cand_vec, members.astype(jnp.float32))
    if config.attitude_check:
        placed = angle_between(precise.einsum("ij,nj->ni", attitude, cand_vec), body) <= eps_rad
        members = members & placed
        attitude = solve_wahba(body, cand_vec, members.astype(jnp.float32))
    n_verified = jnp.sum(members).astype(jnp.int32)
    ok = n_verified >= config.min_verified
    ids = jnp.full((cap,), -1, jnp.int32).at[sel].set(jnp.where(members & ok, cand, -1))
    return SceneResult(ids=ids, ok=ok, attitude=jnp.where(ok, attitude, jnp.nan),
                       n_candidates=jnp.sum(count).astype(jnp.int32),
                       overflow=jnp.any(count > window) | overflow, n_verified=n_verified)


@functools.partial(stored_jit, static_argnames=("camera", "config", "window"))
def _identify_chunk(xy, valid, mag, overflow, eps_rad, database, *, camera, config, window):
    fn = functools.partial(identify_scene, kvector=database.kvector, pairs=database.pairs,
                           star_vectors=database.star_vectors, camera=camera, config=config, window=window)
    return tuple(jax.lax.map(lambda a: fn(*a), (xy, valid, mag, overflow, eps_rad),
                             batch_size=config.map_chunk))


# ε is traced and the call size is the host loop's: neither changes the compiled code
_NOT_COMPILED = ("eps_px", "batch_chunk")


def identify(database: Database, scenes: Scene, config: Config | None = None, *, diagnostics: bool = False,
             tuning: Tuning | None = None):
    """Identify a batch of scenes by geometric voting.

    Args:
        database: the pair table (:func:`~.database.build_database`) of the scenes' camera.
        scenes: (B, N) :class:`~jstarid.scene.Scene`, centroids in the ideal pinhole frame.
        config: :class:`Config` (default ``Config()``).
        diagnostics: also return :class:`Diagnostics`.
        tuning: traced tolerances (default ``config.tuning()``); ``eps_px`` () or (B,) per scene.

    Returns:
        :class:`~jstarid.scene.Identification` (ids (B, N), ok (B,), attitude (B, 3, 3)), and
        :class:`Diagnostics` with ``diagnostics=True``.

    Raises:
        TypeError, ValueError: a malformed scene batch (:func:`~jstarid.algorithms.base.check_scenes`)
            or a non-positive ε.
    """
    config = Config() if config is None else config
    check_scenes(scenes)
    tuning = config.tuning() if tuning is None else tuning
    b, cap = scenes.batch_size, scenes.capacity
    camera = database.camera
    eps_rad = tolerance_rad(tuning.eps_px, b, camera)
    if b == 0:
        ids, ok, att, n_cand, over, n_ver = (np.zeros((0, cap), np.int32), np.zeros((0,), bool),
                                             np.zeros((0, 3, 3), np.float32), np.zeros((0,), np.int32),
                                             np.zeros((0,), bool), np.zeros((0,), np.int32))
    else:
        window = window_size(database, float(np.max(eps_rad)))
        stripped = dataclasses.replace(database, key="")  # the key must not split compilations
        tables = (on_every_device(database, "voting_identify", lambda: stripped)
                  if jax.local_device_count() > 1 else stripped)
        batched = (np.asarray(scenes.xy, np.float32), np.asarray(scenes.valid),
                   np.asarray(scenes.mag, np.float32), np.asarray(scenes.overflow), eps_rad)
        chunk = call_size(b, config.batch_chunk)
        ids, ok, att, n_cand, over, n_ver = run_calls(
            _identify_chunk, chunk_calls(np.arange(b), chunk), lambda c: take_rows(batched, c), (tables,),
            static=dict(camera=camera, config=static_config(config, _NOT_COMPILED), window=window), n_rows=b,
            tails=[(cap,), (), (3, 3), (), (), ()], fills=[-1, False, np.nan, 0, False, 0])
    result = Identification(ids=jnp.asarray(ids), ok=jnp.asarray(ok), attitude=jnp.asarray(att))
    if diagnostics:
        return result, Diagnostics(n_candidates=jnp.asarray(n_cand), overflow=jnp.asarray(over),
                                   n_verified=jnp.asarray(n_ver), window=window if b else 0)
    return result
