"""An index of the catalog's triangles by their two shortest sides: every star triangle that can lie
in one frame, found from a measured triangle in a few binary searches.

A triangle's sides sorted ascending, ``s₁ ≤ s₂ ≤ s₃`` (rad), do not depend on the order of its
stars, and sorting moves no side by more than the largest error of any one side (the sorted order is
1-Lipschitz in the largest-difference norm), so a measured triangle whose sides are each within ε
of a catalog triangle's has sorted sides within ε of the catalog's sorted sides. The index cuts the
(s₁, s₂) plane into square cells of width 2ε (ε = the build tolerance): a window ``[t − ε, t + ε]``
spans at most two cells per axis, and the cells of one s₁ column are adjacent in the code order
``code = c₁ · n_cells + c₂`` — so a query is two runs of the sorted codes, each found by a binary
search (:func:`query`), and s₃ is checked on the run's entries.

Built on the host from a pair table (:func:`jstarid.geometry.star_pairs.pair_table`), memoised per
(stars, frame, tolerance). A triangle's sides are all at most the frame's diagonal; the table grows as
the cube of the stars per field, so it is capped at :data:`MAX_TRIANGLES` (:func:`index_problem`
says when a camera's catalog passes it).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.catalog import cache_dir, load_or_build
from jstarid.geometry.angles import angle_between_host
from jstarid.geometry.star_pairs import frame_pair_angle, pair_table
from jstarid.sky_index import brightest_per_cell

__all__ = ["MAX_TRIANGLES", "SEARCH_TRIANGLES", "TooManyTriangles", "TriangleIndex", "build_triangle_index",
           "expected_triangles", "index_problem", "query", "stars_that_fit"]

MAX_TRIANGLES = 6_000_000  # ≈ 170 MB of table: beyond it the catalog is too deep for the field
# the triangles a deep catalog's brightest stars per sky cell are chosen to give (stars_that_fit):
# three quarters of the cap: the uniform-sky estimate only approximates the count (it overestimated an
# even selection by a third on challenge6)
SEARCH_TRIANGLES = MAX_TRIANGLES * 3 // 4
_MEMO: dict = {}
_FORMAT = 1  # bump when the cached index's layout changes meaning


class TooManyTriangles(ValueError):
    """The catalog has more than :data:`MAX_TRIANGLES` triangles per frame of the camera."""


@functools.partial(jax.tree_util.register_dataclass, data_fields=["codes", "stars", "sides"],
                   meta_fields=["cell_rad", "n_cells", "run", "key"])
@dataclasses.dataclass(frozen=True)
class TriangleIndex:
    """Catalog triangles sorted by cell (a pytree: arrays are leaves; the rest static).

    Attributes:
        codes: (T,) int32 cell code ``c₁ · n_cells + c₂`` of each triangle, ascending.
        stars: (T, 3) int32 catalog rows; star m is opposite side m.
        sides: (T, 3) float32 the sides s₁ ≤ s₂ ≤ s₃ (rad).
        cell_rad: the cells' width 2ε (rad). n_cells: cells per axis.
        run: the most triangles in two adjacent cells of one column (a query run's static length).
        key: identifies the stars, frame and tolerance.
    """

    codes: jax.Array
    stars: jax.Array
    sides: jax.Array
    cell_rad: float
    n_cells: int
    run: int
    key: str = ""

    @property
    def size(self) -> int:
        return int(self.codes.shape[0])


def expected_triangles(n_stars: int, max_side_rad: float) -> float:
    """About how many triangles of ``n_stars`` spread evenly over the sky have every side at most
    ``max_side_rad``: n · k² · s / 6 for k neighbours within the angle, s the share of a star's
    neighbour pairs that are neighbours too. s = 0.9 matches the 1.02 M triangles counted for
    Hipparcos V ≤ 5.7 in a 10° × 7.5° frame (``experiments/cameras/challenge10.toml``); the build
    counts the real number."""
    neighbours = n_stars * (1.0 - math.cos(max_side_rad)) / 2.0
    return n_stars * neighbours * neighbours * 0.9 / 6.0


def index_problem(n_stars: int, camera) -> str | None:
    """Why a catalog of ``n_stars`` is too deep for a triangle index of ``camera``'s frame, or ``None``."""
    expected = expected_triangles(n_stars, frame_pair_angle(camera))
    if expected > MAX_TRIANGLES:
        return (f"about {expected:,.0f} catalog triangles fit in a {camera.name} frame (more than "
                f"{MAX_TRIANGLES:,}); the hypothesis search needs a brighter catalog")
    return None


def stars_that_fit(vectors, mags, camera, budget: float | None = None) -> np.ndarray:
    """The catalog rows whose triangles an index for ``camera`` can hold: every row where the catalog's
    triangles per frame fit ``budget``, else the brightest star of each sky cell.

    A magnitude cut would leave the sparse parts of the sky with too few stars for a triangle; the
    brightest star of each sky cell gives every frame about the same number, spread evenly. The
    cells are the finest whose stars' expected triangles (:func:`expected_triangles`) fit ``budget``.

    Args:
        vectors: (M, 3) ICRS unit vectors. mags: (M,) their V (mag).
        camera: the :class:`~jstarid.camera.Camera`.
        budget: the most triangles per frame wanted (default :data:`SEARCH_TRIANGLES`).

    Returns:
        (K,) int32 rows, ascending (all M where they fit).
    """
    budget = SEARCH_TRIANGLES if budget is None else budget
    vectors, mags = np.asarray(vectors, np.float64), np.asarray(mags)
    n = vectors.shape[0]
    max_side = frame_pair_angle(camera)
    if expected_triangles(n, max_side) <= budget:
        return np.arange(n, dtype=np.int32)
    order = np.argsort(mags, kind="stable")
    by_brightness = vectors[order]

    def brightest(grid):  # the brightest star of each of the 6 · grid² cells
        return brightest_per_cell(by_brightness, grid, 1, order)

    lo, hi = 1, 2  # cells per cube-face side: lo fits the budget; hi (once found) does not
    while expected_triangles(brightest(hi).size, max_side) <= budget:
        lo, hi = hi, 2 * hi
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if expected_triangles(brightest(mid).size, max_side) <= budget else (lo, mid)
    kept = brightest(lo)
    return np.sort(kept).astype(np.int32)


def _triangles(vectors: np.ndarray, max_side: float, camera) -> np.ndarray:
    """(T, 3) int32 rows a < b < c of every triangle whose three sides are at most ``max_side``.

    Raises:
        TooManyTriangles: more than :data:`MAX_TRIANGLES` (stops counting there).
    """
    n = vectors.shape[0]
    _, pairs = pair_table(vectors, max_side)
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))].astype(np.int64)
    edge_codes = pairs[:, 0] * n + pairs[:, 1]  # ascending: sorted by (first, second)
    offsets = np.searchsorted(pairs[:, 0], np.arange(n + 1))
    out, total = [], 0
    for a in range(n):
        later = pairs[offsets[a]:offsets[a + 1], 1]  # neighbours after a, ascending
        if later.size < 2:
            continue
        jb, jc = np.triu_indices(later.size, 1)
        b, c = later[jb], later[jc]
        code = b * n + c
        at = np.minimum(np.searchsorted(edge_codes, code), edge_codes.size - 1)
        keep = edge_codes[at] == code
        if np.any(keep):
            out.append(np.stack([np.full(int(keep.sum()), a), b[keep], c[keep]], 1))
            total += out[-1].shape[0]
            if total > MAX_TRIANGLES:
                raise TooManyTriangles(f"more than {MAX_TRIANGLES:,} catalog triangles fit in a "
                                       f"{camera.name} frame; the hypothesis search needs a brighter catalog")
    return np.concatenate(out).astype(np.int32) if out else np.zeros((0, 3), np.int32)


def build_triangle_index(vectors, camera, eps_rad: float) -> TriangleIndex:
    """The triangle index of ``vectors`` for ``camera``'s frame at tolerance ``eps_rad`` (memoised).

    Args:
        vectors: (S, 3) ICRS unit vectors (row = catalog row).
        camera: the :class:`~jstarid.camera.Camera`: sides up to its diagonal (with the pair table's
            1 % margin).
        eps_rad: the largest side tolerance a query may use (rad); the cells are 2ε wide.

    Raises:
        ValueError: a non-positive tolerance.
        TooManyTriangles: more than :data:`MAX_TRIANGLES` triangles, expected (:func:`index_problem`)
            or counted (remembered: the count is not made twice).
    """
    if not (math.isfinite(eps_rad) and eps_rad > 0):
        raise ValueError(f"eps_rad must be a positive angle, got {eps_rad}")
    vectors = np.asarray(vectors, np.float64)
    max_side = frame_pair_angle(camera)
    digest = hashlib.sha1(np.ascontiguousarray(vectors, np.float32).tobytes()).hexdigest()[:16]
    key = f"{digest}-{max_side:.6e}-{eps_rad:.6e}"
    if key not in _MEMO:
        try:
            problem = index_problem(vectors.shape[0], camera)
            if problem:
                raise TooManyTriangles(problem)
            _MEMO[key] = _cached_build(vectors, camera, max_side, eps_rad, key)
        except TooManyTriangles as refusal:
            _MEMO[key] = refusal
    if isinstance(_MEMO[key], TooManyTriangles):
        raise _MEMO[key]
    return _MEMO[key]


def _cached_build(vectors: np.ndarray, camera, max_side: float, eps_rad: float, key: str) -> TriangleIndex:
    """:func:`_build`, kept on disk under the cache directory: a deep catalog's index takes seconds to
    count (3.3 M triangles: 5 s on 2 cores), which every process would otherwise pay again."""
    def build() -> dict[str, np.ndarray]:
        index = _build(vectors, camera, max_side, eps_rad, key)
        return {"codes": np.asarray(index.codes), "stars": np.asarray(index.stars),
                "sides": np.asarray(index.sides), "cell_rad": np.float64(index.cell_rad),
                "n_cells": np.int64(index.n_cells), "run": np.int64(index.run)}

    arrays, _ = load_or_build(cache_dir() / "triangles" / f"triangles-v{_FORMAT}-{key}.npz", build)
    return TriangleIndex(codes=jnp.asarray(arrays["codes"]), stars=jnp.asarray(arrays["stars"]),
                         sides=jnp.asarray(arrays["sides"]), cell_rad=float(arrays["cell_rad"]),
                         n_cells=int(arrays["n_cells"]), run=int(arrays["run"]), key=key)


def _build(vectors: np.ndarray, camera, max_side: float, eps_rad: float, key: str) -> TriangleIndex:
    abc = _triangles(vectors, max_side, camera)
    va, vb, vc = vectors[abc[:, 0]], vectors[abc[:, 1]], vectors[abc[:, 2]]
    opposite = np.stack([angle_between_host(vb, vc), angle_between_host(va, vc),  # opposite a, b, c
                         angle_between_host(va, vb)], 1)
    order = np.argsort(opposite, axis=1, kind="stable")
    sides = np.take_along_axis(opposite, order, 1)
    stars = np.take_along_axis(abc, order, 1)
    cell = 2.0 * eps_rad
    n_cells = int(math.floor(max_side / cell)) + 2
    if n_cells * n_cells >= 2**31:
        raise ValueError(f"a tolerance of {eps_rad:.3e} rad cuts a {camera.name} frame into too many cells")
    c1, c2 = np.floor(sides[:, 0] / cell).astype(np.int64), np.floor(sides[:, 1] / cell).astype(np.int64)
    codes = c1 * n_cells + c2
    by_code = np.argsort(codes, kind="stable")
    codes, stars, sides = codes[by_code], stars[by_code], sides[by_code]
    # a query reads two adjacent cells of one column: the most triangles any such pair holds
    # (counted over the occupied cells only: the n_cells² grid can be large)
    occupied, counts = np.unique(codes, return_counts=True)
    after = np.searchsorted(occupied, occupied + 1)
    same_column = (after < occupied.size) & ((occupied + 1) % n_cells != 0)
    has_next = same_column & (occupied[np.minimum(after, occupied.size - 1)] == occupied + 1)
    pair = counts + np.where(has_next, counts[np.minimum(after, occupied.size - 1)], 0)
    run = int(max(1, pair.max())) if pair.size else 1
    return TriangleIndex(codes=jnp.asarray(codes.astype(np.int32)), stars=jnp.asarray(stars),
                         sides=jnp.asarray(sides.astype(np.float32)), cell_rad=cell, n_cells=n_cells,
                         run=run, key=key)


def query(index: TriangleIndex, sides, eps_rad):
    """Catalog triangles whose sorted sides are within ``eps_rad`` of ``sides`` (jit-able, fixed size).

    Args:
        index: the :class:`TriangleIndex` (``eps_rad`` at most its build tolerance).
        sides: (3,) float32 the measured sides, ascending (rad).
        eps_rad: () the tolerance (rad).

    Returns:
        ``(slots, match)``: (2·run,) int32 indices into the index's arrays and (2·run,) bool, True
        where the triangle's three sides are within ``eps_rad``.
    """
    cell = index.cell_rad
    last = index.n_cells - 1
    lo1 = jnp.clip(jnp.floor((sides[0] - eps_rad) / cell), 0, last).astype(jnp.int32)
    hi1 = jnp.clip(jnp.floor((sides[0] + eps_rad) / cell), 0, last).astype(jnp.int32)
    lo2 = jnp.clip(jnp.floor((sides[1] - eps_rad) / cell), 0, last).astype(jnp.int32)
    hi2 = jnp.clip(jnp.floor((sides[1] + eps_rad) / cell), 0, last).astype(jnp.int32)
    columns = jnp.stack([lo1, hi1])
    start = jnp.searchsorted(index.codes, columns * index.n_cells + lo2, side="left", method="scan")
    stop = jnp.searchsorted(index.codes, columns * index.n_cells + hi2, side="right", method="scan")
    stop = stop.at[1].set(jnp.where(hi1 == lo1, start[1], stop[1]))  # one column: read it once
    slots = start[:, None] + jnp.arange(index.run, dtype=jnp.int32)[None, :]
    live = slots < stop[:, None]
    slots = jnp.minimum(slots, index.size - 1).reshape(-1)
    near = jnp.all(jnp.abs(index.sides[slots] - sides[None, :]) <= eps_rad, axis=1)
    return slots, live.reshape(-1) & near
