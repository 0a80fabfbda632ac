"""The MLV onboard database (paper §2.2, Fig. 2): reference catalog, index table, feature lookup.

Build (host, once, cached on disk):
1. ``n_boresights`` boresights evenly on the sphere (Fibonacci lattice), each a simulated image of
   the camera (square field, roll fixed or varied: :class:`~jstarid.algorithms.mlv.Config`);
2. the brightest N catalog stars in each image (the first N in-field rows of the boresight's
   sky-index cell list: rows are sorted brightest first) → C(N, 3) triangles;
3. triangles de-duplicated as sorted triples of catalog rows (the index table ``ID``); the reference
   catalog ``C`` is the set of stars used by at least one triangle;
4. each triangle's discretized features (v̂1, v̂2) (eqs. 1–4, float64).

Instead of the paper's two lookup tables LT_v1, LT_v2, one array of composite keys
``(v̂1 − v̂1_min)·stride + v̂2`` sorted ascending (triangles in the same order): eq. 7's rectangle is
2·Th1 + 1 contiguous ranges, each found by ``jnp.searchsorted`` (exact, jit-able, O(log T)).
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.base import cache_key
from jstarid.algorithms.mlv.config import Config
from jstarid.algorithms.mlv.features import discretize, singular_values, triangle_combinations
from jstarid.attitude import rotation_from_boresight
from jstarid.camera import Camera
from jstarid.catalog import cache_dir, load_or_build
from jstarid.geometry import precise
from jstarid.runtime.program_store import stored_jit
from jstarid.sky_index import build_sky_index, cell_of

__all__ = ["Database", "build_database", "fibonacci_sphere", "database_from_triangles", "window_counts"]

_DB_VERSION = 1
_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))
_BUILD_CHUNK = 4096  # boresights per vectorized step
#: Reach of the sky index beyond the frame's half diagonal: 10 % of it (a focal-length retry
#: rescales centroids by up to 2 %, the camera fit accepts up to ``max_focal_error``) plus 1°
#: (the check's tolerances, at most a few tenths of a degree, and the cluster fit's error).
SKY_MARGIN_DEG = 1.0
_SKY_GRID = 32  # cube-face cells per side: 2.8° cells (24 MB of lists at V ≤ 10, 6° field)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Database:
    """MLV database (a pytree: arrays are leaves, sizes and the camera are static).

    Attributes:
        keys: (T,) int32 composite feature keys ``(v̂1 − v1_offset)·stride + v̂2``, ascending.
        triangles: (T, 3) int32 reference-catalog indices of each triangle's stars, star m opposite the
            m-th shortest side.
        sides: (T, 3) float32 side angles (rad), ascending: ``sides[t, m]`` is opposite
            ``triangles[t, m]`` (vertex matching; derivable, so not in :attr:`nbytes`).
        star_rows: (S,) int32 catalog row of each reference-catalog star.
        star_vectors: (S, 3) float32 ICRS unit vectors of the reference stars.
        catalog_vectors: (M, 3) float32 ICRS unit vectors of the whole catalog (attitude check).
        catalog_mags: (M,) float32 their V magnitudes (the brightness test of the camera check).
        sky_cells: (6·G·G, K) int32 :class:`~jstarid.sky_index.SkyIndex` lists of the catalog stars
            that can be near the field of a boresight in each cell (the checks search these K, not
            all M stars; see :data:`SKY_MARGIN_DEG`).
        v1_offset: smallest v̂1 in the table (static int).
        stride: max v̂2 + 1 (static int); v̂2 ∈ [0, stride).
        n_rows: number of v̂1 rows, max v̂1 − v1_offset + 1 (static int).
        sky_grid: G of ``sky_cells`` (static int).
        camera: the static :class:`~jstarid.camera.Camera` it was built for (centroids → directions).
        dv1, dv2: the discretization units Δv1, Δv2 of the keys (static).
        info: build statistics (static): triangles, stars, bytes, build seconds, cache path.
        key: :meth:`cache_key` (static; empty when built from a given triangle table).
    """

    keys: jax.Array
    triangles: jax.Array
    sides: jax.Array
    star_rows: jax.Array
    star_vectors: jax.Array
    catalog_vectors: jax.Array
    catalog_mags: jax.Array
    sky_cells: jax.Array
    v1_offset: int = dataclasses.field(metadata={"static": True})
    stride: int = dataclasses.field(metadata={"static": True})
    n_rows: int = dataclasses.field(metadata={"static": True})
    camera: Camera = dataclasses.field(metadata={"static": True})
    sky_grid: int = dataclasses.field(metadata={"static": True})
    dv1: float = dataclasses.field(metadata={"static": True})
    dv2: float = dataclasses.field(metadata={"static": True})
    info: tuple = dataclasses.field(default=(), metadata={"static": True})
    key: str = dataclasses.field(default="", metadata={"static": True})

    def cache_key(self) -> str:
        """The database's cache key (:func:`jstarid.algorithms.base.cache_key`)."""
        return self.key

    @property
    def n_triangles(self) -> int:
        return int(self.keys.shape[0])

    @property
    def n_reference_stars(self) -> int:
        return int(self.star_rows.shape[0])

    @property
    def nbytes(self) -> int:
        """Compact storage in bytes, as an onboard table would hold it: the keys (int32), the
        index table (uint16 per star while the reference catalog has < 65,536 stars, else int32)
        and the reference catalog (int32 catalog row + 2 float32 angles per star)."""
        idx_bytes = 2 if self.n_reference_stars < 65536 else 4
        return self.n_triangles * (4 + 3 * idx_bytes) + self.n_reference_stars * (4 + 2 * 4)

    @property
    def device_nbytes(self) -> int:
        """Bytes of the arrays as held for identification (int32 / float32)."""
        return int(sum(np.asarray(a).nbytes for a in
                       (self.keys, self.triangles, self.sides, self.star_rows, self.star_vectors,
                 self.catalog_vectors, self.catalog_mags, self.sky_cells)))

    def info_dict(self) -> dict:
        return dict(self.info)


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) float64 unit vectors evenly spread on the sphere (Fibonacci lattice): point k has
    z = 1 − (2k + 1)/n and longitude k·(golden angle); equal areas 4π/n within a few per cent.
    """
    k = np.arange(n, dtype=np.float64)
    z = 1.0 - (2.0 * k + 1.0) / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.mod(k * _GOLDEN_ANGLE, 2.0 * math.pi)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def _cache_key(catalog, camera: Camera, config: Config) -> str:
    # the triangle table does not depend on Δv1, Δv2 (only the features computed from it at load
    # time do): one cached table serves every discretization
    fields = {k: v for k, v in config.database_fields().items() if k not in ("dv1", "dv2")}
    return cache_key("mlv", _DB_VERSION, catalog, camera, fields)


def _brightest_in_field(bore, roll, rows, vec, real, *, camera: Camera, n: int):
    """For each boresight, the first ``n`` in-field entries of its (brightest-first) star list.

    Args:
        bore: (c, 3) ICRS boresights; roll: (c,) rad.
        rows: (c, K) candidate catalog rows, ascending (= brightest first).
        vec: (c, K, 3) their ICRS unit vectors (anything for padding).
        real: (c, K) bool, False for padding entries.

    Returns:
        (c, n) int32 catalog rows (ascending; −1 where fewer than n stars are in the field).
    """
    att = rotation_from_boresight(bore, roll)  # (c, 3, 3): v_cam = C r
    v_cam = precise.einsum("cij,ckj->cki", att, vec)
    _, in_field = camera.project(v_cam)
    in_field &= real
    m = jnp.max(rows) + 1  # anything > every row
    sort_key = jnp.where(in_field, rows, m + rows)  # in-field rows first, still brightest first
    order = jnp.argsort(sort_key, axis=-1)[:, :n]
    picked = jnp.take_along_axis(rows, order, axis=-1)
    ok = jnp.take_along_axis(in_field, order, axis=-1)
    return jnp.where(ok, picked, -1)


_brightest_in_field_jit = stored_jit(_brightest_in_field, static_argnames=("camera", "n"))


def _triangle_table(catalog, camera: Camera, config: Config, progress: bool) -> np.ndarray:
    """(T, 3) int64 unique sorted triples of catalog rows (steps 1–3 of the module doc)."""
    from tqdm.auto import tqdm

    n_cat = len(catalog)
    bores = fibonacci_sphere(config.n_boresights)
    if config.database_roll_deg is None:
        rolls = np.mod(np.arange(config.n_boresights) * _GOLDEN_ANGLE, 2.0 * math.pi)
    else:
        rolls = np.full(config.n_boresights, math.radians(config.database_roll_deg))
    index = build_sky_index(catalog.unit_vectors, camera.half_diagonal_rad,
                            key=f"{catalog.fingerprint}-mlv-db")
    cells = index.cells  # (cells, K) ascending rows, padding = n_cat
    vec_pad = np.concatenate([catalog.unit_vectors, [[0.0, 0.0, -1.0]]]).astype(np.float32)
    combos = triangle_combinations(config.n_stars)
    base = np.int64(n_cat + 1)
    found = []
    chunks = range(0, config.n_boresights, _BUILD_CHUNK)
    for lo in tqdm(chunks, desc="MLV database", unit="chunk", disable=not progress):
        hi = min(lo + _BUILD_CHUNK, config.n_boresights)
        b = np.zeros((_BUILD_CHUNK, 3), np.float32)  # pad to one static shape (one compilation)
        b[: hi - lo] = bores[lo:hi]
        b[hi - lo:] = bores[lo]
        r = np.zeros(_BUILD_CHUNK, np.float32)
        r[: hi - lo] = rolls[lo:hi]
        rows = cells[np.asarray(cell_of(jnp.asarray(b), index.grid))]
        picked = np.asarray(_brightest_in_field_jit(
            jnp.asarray(b), jnp.asarray(r), jnp.asarray(rows), jnp.asarray(vec_pad[rows]),
            jnp.asarray(rows < n_cat), camera=camera, n=config.n_stars))[: hi - lo]
        tri = picked[:, combos].reshape(-1, 3).astype(np.int64)  # ascending within each triple
        tri = tri[np.all(tri >= 0, axis=1)]
        found.append(np.unique((tri[:, 0] * base + tri[:, 1]) * base + tri[:, 2]))
    codes = np.unique(np.concatenate(found)) if found else np.zeros(0, np.int64)
    return np.stack([codes // (base * base), (codes // base) % base, codes % base], axis=1)


def _angle(u, v):
    """Angles (rad) between unit vectors (..., 3), float64, accurate for small angles."""
    return 2.0 * np.arcsin(np.clip(0.5 * np.linalg.norm(u - v, axis=-1), 0.0, 1.0))


def database_from_triangles(catalog, camera: Camera, triangles: np.ndarray, dv1: float,
                            dv2: float, info: dict | None = None) -> Database:
    """Features, reference catalog and sorted lookup keys for a given triangle table.

    Args:
        catalog: the :class:`~jstarid.catalog.Catalog` whose rows ``triangles`` holds.
        camera: camera the database is for.
        triangles: (T, 3) integer catalog rows of each triangle (any order).
        dv1, dv2: discretization units (eq. 4).
        info: extra build statistics to record.

    Returns:
        A :class:`Database`.
    """
    triangles = np.sort(np.asarray(triangles, np.int64).reshape(-1, 3), axis=1)
    if triangles.shape[0] == 0:
        raise ValueError("no triangles: the field never holds three catalog stars")
    star_rows, inverse = np.unique(triangles, return_inverse=True)
    tri_ref = inverse.reshape(-1, 3)
    vec = np.asarray(catalog.unit_vectors, np.float64)
    sv = singular_values(vec[triangles[:, 0]], vec[triangles[:, 1]], vec[triangles[:, 2]], xp=np)
    v1h, v2h = discretize(sv[:, 0], sv[:, 1], dv1, dv2, xp=np)  # eq. 4 in float64
    v1_offset = int(v1h.min())
    stride = int(v2h.max()) + 1
    n_rows = int(v1h.max()) - v1_offset + 1
    keys = (v1h - v1_offset) * stride + v2h
    if keys.max() >= 2**31 - stride * 8:
        raise ValueError("feature keys overflow int32: use coarser Δv1, Δv2")
    order = np.lexsort((tri_ref[:, 2], tri_ref[:, 1], tri_ref[:, 0], keys))
    # side opposite each vertex, then vertices re-ordered by that side (ascending)
    a, b, c = (vec[triangles[:, m]] for m in range(3))
    opposite = np.stack([_angle(b, c), _angle(a, c), _angle(a, b)], axis=1)
    by_side = np.argsort(opposite, axis=1, kind="stable")
    tri_ref = np.take_along_axis(tri_ref, by_side, axis=1)
    opposite = np.take_along_axis(opposite, by_side, axis=1)
    info = dict(info or {})
    sky = build_sky_index(vec, 1.1 * camera.half_diagonal_rad + math.radians(SKY_MARGIN_DEG),
                          grid=_SKY_GRID, key=f"mlv-{catalog.fingerprint}")
    db = Database(
        keys=jnp.asarray(keys[order], jnp.int32),
        triangles=jnp.asarray(tri_ref[order], jnp.int32),
        sides=jnp.asarray(opposite[order], jnp.float32),
        star_rows=jnp.asarray(star_rows, jnp.int32),
        star_vectors=jnp.asarray(vec[star_rows], jnp.float32),
        catalog_vectors=jnp.asarray(vec, jnp.float32),
        catalog_mags=jnp.asarray(catalog.mag, jnp.float32),
        sky_cells=jnp.asarray(sky.cells), sky_grid=sky.grid,
        v1_offset=v1_offset, stride=stride, n_rows=n_rows, camera=camera,
        dv1=float(dv1), dv2=float(dv2), info=(),
    )
    info.update(n_triangles=db.n_triangles, n_reference_stars=db.n_reference_stars,
                nbytes=db.nbytes, device_nbytes=db.device_nbytes)
    return dataclasses.replace(db, info=tuple(sorted(info.items())))


def window_counts(database: Database, th1: int, th2: int) -> np.ndarray:
    """How many database triangles lie in each database triangle's own eq. 7 window (host, exact).

    A query triangle is a noisy copy of database triangles, so these counts are the candidates a
    query meets: their distribution sizes the candidate buffers
    (:func:`~jstarid.algorithms.mlv.identify.candidate_buffers`). A narrow field packs far more
    triangles into the same feature bins (``tetra3_test``: median 790 per window at Th = 1,
    ``mlv2021``: 23).

    Args:
        database: the :class:`Database`.
        th1, th2: the window's half-widths Th1, Th2 (bins).

    Returns:
        (T,) int64 counts (each at least 1: the triangle itself).
    """
    keys = np.asarray(database.keys, np.int64)
    stride = database.stride
    row, v2 = keys // stride, keys % stride
    lo2, hi2 = np.maximum(v2 - th2, 0), np.minimum(v2 + th2, stride - 1)
    total = np.zeros(keys.shape, np.int64)
    for d1 in range(-int(th1), int(th1) + 1):  # one contiguous key range per v̂1 row (module doc)
        r = row + d1
        inside = (r >= 0) & (r < database.n_rows)
        count = (np.searchsorted(keys, r * stride + hi2, side="right")
                 - np.searchsorted(keys, r * stride + lo2, side="left"))
        total += np.where(inside, count, 0)
    return total


def build_database(catalog, camera: Camera, config: Config | None = None, *,
                   use_cache: bool = True, progress: bool = True) -> Database:
    """Build (or load from the disk cache) the MLV database for a catalog and camera.

    Args:
        catalog: :class:`~jstarid.catalog.Catalog` (the identification catalog, V ≤ camera limit).
        camera: :class:`~jstarid.camera.Camera`.
        config: :class:`~jstarid.algorithms.mlv.Config` (default: paper values); ``n_stars``,
            ``dv1``, ``dv2``, ``n_boresights`` and ``database_roll_deg`` shape the database.
        use_cache: read/write ``mlv-db-<hash>.npz`` under :func:`jstarid.catalog.cache_dir`, keyed
            by the catalog fingerprint, every camera field and those config fields.
        progress: show a tqdm progress bar over boresight chunks.

    Returns:
        A :class:`Database`; ``db.info_dict()`` has ``n_triangles``, ``nbytes``, ``build_seconds``
        (0 when loaded from the cache) and ``cache_path``.
    """
    config = Config() if config is None else config
    key = _cache_key(catalog, camera, config)
    path = cache_dir() / f"mlv-{key}.npz"

    def build() -> dict:
        t0 = time.perf_counter()
        triangles = _triangle_table(catalog, camera, config, progress)
        return {"triangles": triangles.astype(np.int32), "build_seconds": time.perf_counter() - t0}

    # only the triangle table is stored: the features follow from it and Δv1, Δv2 (see _cache_key)
    arrays, cached = load_or_build(path if use_cache else None, build)
    seconds = float(arrays["build_seconds"])
    info = ({"build_seconds": 0.0, "cached": True, "original_build_seconds": seconds, "cache_path": str(path)}
            if cached else
            {"build_seconds": seconds, "cached": False, "cache_path": str(path) if use_cache else ""})
    db = database_from_triangles(catalog, camera, arrays["triangles"], config.dv1, config.dv2, info=info)
    return dataclasses.replace(db, key=key)


def first_use(catalog, camera: Camera, config: Config | None = None) -> tuple[str, float] | None:
    """What :func:`build_database` will build for these settings and about how long it takes on a
    2-core CPU (s); ``None`` when it is cached."""
    config = Config() if config is None else config
    if (cache_dir() / f"mlv-{_cache_key(catalog, camera, config)}.npz").exists():
        return None
    return f"MLV triangle database for {camera.name} ({config.n_boresights:,} boresights)", 10.0
