"""The catalog's star pairs that fit in one frame, sorted by angle (shared by the pair-angle
baselines: geometric voting and the pyramid).

Built on the host in float64 (each angle exact before it is stored as float32), searched on the
device with Mortari's k-vector (:mod:`jstarid.geometry.kvector`). :func:`pair_database` is the part
of both baselines' ``build_database`` they share (the size check, the cached table and its k-vector),
:func:`pair_table_first_use` their ``first_use``.
"""

from __future__ import annotations

import functools
import math
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jstarid.catalog import cache_dir, load_or_build, read_arrays
from jstarid.geometry.angles import angle_between_host
from jstarid.geometry.kvector import KVector, build_kvector

__all__ = ["MAX_PAIRS", "PairTable", "cached_pair_table", "expected_pairs", "frame_pair_angle",
           "pair_database", "pair_table", "pair_table_first_use", "pair_table_path", "table_problem",
           "widest_window"]

_ROWS_PER_STEP = 1024  # catalog rows per vectorized step of the pair search
#: Largest pair table (pairs): 12 bytes a pair on disk and on the device.
MAX_PAIRS = 40_000_000


def frame_pair_angle(camera) -> float:
    """Largest angle (rad) between two detections of one frame of ``camera``: its diagonal, plus 1 %
    for a lens whose focal length differs slightly from the nominal one."""
    return 2.0 * camera.half_diagonal_rad * 1.01


def table_problem(name: str, catalog, camera) -> str | None:
    """One line saying why the pair table of ``catalog`` for ``camera`` is too large
    (:data:`MAX_PAIRS`), or ``None`` (also when ``catalog`` is ``None``)."""
    if catalog is None:
        return None
    reach = frame_pair_angle(camera)
    pairs = expected_pairs(len(catalog), reach)
    if pairs > MAX_PAIRS:
        return (f"{name}: {len(catalog):,} catalog stars within a {math.degrees(reach):.1f}° "
                f"diagonal make ≈ {pairs:,.0f} pairs (more than {MAX_PAIRS:,}); use a brighter catalog")
    return None


def expected_pairs(n_stars: int, max_angle_rad: float) -> float:
    """Pairs among ``n_stars`` stars spread evenly over the sky that lie within ``max_angle_rad``."""
    return 0.5 * n_stars * (n_stars - 1) * (1.0 - math.cos(max_angle_rad)) / 2.0


def pair_table(vectors: np.ndarray, max_angle_rad: float, *, progress: bool = False,
               desc: str = "pair table") -> tuple[np.ndarray, np.ndarray]:
    """Every pair i < j of unit vectors within ``max_angle_rad``, sorted by angle.

    Args:
        vectors: (S, 3) float64 unit vectors (ICRS; row = catalog row).
        max_angle_rad: largest angle kept (rad).
        progress: a progress bar over blocks of rows.
        desc: its label.

    Returns:
        ``(angles, rows)``: (P,) float32 angles (rad), ascending, and (P, 2) int32 the two rows of
        each pair (first < second).
    """
    from tqdm.auto import tqdm

    vectors = np.asarray(vectors, np.float64)
    cos_max = math.cos(max_angle_rad)
    angles, rows = [], []
    for lo in tqdm(range(0, vectors.shape[0], _ROWS_PER_STEP), desc=desc, unit="step", disable=not progress):
        dots = np.matmul(vectors[lo:lo + _ROWS_PER_STEP], vectors.T)
        i, j = np.nonzero(dots >= cos_max)
        i = i + lo
        keep = j > i
        i, j = i[keep], j[keep]
        u, v = vectors[i], vectors[j]
        angles.append(angle_between_host(u, v))  # full precision at small separations
        rows.append(np.stack([i, j], axis=1).astype(np.int32))
    angles = np.concatenate(angles) if angles else np.zeros((0,))
    rows = np.concatenate(rows) if rows else np.zeros((0, 2), np.int32)
    order = np.argsort(angles, kind="stable")
    return angles[order].astype(np.float32), rows[order]


def widest_window(sorted_angles: np.ndarray, eps_rad: float, upto_rad: float | None = None) -> int:
    """The most pairs any window ``[θ − ε, θ + ε]`` of the sorted angles can hold (≥ 1): a static
    buffer width that no range search can exceed (a hair of slack for float32 query bounds).
    ``upto_rad``: only windows with θ ≤ ``upto_rad``."""
    s = np.asarray(sorted_angles, np.float64)
    if upto_rad is not None:
        s = s[: np.searchsorted(s, upto_rad + 2.0 * eps_rad, side="right")]
    if s.size == 0:
        return 1
    stop = np.searchsorted(s, s + 2.0 * eps_rad * (1 + 1e-5) + 1e-7, side="right")
    return int(max(1, np.max(stop - np.arange(s.size))))


def cached_pair_table(path: Path | None, vectors: np.ndarray, max_angle_rad: float, *, progress: bool = False,
                      desc: str = "pair table") -> tuple[np.ndarray, np.ndarray]:
    """:func:`pair_table`, read from ``path`` (an ``.npz``) when it exists, else built and written
    there (:func:`jstarid.catalog.load_or_build`: atomically, as several processes may build it at
    once); ``path=None``: no cache."""
    def build():
        t0 = time.perf_counter()
        angles, pairs = pair_table(vectors, max_angle_rad, progress=progress, desc=desc)
        return {"angles": angles, "pairs": pairs, "build_seconds": time.perf_counter() - t0}

    arrays, _ = load_or_build(path, build, load=functools.partial(read_arrays, names=("angles", "pairs")))
    return arrays["angles"], arrays["pairs"]


def pair_table_path(name: str, key: str) -> Path:
    """The cache file of baseline ``name``'s pair table with cache key ``key``."""
    return cache_dir() / f"{name}-{key}.npz"


class PairTable(NamedTuple):
    """A pair-angle baseline's table (host arrays) and its k-vector (:func:`pair_database`).

    Attributes:
        angles: (P,) float32 pair angles (rad), ascending.
        pairs: (P, 2) int32 catalog rows of each pair, in that order (first < second).
        vectors: (S, 3) float64 ICRS unit vectors of the catalog (row = catalog row).
        kvector: :class:`~jstarid.geometry.kvector.KVector` over ``angles``.
    """

    angles: np.ndarray
    pairs: np.ndarray
    vectors: np.ndarray
    kvector: KVector


def pair_database(name: str, key: str, catalog, camera, *, use_cache: bool = True,
                  progress: bool = True) -> PairTable:
    """The pair table of baseline ``name`` for ``catalog`` and ``camera``, read from its cache file
    (:func:`pair_table_path`) or built (and cached), with the k-vector over its angles.

    Args:
        name: the algorithm's registry name (its cache file, progress bar and messages).
        key: the database's cache key (:func:`jstarid.algorithms.base.cache_key`).
        catalog: :class:`~jstarid.catalog.Catalog` (the identification catalog).
        camera: :class:`~jstarid.camera.Camera`; pairs up to :func:`frame_pair_angle` are kept.
        use_cache: read/write the cache file.
        progress: a progress bar while building.

    Returns:
        The :class:`PairTable`.

    Raises:
        ValueError: the table would exceed :data:`MAX_PAIRS` (:func:`table_problem`), or no two
            catalog stars fit in one frame.
    """
    problem = table_problem(name, catalog, camera)
    if problem:
        raise ValueError(problem)
    vectors = np.asarray(catalog.unit_vectors, np.float64)
    angles, pairs = cached_pair_table(pair_table_path(name, key) if use_cache else None, vectors,
                                      frame_pair_angle(camera), progress=progress, desc=f"{name} pair table")
    if angles.size == 0:
        raise ValueError(f"{name}: no two catalog stars fit in one frame of this camera")
    kvector, _ = build_kvector(angles)  # already sorted: the order is the identity
    return PairTable(angles, pairs, vectors, kvector)


def pair_table_first_use(name: str, key: str, catalog, camera) -> tuple[str, float] | None:
    """What :func:`pair_database` builds for baseline ``name`` and about how long it takes on a
    2-core CPU (s, about 1 s per million pairs); ``None`` when it is cached."""
    if pair_table_path(name, key).exists():
        return None
    pairs = expected_pairs(len(catalog), frame_pair_angle(camera))
    return f"{name} pair table for {camera.name} (≈ {pairs / 1e6:.1f} M pairs)", max(2.0, pairs / 1e6)
