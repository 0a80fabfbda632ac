"""The pyramid's database: the catalog's pair angles with a k-vector (Mortari et al. 2004, §"k-vector"),
and a sky index for the fourth star's lookup.

Pairs farther apart than the frame's diagonal are left out (:mod:`jstarid.geometry.star_pairs`,
shared with the voting baseline). The sky index lists, for any boresight, the stars that can be in
the frame: the fourth detection's star is looked for among them.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.base import cache_key
from jstarid.algorithms.pyramid.config import Config
from jstarid.camera import Camera
from jstarid.geometry.kvector import KVector
from jstarid.geometry.star_pairs import pair_database, pair_table_first_use, table_problem, widest_window
from jstarid.sky_index import build_sky_index

__all__ = ["Database", "build_database", "camera_problem", "first_use", "window_size"]

_DB_VERSION = 1
SKY_MARGIN_RAD = 0.02  # the sky index's reach past the half diagonal: a triangle's attitude error


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["kvector", "pairs", "star_vectors", "cells", "offsets", "partners",
                                "partner_angles"],
                   meta_fields=["camera", "grid", "search_steps", "key"])
@dataclasses.dataclass(frozen=True)
class Database:
    """Pair table and sky index (a pytree: arrays are leaves; camera, grid and key are static).

    Attributes:
        kvector: :class:`~jstarid.geometry.kvector.KVector` over the P pair angles (rad, ascending).
        pairs: (P, 2) int32 catalog rows of each pair, in the angle order.
        star_vectors: (S, 3) float32 ICRS unit vectors (row = catalog row).
        cells: (6·G·G, K) int32 sky-index lists (:mod:`jstarid.sky_index`; padding = S).
        offsets: (S + 1,) int32 each star's range in ``partners`` (the pair table by star).
        partners: (2P,) int32 every pair's other star, grouped by star and sorted by angle in a group.
        partner_angles: (2P,) float32 their angles (rad).
        camera: the :class:`~jstarid.camera.Camera`. grid: G.
        search_steps: binary-search steps that cover the largest group. key: cache key.
    """

    kvector: KVector
    pairs: jax.Array
    star_vectors: jax.Array
    cells: jax.Array
    offsets: jax.Array
    partners: jax.Array
    partner_angles: jax.Array
    camera: Camera
    grid: int
    search_steps: int
    key: str = ""

    def cache_key(self) -> str:
        return self.key

    @property
    def n_pairs(self) -> int:
        return int(self.pairs.shape[0])


def camera_problem(camera: Camera, config: Config | None = None, catalog=None) -> str | None:
    """Why the pyramid cannot work on this camera and catalog (a pair table past
    :data:`~jstarid.geometry.star_pairs.MAX_PAIRS`), or ``None``."""
    return table_problem("pyramid", catalog, camera)


def _cache_key(catalog, camera: Camera, config: Config) -> str:
    return cache_key("pyramid", _DB_VERSION, catalog, camera, config.database_fields())


def build_database(catalog, camera: Camera, config: Config | None = None, *, use_cache: bool = True,
                   progress: bool = True) -> Database:
    """Build (or load from the disk cache) the pair table and sky index of a catalog and camera.

    Args:
        catalog: :class:`~jstarid.catalog.Catalog` (the identification catalog).
        camera: :class:`~jstarid.camera.Camera`.
        config: :class:`~jstarid.algorithms.pyramid.Config` (nothing in it shapes the database).
        use_cache: read/write ``pyramid-<key>.npz`` under :func:`jstarid.catalog.cache_dir`.
        progress: a progress bar while building.

    Raises:
        ValueError: the table would be too large (:func:`camera_problem`), or no two catalog stars
            fit in one frame.
    """
    config = Config() if config is None else config
    key = _cache_key(catalog, camera, config)
    # the size check (camera_problem), the cached table and its k-vector, shared with voting
    table = pair_database("pyramid", key, catalog, camera, use_cache=use_cache, progress=progress)
    angles, pairs, vectors = table.angles, table.pairs, table.vectors
    index = build_sky_index(vectors, camera.half_diagonal_rad, margin_rad=SKY_MARGIN_RAD,
                            key=f"{catalog.fingerprint}-pyramid-{camera.half_diagonal_rad:.6e}")
    # the same pairs grouped by star (both orientations), by angle within a group: the triangle join
    # looks up one star's partners at one angle
    first = np.concatenate([pairs[:, 0], pairs[:, 1]])
    partners = np.concatenate([pairs[:, 1], pairs[:, 0]])
    both = np.concatenate([angles, angles])
    order = np.lexsort((both, first))
    offsets = np.searchsorted(first[order], np.arange(len(catalog) + 1)).astype(np.int32)
    steps = max(1, int(np.ceil(np.log2(int(np.max(np.diff(offsets))) + 1))) + 1)
    return Database(kvector=table.kvector, pairs=jnp.asarray(pairs),
                    star_vectors=jnp.asarray(vectors, jnp.float32), cells=jnp.asarray(index.cells),
                    offsets=jnp.asarray(offsets),
                    partners=jnp.asarray(partners[order].astype(np.int32)),
                    partner_angles=jnp.asarray(both[order].astype(np.float32)), camera=camera,
                    grid=index.grid, search_steps=steps, key=key)


def first_use(catalog, camera: Camera, config: Config | None = None) -> tuple[str, float] | None:
    """What :func:`build_database` builds and about how long it takes on a 2-core CPU (s); ``None``
    when it is cached."""
    config = Config() if config is None else config
    return pair_table_first_use("pyramid", _cache_key(catalog, camera, config), catalog, camera)


_WINDOWS: dict[tuple, int] = {}


def window_size(database: Database, eps_rad: float, upto_rad: float | None = None) -> int:
    """The most catalog pairs any window ``[θ − ε, θ + ε]`` (θ ≤ ``upto_rad`` if given) holds (host,
    memoised): the static width of a side's candidate list."""
    cache = (database.key, float(eps_rad), upto_rad)
    if cache not in _WINDOWS:
        _WINDOWS[cache] = widest_window(np.asarray(database.kvector.values), eps_rad, upto_rad)
    return _WINDOWS[cache]
