"""A reference "identifier" for tests only: returns the truth, optionally corrupted.

It lets the metrics and the evaluation harness be tested before (and independently of) the real
algorithms. ``fail_fraction`` of the scenes are reported as failures (``ok = False``, no ids) and
``wrong_fraction`` of the scenes get one identified star's id replaced by a different catalog row.
Which scenes are corrupted is drawn from ``Config.seed`` (deterministic).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from jstarid.scene import Identification, Scene

__all__ = ["Config", "build_database", "identify"]


@dataclasses.dataclass(frozen=True)
class Config:
    """Oracle settings: fractions of scenes to fail / to corrupt, and the seed that picks them."""

    fail_fraction: float = 0.0
    wrong_fraction: float = 0.0
    seed: int = 0


def build_database(catalog, camera, config: Config = Config()):
    """The oracle needs only the catalog size (to draw a wrong id)."""
    del camera, config
    return {"n_stars": len(catalog)}


def identify(database, scenes: Scene, config: Config = Config()) -> Identification:
    """Truth for every true star, −1 for false stars; scenes corrupted as configured."""
    return _identify(scenes, database["n_stars"], config)


@functools.partial(jax.jit, static_argnames=("n_stars", "config"))
def _identify(scenes, n_stars, config):
    b = scenes.batch_size
    k_fail, k_wrong = jax.random.split(jax.random.key(config.seed))
    fail = jax.random.uniform(k_fail, (b,)) < config.fail_fraction
    wrong = (jax.random.uniform(k_wrong, (b,)) < config.wrong_fraction) & ~fail
    ids = jnp.where(scenes.valid, scenes.truth, -1)
    # corrupt the first identified star of a "wrong" scene: shift its row by one (mod catalog size)
    first = jnp.argmax(ids >= 0, axis=1)
    has = jnp.any(ids >= 0, axis=1)
    rows = jnp.arange(b)
    bad = (ids[rows, first] + 1) % n_stars
    ids = ids.at[rows, first].set(jnp.where(wrong & has, bad, ids[rows, first]))
    ids = jnp.where(fail[:, None], -1, ids)
    return Identification(ids=ids.astype(jnp.int32), ok=~fail, attitude=None)
