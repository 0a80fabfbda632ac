"""The catalog's star pairs that fit in one frame, sorted by angle (shared by the pair-angle
baselines: geometric voting and the pyramid).

Built on the host in float64 (each angle exact before it is stored as float32), searched on the
device with Mortari's k-vector (:mod:`jstarid.geometry.kvector`).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

__all__ = ["MAX_PAIRS", "cached_pair_table", "expected_pairs", "frame_pair_angle", "pair_table",
           "table_problem", "widest_window"]

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
        # atan2(|u × v|, u · v): full precision at small separations (jstarid.geometry.angles)
        angles.append(np.arctan2(np.linalg.norm(np.cross(u, v), axis=1), np.sum(u * v, axis=1)))
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
    there (atomically: several processes may build it at once); ``path=None``: no cache."""
    from jstarid.catalog import temporary_path

    if path is not None and Path(path).exists():
        with np.load(path) as data:
            return data["angles"], data["pairs"]
    t0 = time.perf_counter()
    angles, pairs = pair_table(vectors, max_angle_rad, progress=progress, desc=desc)
    if path is not None:
        tmp = temporary_path(path)
        np.savez(tmp, angles=angles, pairs=pairs, build_seconds=time.perf_counter() - t0)
        tmp.replace(path)
    return angles, pairs
