"""The grid database: every catalog star's grid pattern (Padgett & Kreutz-Delgado 1997, §III).

Built with the same :func:`~.pattern.grid_pattern` as the image side, vmapped over the catalog, from
each star's catalog neighbours (a k-d tree query on the host). Seconds to build; not cached on disk.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.base import cache_key
from jstarid.algorithms.grid.config import Config
from jstarid.algorithms.grid.pattern import grid_pattern
from jstarid.camera import Camera
from jstarid.runtime.program_store import stored_jit

__all__ = ["Database", "build_database", "radii_px"]

_DB_VERSION = 1
_STARS_PER_STEP = 2048


@functools.partial(jax.tree_util.register_dataclass, data_fields=["patterns", "star_vectors"],
                   meta_fields=["camera", "pattern_px", "buffer_px", "grid", "key"])
@dataclasses.dataclass(frozen=True)
class Database:
    """Catalog patterns (a pytree: arrays are leaves, the rest static).

    Attributes:
        patterns: (S, g²/32) uint32 each catalog star's pattern (all zero when it has no neighbour to
            orient by: it then matches nothing).
        star_vectors: (S, 3) float32 ICRS unit vectors (row = catalog row).
        camera: the :class:`~jstarid.camera.Camera`. pattern_px, buffer_px: the radii (px).
        grid: g. key: cache key.
    """

    patterns: jax.Array
    star_vectors: jax.Array
    camera: Camera
    pattern_px: float
    buffer_px: float
    grid: int
    key: str = ""

    def cache_key(self) -> str:
        return self.key


def radii_px(camera: Camera, config: Config) -> tuple[float, float]:
    """The pattern and buffer radii (px) of ``config`` on ``camera`` (fractions of the shorter side)."""
    side = float(min(camera.width, camera.height))
    return config.pattern_radius * side, config.buffer_radius * side


@functools.partial(stored_jit, static_argnames=("f_px", "pattern_px", "buffer_px", "grid"))
def _patterns(centres, neighbours, real, *, f_px, pattern_px, buffer_px, grid):
    fn = functools.partial(grid_pattern, f_px=f_px, pattern_px=pattern_px, buffer_px=buffer_px, grid=grid)
    return jax.vmap(fn)(centres, neighbours, real)[0]


def build_database(catalog, camera: Camera, config: Config | None = None, *, use_cache: bool = True,
                   progress: bool = True) -> Database:
    """Every catalog star's grid pattern for ``camera``.

    Args:
        catalog: :class:`~jstarid.catalog.Catalog` (the identification catalog).
        camera: :class:`~jstarid.camera.Camera`.
        config: :class:`~jstarid.algorithms.grid.Config` (its radii and grid shape the database).
        use_cache: unused (nothing is cached on disk: the build takes seconds).
        progress: unused (the build takes seconds).
    """
    from scipy.spatial import cKDTree

    config = Config() if config is None else config
    pattern_px, buffer_px = radii_px(camera, config)
    vectors = np.asarray(catalog.unit_vectors, np.float64)
    # neighbours up to the pattern square's corner
    reach = math.atan(math.sqrt(2.0) * pattern_px / camera.f_px) * 1.001
    lists = cKDTree(vectors).query_ball_point(vectors, 2.0 * math.sin(reach / 2.0))
    m = max(1, max(len(x) for x in lists))
    m = int(math.ceil(m / 16) * 16)
    rows = np.zeros((len(vectors), m), np.int64)
    real = np.zeros((len(vectors), m), bool)
    for s, idx in enumerate(lists):
        rows[s, : len(idx)] = idx
        real[s, : len(idx)] = True
    vec32 = vectors.astype(np.float32)
    words = []
    for lo in range(0, len(vectors), _STARS_PER_STEP):
        sl = slice(lo, lo + _STARS_PER_STEP)
        words.append(np.asarray(_patterns(jnp.asarray(vec32[sl]), jnp.asarray(vec32[rows[sl]]),
                                          jnp.asarray(real[sl]), f_px=float(camera.f_px),
                                          pattern_px=pattern_px, buffer_px=buffer_px, grid=config.grid)))
    key = cache_key("grid", _DB_VERSION, catalog, camera, config.database_fields())
    return Database(patterns=jnp.asarray(np.concatenate(words)), star_vectors=jnp.asarray(vec32),
                    camera=camera, pattern_px=pattern_px, buffer_px=buffer_px, grid=config.grid, key=key)
