"""A reference "identifier" for tests only: returns the truth, optionally corrupted.

It lets the metrics and the evaluation harness be tested before (and independently of) the real
algorithms, and it is the smallest complete example of the algorithm contract
(:mod:`jstarid.algorithms.base`). ``fail_fraction`` of the scenes are reported as failures
(``ok = False``, no ids) and ``wrong_fraction`` of the scenes get one identified star's id replaced by
a different catalog row. Which scenes are corrupted is drawn from ``Config.seed`` (deterministic).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jstarid.algorithms.base import cache_key, check_scenes
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Identification, Scene

__all__ = ["Config", "Database", "Diagnostics", "Tuning", "build_database", "identify"]


class Tuning(NamedTuple):
    """The oracle has no tolerances to sweep."""


@dataclasses.dataclass(frozen=True)
class Config:
    """Oracle settings: fractions of scenes to fail / to corrupt, and the seed that picks them."""

    fail_fraction: float = 0.0
    wrong_fraction: float = 0.0
    seed: int = 0

    def __post_init__(self):
        if not (0.0 <= self.fail_fraction <= 1.0 and 0.0 <= self.wrong_fraction <= 1.0):
            raise ValueError("fail_fraction and wrong_fraction must be in [0, 1]")

    @classmethod
    def paper(cls, **overrides) -> Config:
        """There is no paper: the truth, uncorrupted."""
        return cls(**overrides)

    def tuning(self) -> Tuning:
        return Tuning()

    def database_fields(self) -> dict:
        return {}


@functools.partial(jax.tree_util.register_dataclass, data_fields=[], meta_fields=["n_stars", "key"])
@dataclasses.dataclass(frozen=True)
class Database:
    """The oracle needs only the catalog size (to draw a wrong id)."""

    n_stars: int
    key: str = ""

    def cache_key(self) -> str:
        return self.key


class Diagnostics(NamedTuple):
    """Attributes: n_candidates (B,) int32 zeros (nothing is searched); overflow (B,) bool, the
    scene's own flag."""

    n_candidates: jax.Array
    overflow: jax.Array


def build_database(catalog, camera, config: Config | None = None, *, use_cache: bool = True,
                   progress: bool = True) -> Database:
    """The catalog size; nothing to build or cache (``use_cache`` and ``progress`` are unused)."""
    config = Config() if config is None else config
    return Database(n_stars=len(catalog),
                    key=cache_key("oracle", 1, catalog, camera, config.database_fields()))


def identify(database: Database, scenes: Scene, config: Config | None = None, *,
             tuning: Tuning | None = None, diagnostics: bool = False):
    """Truth for every true star, −1 for false stars; a scene with no true star fails; scenes
    corrupted as configured (``tuning``: the oracle has none, accepted for the contract)."""
    config = Config() if config is None else config
    check_scenes(scenes)
    result = _identify(scenes, database.n_stars, config)
    if diagnostics:
        return result, Diagnostics(n_candidates=jnp.zeros(scenes.batch_size, jnp.int32),
                                   overflow=scenes.overflow)
    return result


@functools.partial(stored_jit, static_argnames=("n_stars", "config"))
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
    return Identification(ids=ids.astype(jnp.int32), ok=~fail & has,
                          attitude=None)
