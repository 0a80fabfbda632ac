"""The SGM database: one neighbor graph per catalog star, sorted by MST weight, with a k-vector.

You et al. 2022, "Database generation": every catalog star J is a main star; its neighbor graph G_J
(J and every star within r; edge weight = angular separation, deg) gives the adjacency A_J (graph
matching) and w_J, the total MST edge weight (rough search, eq. 1). Rows are sorted by w_J so that a
k-vector finds ``|w_J − w_I| ≤ Δw`` in O(1). Built on the host once, cached on disk (``np.savez``
under :func:`jstarid.catalog.cache_dir`, keyed by the catalog fingerprint and the shaping fields).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from jstarid.algorithms.base import cache_key
from jstarid.algorithms.sgm.bound import row_table, sorted_edges
from jstarid.algorithms.sgm.config import Config
from jstarid.algorithms.sgm.graph import adjacency_deg, catalog_neighbors, mst_weight, plane_coords
from jstarid.camera import radius_that_fits
from jstarid.catalog import cache_dir, load_or_build, read_arrays, write_arrays
from jstarid.geometry import KVector, build_kvector
from jstarid.runtime import device_cache, on_every_device
from jstarid.runtime.program_store import stored_jit

__all__ = ["Database", "build_database", "database_tables"]

_FORMAT = 2  # bump when the stored arrays change meaning (2: adjacency recomputed on load)
_STORED = ("main", "members", "n", "w")


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["main", "members", "n", "adj", "w", "kvector"],
                   meta_fields=["capacity", "radius_deg", "camera", "catalog", "build_seconds",
                                "nbytes", "from_cache", "key"])
@dataclasses.dataclass(frozen=True, eq=False)
class Database:
    """SGM database, rows sorted by ascending w (a pytree: the arrays are its leaves).

    Attributes:
        main: (D,) int32 catalog row of each database main star.
        members: (D, K) int32 catalog rows of the graph vertices (vertex 0 = the main star; −1 pad).
        n: (D,) int32 vertex count (main star included).
        adj: (D, K, K) float32 adjacency A_J (deg), 0 on padding.
        w: (D,) float32 MST weight w_J (deg), ascending.
        kvector: :class:`~jstarid.geometry.KVector` over ``w``.
        capacity: K.
        radius_deg: r used to build it (deg).
        camera: the camera the scenes come from (for ``unproject``).
        catalog: the catalog whose rows ``main``/``members`` refer to.
        build_seconds: time spent building (0 when loaded from the cache … then ``load_seconds``).
        nbytes: bytes of the arrays in memory (the adjacency included).
        from_cache: loaded from disk.
        key: :meth:`cache_key`, the name of its cache file.
    """

    #: The first ``identify`` of a process with no program kept on disk compiles one kernel per
    #: graph-size bucket: ≈ 95 s for the demo on 2 CPU cores (:func:`jstarid.engine.plan`).
    FIRST_COMPILE_SECONDS: ClassVar[float] = 100.0

    main: np.ndarray
    members: np.ndarray
    n: np.ndarray
    adj: np.ndarray
    w: np.ndarray
    kvector: KVector
    capacity: int
    radius_deg: float
    camera: object
    catalog: object
    build_seconds: float
    nbytes: int
    from_cache: bool
    key: str = ""

    def cache_key(self) -> str:
        """The database's cache key (:func:`jstarid.algorithms.base.cache_key`)."""
        return self.key

    def __len__(self) -> int:
        return int(self.main.shape[0])

    @property
    def edges(self) -> np.ndarray:
        """(D, K(K − 1)/2) float32 sorted edge lengths of each graph, +inf padded (deg;
        :func:`~.bound.sorted_edges`, computed on first use); a graph of ≤ r vertices is read whole from
        the first r(r − 1)/2 entries.
        """
        return self._per_graph("_edges", sorted_edges)

    @property
    def rows(self) -> np.ndarray:
        """(D, K, K) float32 sorted rows of each graph's adjacency, +inf padded (deg;
        :func:`~.bound.row_table`, computed on first use): the row bound's input, sorted once."""
        return self._per_graph("_rows", row_table)

    @property
    def plane(self) -> np.ndarray:
        """(D, K, 2) float32 :func:`~.graph.plane_coords` of each graph's vertices (deg; computed on
        first use from the catalog): the triangle screen's input (:mod:`.screen`)."""
        return device_cache.cached(self, "sgm_plane", lambda: _plane(self.catalog, self.members, self.n))

    def _per_graph(self, name: str, fn) -> np.ndarray:
        """``fn(adj, mask)`` of every graph, in blocks of 512, once per database
        (:data:`jstarid.runtime.device_cache`).
        """
        def make():
            mask = np.arange(self.capacity)[None, :] < self.n[:, None]
            return np.concatenate([np.asarray(fn(self.adj[lo:lo + 512], mask[lo:lo + 512]))
                                   for lo in range(0, len(self), 512)])

        return device_cache.cached(self, "sgm" + name, make)


def _round_up(x: int, m: int) -> int:
    return int(math.ceil(x / m) * m)


def _cache_key(catalog, config: Config) -> str:
    # the graphs do not depend on the camera: the paper projects each main star to the centre
    return cache_key("sgm", _FORMAT, catalog, None, config.database_fields())


def _build_arrays(catalog, config: Config, progress: bool):
    vec = np.asarray(catalog.unit_vectors, np.float64)
    n_stars = vec.shape[0]
    neigh = [catalog_neighbors(vec, j, config.radius_deg)
             for j in tqdm(range(n_stars), desc="SGM neighbor graphs", disable=not progress)]
    counts = np.array([len(x) for x in neigh], np.int32)
    largest = int(counts.max())
    cap = _capacity(largest, config)
    if largest > cap:  # an explicit neighbor_capacity too small
        worst = int(np.argmax(counts))
        raise ValueError(f"neighbor_capacity={cap} is too small: catalog row {worst} has "
                         f"{largest} stars within r={config.radius_deg}°; use ≥ {largest} or None")
    members = np.full((n_stars, cap), -1, np.int32)
    for j, rows in enumerate(neigh):
        members[j, :rows.size] = rows
    adj = _adjacency(catalog, members, counts)
    mask = np.arange(cap)[None, :] < counts[:, None]
    # MST weights with the same jnp Prim routine the scenes use (identical arithmetic for w_I, w_J)
    mst = jax.jit(jax.vmap(mst_weight))
    w = np.zeros(n_stars, np.float32)
    step = 512
    for s in tqdm(range(0, n_stars, step), desc="SGM MST weights", disable=not progress):
        w[s:s + step] = np.asarray(mst(jnp.asarray(adj[s:s + step]), jnp.asarray(mask[s:s + step])))
    order = np.argsort(w, kind="stable")
    return {"main": order.astype(np.int32), "members": members[order], "n": counts[order],
            "adj": adj[order], "w": w[order]}


_BLOCK = 512  # graphs per adjacency call (one compiled shape per capacity)


@stored_jit
def _block_adjacency(vecs, mask):
    return jax.vmap(adjacency_deg)(jnp.where(mask[..., None], vecs, 0.0), mask)


@stored_jit
def _block_plane(vecs, mask):
    return jax.vmap(plane_coords)(jnp.where(mask[..., None], vecs, 0.0), mask)


def _plane(catalog, members: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(D, K, 2) :func:`~.graph.plane_coords` of every database graph, in blocks of ``_BLOCK``."""
    return _per_block(catalog, members, n, _block_plane)


def _per_block(catalog, members: np.ndarray, n: np.ndarray, fn) -> np.ndarray:
    """``fn(vecs, mask)`` of every database graph's vertex vectors, ``_BLOCK`` graphs per call."""
    vec = jnp.asarray(np.asarray(catalog.unit_vectors), jnp.float32)
    cap = members.shape[1]
    mask = np.arange(cap)[None, :] < n[:, None]
    out = None  # filled in place: the adjacency is hundreds of MB, no second copy
    for lo in range(0, members.shape[0], _BLOCK):
        rows = members[lo:lo + _BLOCK]
        pad = _BLOCK - rows.shape[0]
        take = np.pad(np.maximum(rows, 0), ((0, pad), (0, 0)))
        keep = np.pad(mask[lo:lo + _BLOCK], ((0, pad), (0, 0)))
        block = np.asarray(fn(vec[take], jnp.asarray(keep)))[:rows.shape[0]]
        if out is None:
            out = np.empty((members.shape[0],) + block.shape[1:], block.dtype)
        out[lo:lo + rows.shape[0]] = block
    return out


def _adjacency(catalog, members: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(D, K, K) float32 adjacency A_J (deg, 0 on padding) of every database graph.

    Computed by the image graphs' own :func:`~.graph.adjacency_deg` in float32 (the same arithmetic
    on both sides of eq. 2), in blocks of ``_BLOCK`` graphs. Not stored in the cache but recomputed
    on load: it is 99 % of the database (327 of 332 MB for ``tetra3_test``, V ≤ 7, r = 3.8°) and takes
    about a second to rebuild from ``members``.
    """
    return _per_block(catalog, members, n, _block_adjacency)


def build_database(catalog, camera, config: Config | None = None, *, use_cache: bool = True,
                   progress: bool = True) -> Database:
    """Build (or load from the disk cache) the SGM database.

    Args:
        catalog: :class:`~jstarid.catalog.Catalog`; every star is a database main star.
        camera: :class:`~jstarid.camera.Camera` of the scenes (kept for ``identify``; the database
            itself does not depend on it: the paper projects each main star to the image centre).
        config: :class:`Config` (``None`` → defaults); ``radius_deg``, ``neighbor_capacity`` and
            ``size_bucket`` shape it.
        use_cache: read/write ``sgm-db-*.npz`` under :func:`jstarid.catalog.cache_dir`.
        progress: show tqdm progress bars while building.

    Returns:
        :class:`Database`.

    Raises:
        ValueError: an explicit ``neighbor_capacity`` smaller than the largest neighbor graph, or a
            camera whose frame the neighbor circle does not fit (:func:`camera_problem`).
    """
    config = Config() if config is None else config
    problem = camera_problem(camera, config, catalog)
    if problem:
        raise ValueError(problem)
    key = _cache_key(catalog, config)
    path = cache_dir() / f"sgm-{key}.npz"
    t0 = time.perf_counter()
    # the adjacency is not stored (99 % of the database, a second to recompute: _adjacency)
    arrays, from_cache = load_or_build(
        path if use_cache else None, lambda: _build_arrays(catalog, config, progress),
        load=functools.partial(read_arrays, names=_STORED),
        save=lambda file, built: write_arrays(file, {k: built[k] for k in _STORED}))
    if from_cache:
        arrays["adj"] = _adjacency(catalog, arrays["members"], arrays["n"])
    kv, order = build_kvector(arrays["w"])
    if not np.array_equal(order, np.arange(order.size)):  # stored sorted; stable sort keeps it
        raise RuntimeError("SGM database is not sorted by w")
    elapsed = time.perf_counter() - t0
    return Database(
        main=arrays["main"], members=arrays["members"], n=arrays["n"], adj=arrays["adj"],
        w=arrays["w"], kvector=kv, capacity=int(arrays["members"].shape[1]),
        radius_deg=float(config.radius_deg), camera=camera, catalog=catalog,
        build_seconds=elapsed, nbytes=int(sum(a.nbytes for a in arrays.values())),
        from_cache=from_cache, key=key)


def camera_problem(camera, config: Config | None = None, catalog=None) -> str | None:
    """Why SGM cannot work on ``camera`` with ``config`` (one line), or ``None``. Said before
    anything is built.

    * The neighbor graph of the main star needs the whole circle of radius r around it inside the
      frame (§3.1): a circle wider than the half field (the principal point to the nearest edge)
      cuts every image graph, and no database graph can match it.
    * The database holds a (K, K) adjacency per catalog star, K the largest neighbor graph: past
      ``config.max_database_mb`` it does not fit a laptop (the narrow twin, V ≤ 10 and r = 2°:
      106,172 graphs of up to 95 stars, 3.6 GiB), and eq. 2's (pq)² affinity per candidate grows
      with it.

    Args:
        camera: the :class:`~jstarid.Camera`.
        config: SGM's :class:`Config` (default ``Config()``).
        catalog: the catalog the database would be built from (default: ``camera.mag_limit``'s).
    """
    config = Config() if config is None else config
    half_fov = camera.inscribed_half_field_deg
    if config.radius_deg > half_fov:
        return (f"SGM's neighbor circle r = {config.radius_deg:g}° does not fit the {half_fov:.2f}° "
                f"half field of camera {camera.name}: every image graph would be cut by the frame; "
                f"give radius_deg ≤ {math.floor(half_fov * 100) / 100:g} (e.g. --set "
                f"sgm.radius_deg={radius_that_fits(camera, config.radius_deg):g}) or leave SGM out")
    if catalog is None:
        from jstarid.catalog import load_catalog

        catalog = load_catalog(camera.mag_limit)
    sizes = graph_sizes(catalog, config.radius_deg)
    cap = _capacity(int(sizes.max()), config)
    mib = sizes.size * cap * cap * 4 / 2**20
    if mib <= config.max_database_mb:
        return None
    return (f"SGM's database for camera {camera.name} would hold {sizes.size:,} neighbor graphs of "
            f"up to {int(sizes.max())} stars (r = {config.radius_deg:g}°, catalog V ≤ "
            f"{catalog.mag_limit:g}): {mib / 1024:.1f} GiB of adjacency, over max_database_mb = "
            f"{config.max_database_mb}; use a brighter catalog (--mag-limit), a smaller radius_deg or a "
            f"larger max_database_mb (--set sgm.max_database_mb=…), or leave SGM out")


def graph_sizes(catalog, radius_deg: float) -> np.ndarray:
    """(D,) int vertex count of each catalog star's neighbor graph (itself included) at radius r."""
    from scipy.spatial import cKDTree

    vec = np.asarray(catalog.unit_vectors, np.float64)
    chord = 2.0 * math.sin(math.radians(radius_deg) / 2.0)
    return np.asarray(cKDTree(vec).query_ball_point(vec, chord, return_length=True), np.int64)


def _capacity(largest: int, config: Config) -> int:
    """K: ``neighbor_capacity``, or the largest graph rounded up to ``size_bucket``."""
    if config.neighbor_capacity is not None:
        return int(config.neighbor_capacity)
    return _round_up(max(largest, 2), config.size_bucket)


def first_use(catalog, camera, config: Config | None = None) -> tuple[str, float] | None:
    """What :func:`build_database` will build for these settings and about how long it takes on a
    2-core CPU (s); ``None`` when it is cached."""
    config = Config() if config is None else config
    if (cache_dir() / f"sgm-{_cache_key(catalog, config)}.npz").exists():
        return None
    return f"SGM neighbor graphs of {len(catalog):,} stars", 5.0


def database_tables(db: Database, table: str = "adj"):
    """``(db.<table>, n)`` as device arrays on every device (placed once per database and table):
    ``"adj"`` for the spectral matching, ``"rows"`` (``Database.rows``) for the row bound."""
    return on_every_device(db, table, lambda: (jnp.asarray(getattr(db, table)), jnp.asarray(db.n)))
