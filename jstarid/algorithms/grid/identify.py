"""Grid identification (Padgett & Kreutz-Delgado 1997), batched and jit-compiled.

Per scene (:func:`identify_scene`, vmapped over ``Config.batch_chunk`` scenes in one jit call):

1. the ``n_refs`` valid detections nearest the principal point are the reference stars;
2. each reference's pattern (:func:`~.pattern.grid_pattern`) from every other detection, in the same
   tangent-plane pixels as the catalog's;
3. its best catalog star is the one whose pattern shares the most bits with it (population count of
   the AND); a reference is named when the best is unique and shares at least ``min_overlap`` bits;
4. check (our choice, see :class:`~.config.Config`): two named references agree when their stars'
   angle is within ε of the measured one; the largest mutually consistent set is kept
   (:func:`jstarid.geometry.consistency.most_consistent`) and the scene is claimed with at least
   ``min_verified`` names. Only references are named.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.base import check_scenes, tolerance_rad
from jstarid.algorithms.grid.config import Config, Tuning
from jstarid.algorithms.grid.database import Database, radii_px
from jstarid.algorithms.grid.pattern import grid_pattern, overlap
from jstarid.attitude import solve_wahba
from jstarid.completion import first_argmax
from jstarid.geometry.angles import pairwise_angles
from jstarid.geometry.consistency import most_consistent
from jstarid.runtime import call_size, chunk_calls, on_every_device, run_calls, take_rows
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Identification, Scene

__all__ = ["Diagnostics", "SceneResult", "identify", "identify_scene"]


class SceneResult(NamedTuple):
    """What :func:`identify_scene` returns for one scene (a leading batch axis when batched).

    Attributes:
        ids: (cap,) int32 catalog rows (−1 = not identified). ok: () bool.
        attitude: (3, 3) float32 C of the names (NaN when not ``ok``).
        n_candidates: () int32 references with a pattern (each is matched against every catalog star).
        overflow: () bool the scene's own flag.
        best_overlap: (n_refs,) int32 bits shared with each reference's best catalog star.
    """

    ids: jax.Array
    ok: jax.Array
    attitude: jax.Array
    n_candidates: jax.Array
    overflow: jax.Array
    best_overlap: jax.Array


class Diagnostics(NamedTuple):
    """Per-scene internals (batch axis first): ``n_candidates`` (B,) int32 references with a pattern;
    ``overflow`` (B,) bool the scene's own flag; ``best_overlap`` (B, n_refs) int32."""

    n_candidates: jax.Array
    overflow: jax.Array
    best_overlap: jax.Array


def identify_scene(xy, valid, overflow, eps_rad, *, database: Database, config: Config) -> SceneResult:
    """The grid algorithm on one scene (module docstring).

    Args:
        xy: (cap, 2) float32 centroids (px). valid: (cap,) bool. overflow: () bool.
        eps_rad: () float32 the check's tolerance (rad).
        database: the :class:`~.database.Database`. config: static :class:`Config`.
    """
    camera = database.camera
    cap = xy.shape[0]
    n = min(config.n_refs, cap)
    centre = jnp.array([camera.cx, camera.cy], jnp.float32)
    d2 = jnp.sum((xy - centre[None, :]) ** 2, axis=-1)
    _, refs = jax.lax.top_k(-jnp.where(valid, d2, jnp.inf), n)
    use = valid[refs]
    body = camera.unproject(xy)

    def match(r):
        words, oriented = grid_pattern(body[r], body, valid & (jnp.arange(cap) != r), f_px=float(camera.f_px),
                                       pattern_px=database.pattern_px, buffer_px=database.buffer_px,
                                       grid=database.grid)
        score = overlap(words, database.patterns)
        best = jnp.max(score)
        unique = jnp.sum(score == best) == 1
        return first_argmax(score), best, oriented & unique & (best >= config.min_overlap)

    cand, best, named = jax.vmap(match)(refs)
    named = named & use
    ref_body = body[refs]
    cand_vec = database.star_vectors[cand]
    agree = (named[:, None] & named[None, :] & (cand[:, None] != cand[None, :])
             & (jnp.abs(pairwise_angles(ref_body) - pairwise_angles(cand_vec)) <= eps_rad)
             & ~jnp.eye(n, dtype=bool))
    members = most_consistent(agree, best, named)
    ok = jnp.sum(members) >= config.min_verified
    attitude = solve_wahba(ref_body, cand_vec, members.astype(jnp.float32))
    ids = jnp.full((cap,), -1, jnp.int32).at[refs].set(jnp.where(members & ok, cand, -1))
    return SceneResult(ids=ids, ok=ok, attitude=jnp.where(ok, attitude, jnp.nan),
                       n_candidates=jnp.sum(use).astype(jnp.int32), overflow=overflow,
                       best_overlap=jnp.zeros((config.n_refs,), jnp.int32).at[:n].set(best))


@functools.partial(stored_jit, static_argnames=("config",))
def _identify_chunk(xy, valid, overflow, eps_rad, database, *, config):
    fn = functools.partial(identify_scene, database=database, config=config)
    return tuple(jax.vmap(fn)(xy, valid, overflow, eps_rad))


def identify(database: Database, scenes: Scene, config: Config | None = None, *, diagnostics: bool = False,
             tuning: Tuning | None = None):
    """Identify a batch of scenes with the grid algorithm.

    Args:
        database: :func:`~.database.build_database` for the scenes' camera and ``config``'s radii.
        scenes: (B, N) :class:`~jstarid.scene.Scene`, centroids in the ideal pinhole frame.
        config: :class:`Config` (default ``Config()``).
        diagnostics: also return :class:`Diagnostics`.
        tuning: traced tolerance (default ``config.tuning()``); ``eps_px`` () or (B,).

    Raises:
        TypeError, ValueError: a malformed scene batch, a non-positive ε, or a database built with
            other radii or grid than ``config``'s.
    """
    config = Config() if config is None else config
    check_scenes(scenes)
    if (database.grid, (database.pattern_px, database.buffer_px)) != (config.grid,
                                                                      radii_px(database.camera, config)):
        raise ValueError("the database was built with another grid or other radii than this config's")
    tuning = config.tuning() if tuning is None else tuning
    b, cap = scenes.batch_size, scenes.capacity
    eps_rad = tolerance_rad(tuning.eps_px, b, database.camera)
    out = [np.full((b, cap), -1, np.int32), np.zeros((b,), bool), np.full((b, 3, 3), np.nan, np.float32),
           np.zeros((b,), np.int32), np.zeros((b,), bool), np.zeros((b, config.n_refs), np.int32)]
    if b:
        stripped = dataclasses.replace(database, key="")  # the key must not split compilations
        tables = (on_every_device(database, "grid_identify", lambda: stripped)
                  if jax.local_device_count() > 1 else stripped)
        batched = (np.asarray(scenes.xy, np.float32), np.asarray(scenes.valid), np.asarray(scenes.overflow),
                   eps_rad)
        run_calls(_identify_chunk, chunk_calls(np.arange(b), call_size(b, config.batch_chunk)),
                  lambda c: take_rows(batched, c), (tables,),
                  static=dict(config=dataclasses.replace(config, eps_px=Config().eps_px, batch_chunk=1)),
                  n_rows=b, tails=[], fills=[], out=out)
    res = SceneResult(*out)
    result = Identification(ids=jnp.asarray(res.ids), ok=jnp.asarray(res.ok),
                            attitude=jnp.asarray(res.attitude))
    if diagnostics:
        return result, Diagnostics(n_candidates=jnp.asarray(res.n_candidates),
                                   overflow=jnp.asarray(res.overflow),
                                   best_overlap=jnp.asarray(res.best_overlap))
    return result
