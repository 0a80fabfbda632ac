"""A cube-map index of the sky: for any boresight, the few hundred stars that can be in the field.

The sphere is cut into ``6 × G × G`` gnomonic cube-face cells; each stores (padded to a static
capacity K) the stars within ``R = field radius + cell radius + margin`` of its centre, so a
boresight anywhere in the cell sees only stars of that list and a jit-compiled caller gathers K
stars per scene in O(1) (``cell_of`` is arithmetic). Built on the host once per (catalog, radius),
memoised.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from jstarid.runtime import device_cache

__all__ = ["SkyIndex", "brightest_per_cell", "build_sky_index", "cell_of", "local_stars"]

_MEMO: dict = {}


@dataclasses.dataclass(frozen=True, eq=False)
class SkyIndex:
    """Per-cell star lists.

    Attributes:
        cells: (6·G·G, K) int32 indices into the simulation star table; padding points at the extra
            sentinel row ``M`` (a star of magnitude +inf that is never detected).
        grid: G, cells per cube-face side.
        radius_rad: R, the angular radius each list covers (rad).
        counts: (6·G·G,) int32 number of real (non-padding) entries per cell; lists are padded at
            the end, so ``cells[c, :counts[c]]`` are the stars of cell c.
    """

    cells: np.ndarray
    grid: int
    radius_rad: float
    counts: np.ndarray

    @property
    def capacity(self) -> int:
        return int(self.cells.shape[1])

    def device_arrays(self):
        """``(cells, counts)`` as device arrays, copied once per index (the index is memoised)."""
        return device_cache.cached(self, "sky_index",
                                   lambda: (jnp.asarray(self.cells), jnp.asarray(self.counts)))


def cell_of(direction, grid: int):
    """Cube-map cell of unit vectors (..., 3) → (...,) int32 cell index in ``[0, 6·G·G)``: the face is the
    axis of the largest |component| and its sign; (u, v) ∈ [−1, 1] are the other two components over it.
    """
    a = jnp.abs(direction)
    axis = jnp.argmax(a, axis=-1)
    major = jnp.take_along_axis(direction, axis[..., None], axis=-1)[..., 0]
    face = 2 * axis + (major < 0)
    # the two minor components, in increasing axis order
    i1 = jnp.where(axis == 0, 1, 0)
    i2 = jnp.where(axis == 2, 1, 2)
    denom = jnp.maximum(jnp.abs(major), 1e-12)
    u = jnp.take_along_axis(direction, i1[..., None], axis=-1)[..., 0] / denom
    v = jnp.take_along_axis(direction, i2[..., None], axis=-1)[..., 0] / denom
    iu = jnp.clip(jnp.floor((u + 1.0) * 0.5 * grid), 0, grid - 1).astype(jnp.int32)
    iv = jnp.clip(jnp.floor((v + 1.0) * 0.5 * grid), 0, grid - 1).astype(jnp.int32)
    return (face * grid * grid + iu * grid + iv).astype(jnp.int32)


def brightest_per_cell(vectors, grid: int, per_cell: int, rows) -> np.ndarray:
    """The first ``per_cell`` of ``rows`` (sorted brightest first) in each cube-map sky cell.

    Args:
        vectors: (R, 3) unit vectors of ``rows``.
        grid: cells per cube-face side (:func:`jstarid.sky_index.cell_of`; 6·grid² cells).
        per_cell: stars kept per cell.
        rows: (R,) catalog rows, brightest first.

    Returns:
        (≤ R,) int32 the kept rows, in their input order (brightest first).
    """
    rows = np.asarray(rows)
    cell = np.asarray(cell_of(np.asarray(vectors, np.float64), grid))
    order = np.argsort(cell, kind="stable")  # by cell, brightest first within each cell
    sorted_cells = cell[order]
    first = np.searchsorted(sorted_cells, sorted_cells, side="left")
    rank = np.empty(len(rows), np.int64)
    rank[order] = np.arange(len(rows)) - first  # brightness rank of each star within its cell
    return rows[rank < per_cell].astype(np.int32)


def local_stars(cells, star_vectors, boresight, grid: int):
    """The indexed stars that can be in the field of a boresight (jit-able, fixed size).

    Args:
        cells: (6·G·G, K) int32 lists of :class:`SkyIndex` (``device_arrays()[0]``); padding M.
        star_vectors: (M, 3) the vectors the index was built from (ICRS unit vectors).
        boresight: (3,) ICRS unit vector (``C[2]`` of an attitude ``v_cam = C r``).
        grid: G of the index.

    Returns:
        ``(rows, vectors, real)``: (K,) int32 star indices (M for padding), (K, 3) their vectors and
        (K,) bool, False for padding. A padding entry's vector is the antipode of the boresight, so
        no detection in the field is ever near it.
    """
    rows = cells[cell_of(boresight, grid)]
    real = rows < star_vectors.shape[0]
    vectors = jnp.where(real[:, None], star_vectors[jnp.minimum(rows, star_vectors.shape[0] - 1)],
                        -boresight[None, :])
    return rows, vectors, real


def _cell_geometry(grid: int):
    """Cell-centre unit vectors (6·G·G, 3) and the largest centre-to-corner angle (rad)."""
    edges = np.linspace(-1.0, 1.0, grid + 1)
    mid = 0.5 * (edges[:-1] + edges[1:])
    centres, radius = [], 0.0
    for face in range(6):
        axis, sign = divmod(face, 2)
        sign = -1.0 if sign else 1.0
        minor = [i for i in range(3) if i != axis]

        def to_vec(u, v, axis=axis, sign=sign, minor=minor):
            vec = np.zeros(np.broadcast(u, v).shape + (3,))
            vec[..., axis] = sign
            vec[..., minor[0]] = u
            vec[..., minor[1]] = v
            return vec / np.linalg.norm(vec, axis=-1, keepdims=True)

        uu, vv = np.meshgrid(mid, mid, indexing="ij")
        c = to_vec(uu, vv)
        centres.append(c.reshape(-1, 3))
        for du in (edges[:-1], edges[1:]):
            for dv in (edges[:-1], edges[1:]):
                cu, cv = np.meshgrid(du, dv, indexing="ij")
                corner = to_vec(cu, cv)
                ang = np.arccos(np.clip(np.sum(corner * c, -1), -1.0, 1.0))
                radius = max(radius, float(ang.max()))
    return np.concatenate(centres), radius


def build_sky_index(star_vectors: np.ndarray, field_radius_rad: float, *, grid: int | None = None,
                    margin_rad: float = 0.0, subset: np.ndarray | None = None,
                    key: str | None = None) -> SkyIndex:
    """Per-cell lists of the stars within reach of any boresight in the cell.

    Args:
        star_vectors: (M, 3) ICRS unit vectors of the stars to index.
        field_radius_rad: largest boresight-to-star angle that can be in the field (rad).
        grid: cells per face side; default chosen so a cell is ≈ 1/8 of the field radius.
        margin_rad: extra angle (rad), e.g. for position noise pushing a star into the frame.
        subset: optional (S,) indices of the stars to index (e.g. those bright enough to be
            detected); the lists still hold indices into ``star_vectors``.
        key: memoisation key (e.g. the catalog fingerprint plus what chose ``subset``); ``None``
            disables memoisation.

    Returns:
        A :class:`SkyIndex`; the padding index is ``M`` (``len(star_vectors)``).
    """
    from scipy.spatial import cKDTree

    if grid is None:
        grid = int(min(64, max(8, math.ceil(4 * math.pi / max(field_radius_rad, 1e-3)))))
    memo_key = None if key is None else (key, round(field_radius_rad, 9), grid, round(margin_rad, 9))
    if memo_key is not None and memo_key in _MEMO:
        return _MEMO[memo_key]
    centres, cell_radius = _cell_geometry(grid)
    reach = field_radius_rad + cell_radius + margin_rad + 1e-6
    if reach >= math.pi:
        reach = math.pi
    ids = np.arange(len(star_vectors)) if subset is None else np.asarray(subset)
    tree = cKDTree(star_vectors[ids])
    lists = tree.query_ball_point(centres, 2.0 * math.sin(min(reach, math.pi) / 2.0) + 1e-12)
    k = max(1, max(len(x) for x in lists))
    k = int(math.ceil(k / 64) * 64)  # bucket the capacity so similar catalogs share compilations
    m = star_vectors.shape[0]
    cells = np.full((len(lists), k), m, dtype=np.int32)
    for i, idx in enumerate(lists):
        cells[i, : len(idx)] = np.sort(ids[idx])
    counts = np.array([len(x) for x in lists], dtype=np.int32)
    index = SkyIndex(cells=cells, grid=grid, radius_rad=reach, counts=counts)
    if memo_key is not None:
        _MEMO[memo_key] = index
    return index
