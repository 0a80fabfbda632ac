"""The geometric-voting database: every catalog star pair that fits in one frame, sorted by angle.

Kolomenkin et al. (2008) §III: the catalog's pair distances, sorted, with their two stars; a range of
distances is found by search. Here the range search is Mortari's k-vector
(:mod:`jstarid.geometry.kvector`). Pairs farther apart than the frame's diagonal can never be seen
together and are left out. Built on the host in float64 (the angle of a pair is exact to float32
before it is stored) and cached on disk.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.base import cache_key
from jstarid.algorithms.voting.config import Config
from jstarid.camera import Camera
from jstarid.geometry.kvector import KVector
from jstarid.geometry.star_pairs import (
    frame_pair_angle,
    pair_database,
    pair_table_first_use,
    table_problem,
    widest_window,
)

__all__ = ["Database", "build_database", "camera_problem", "first_use", "window_size"]

_DB_VERSION = 1


@functools.partial(jax.tree_util.register_dataclass, data_fields=["kvector", "pairs", "star_vectors"],
                   meta_fields=["camera", "max_angle_rad", "key"])
@dataclasses.dataclass(frozen=True)
class Database:
    """Pair table (a pytree: arrays are leaves, the camera and key are static).

    Attributes:
        kvector: :class:`~jstarid.geometry.kvector.KVector` over the P pair angles (rad, ascending).
        pairs: (P, 2) int32 catalog rows of each pair's stars, in the angle order.
        star_vectors: (S, 3) float32 ICRS unit vectors of the catalog stars (row = catalog row).
        camera: the :class:`~jstarid.camera.Camera` the table was built for.
        max_angle_rad: the largest pair angle kept (the frame's diagonal).
        key: cache key (:func:`jstarid.algorithms.base.cache_key`).
    """

    kvector: KVector
    pairs: jax.Array
    star_vectors: jax.Array
    camera: Camera
    max_angle_rad: float
    key: str = ""

    def cache_key(self) -> str:
        return self.key

    @property
    def n_pairs(self) -> int:
        return int(self.pairs.shape[0])


def camera_problem(camera: Camera, config: Config | None = None, catalog=None) -> str | None:
    """Why geometric voting cannot work on this camera and catalog (a pair table past
    :data:`~jstarid.geometry.star_pairs.MAX_PAIRS`), or ``None``."""
    return table_problem("voting", catalog, camera)


def _cache_key(catalog, camera: Camera, config: Config) -> str:
    return cache_key("voting", _DB_VERSION, catalog, camera, config.database_fields())


def build_database(catalog, camera: Camera, config: Config | None = None, *, use_cache: bool = True,
                   progress: bool = True) -> Database:
    """Build (or load from the disk cache) the pair table of a catalog and camera.

    Args:
        catalog: :class:`~jstarid.catalog.Catalog` (the identification catalog).
        camera: :class:`~jstarid.camera.Camera`.
        config: :class:`~jstarid.algorithms.voting.Config` (nothing in it shapes the table).
        use_cache: read/write ``voting-<key>.npz`` under :func:`jstarid.catalog.cache_dir`.
        progress: a progress bar while building.

    Returns:
        The :class:`Database`.

    Raises:
        ValueError: the table would exceed :data:`~jstarid.geometry.star_pairs.MAX_PAIRS`
            (:func:`camera_problem`), or the catalog has fewer than two stars.
    """
    config = Config() if config is None else config
    if len(catalog) < 2:
        raise ValueError("voting needs a catalog of at least two stars")
    key = _cache_key(catalog, camera, config)
    # the size check (camera_problem), the cached table and its k-vector, shared with the pyramid
    table = pair_database("voting", key, catalog, camera, use_cache=use_cache, progress=progress)
    return Database(kvector=table.kvector, pairs=jnp.asarray(table.pairs),
                    star_vectors=jnp.asarray(table.vectors, jnp.float32), camera=camera,
                    max_angle_rad=frame_pair_angle(camera), key=key)


def first_use(catalog, camera: Camera, config: Config | None = None) -> tuple[str, float] | None:
    """What :func:`build_database` builds for these settings and about how long it takes on a 2-core
    CPU (s); ``None`` when it is cached."""
    config = Config() if config is None else config
    return pair_table_first_use("voting", _cache_key(catalog, camera, config), catalog, camera)


_WINDOWS: dict[tuple[str, float], int] = {}


def window_size(database: Database, eps_rad: float) -> int:
    """The most catalog pairs any query window ``[θ − ε, θ + ε]`` can hold (host, memoised): the
    static width of the voting buffer, so no window is ever cut."""
    cache = (database.key, float(eps_rad))
    if cache not in _WINDOWS:
        _WINDOWS[cache] = widest_window(np.asarray(database.kvector.values), eps_rad)
    return _WINDOWS[cache]
