"""Mortari's k-vector: O(1) range search on a static sorted array, pure ``jnp`` and jit-able.

For sorted values ``s[0] ≤ … ≤ s[n−1]`` the k-vector stores, for the straight line
``z(j) = y0 + m·j`` (``j = 0 … n``) that runs from just below ``s[0]`` to just above ``s[n−1]``, the
counts ``k[j] = #{i : s[i] ≤ z(j)}``. A query value ``a`` falls between two lines whose index is one
arithmetic step (``(a − y0) / m``) away, so the position of ``a`` in ``s`` is bracketed by two k-vector
entries; a short fixed-length binary search inside that bracket (at most a few elements wide for
reasonably spread data) makes the answer exact. Mortari & Neta, "k-vector range searching techniques",
AAS 00-128 (2000).

Building happens on the host (NumPy); :func:`range_search` is a pure function of device arrays and can
be vmapped over queries.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["KVector", "build_kvector", "range_search"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class KVector:
    """A k-vector over sorted values.

    Attributes:
        values: (n,) sorted values (any unit; float32 on device).
        k: (n + 1,) int32 counts ``k[j] = #{i : values[i] ≤ y0 + slope·j}``.
        y0: () line intercept, slightly below ``values[0]``.
        slope: () line slope (> 0).
        n_iter: static number of binary-search steps that makes the bracketed answer exact.
    """

    values: jax.Array
    k: jax.Array
    y0: jax.Array
    slope: jax.Array
    n_iter: int = dataclasses.field(metadata=dict(static=True), default=1)

    @property
    def size(self) -> int:
        return int(self.values.shape[0])


def build_kvector(values) -> tuple[KVector, np.ndarray]:
    """Sort ``values`` and build their k-vector (host side).

    Args:
        values: (n,) finite values, n ≥ 1.

    Returns:
        ``(kvector, order)``: the :class:`KVector` over ``values[order]`` (ascending, float32) and the
        (n,) int64 permutation ``order`` that sorts ``values``.

    Raises:
        ValueError: empty or non-finite input.
    """
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    if values.size == 0 or not np.all(np.isfinite(values)):
        raise ValueError("k-vector needs a non-empty array of finite values")
    order = np.argsort(values, kind="stable")
    s = values[order].astype(np.float32)
    n = s.size
    lo, hi = float(s[0]), float(s[-1])
    # the line starts/ends a hair outside the data so that z(0) < s[0] and z(n) > s[n−1]
    xi = 1e-6 * max(abs(lo), abs(hi), 1.0) + 1e-6 * (hi - lo)
    y0 = lo - xi
    slope = (hi - lo + 2.0 * xi) / n
    z = y0 + slope * np.arange(n + 1, dtype=np.float64)
    k = np.searchsorted(s.astype(np.float64), z, side="right").astype(np.int32)
    # brackets span up to 4 line steps (see _bracket) → bound the elements inside one bracket
    width = int(np.max(k[np.minimum(np.arange(n + 1) + 4, n)] - k)) + 2
    n_iter = max(1, math.ceil(math.log2(width + 1)) + 1)
    kv = KVector(values=jnp.asarray(s), k=jnp.asarray(k), y0=jnp.float32(y0),
                 slope=jnp.float32(slope), n_iter=n_iter)
    return kv, order


def _bracket(kv: KVector, a):
    """Indices ``(lo, hi)`` into ``values`` with every element < lo below ``a`` and ≥ hi above it."""
    n = kv.size
    j = jnp.floor((a - kv.y0) / kv.slope).astype(jnp.int32)
    # one line step of slack on each side absorbs rounding in (a − y0) / slope
    lo = kv.k[jnp.clip(j - 1, 0, n)]
    hi = kv.k[jnp.clip(j + 2, 0, n)]
    # queries outside the data range
    lo = jnp.where(a > kv.values[n - 1], n, lo)
    hi = jnp.where(a < kv.values[0], 0, hi)
    return lo, jnp.maximum(hi, lo)


def _search(kv: KVector, a, strict: bool):
    """First index i with ``values[i] > a`` (strict) or ``values[i] ≥ a``, exact."""
    n = kv.size
    lo, hi = _bracket(kv, a)

    def body(_, carry):
        lo, hi = carry
        active = lo < hi
        mid = (lo + hi) // 2
        v = kv.values[jnp.clip(mid, 0, n - 1)]
        pred = (v > a) if strict else (v >= a)
        new_hi = jnp.where(active & pred, mid, hi)
        new_lo = jnp.where(active & ~pred, mid + 1, lo)
        return new_lo, new_hi

    lo, hi = jax.lax.fori_loop(0, kv.n_iter, body, (lo, hi))
    return lo


def range_search(kv: KVector, lower, upper):
    """Indices of the sorted values inside the closed interval ``[lower, upper]``.

    Args:
        kv: the k-vector.
        lower: () scalar lower bound (same unit as the values).
        upper: () scalar upper bound.

    Returns:
        ``(start, stop)`` int32 scalars: ``values[start:stop]`` are exactly the values in
        ``[lower, upper]`` (``start == stop`` when none; equal to ``np.searchsorted(values, lower,
        "left")`` and ``np.searchsorted(values, upper, "right")``).
    """
    lower = jnp.asarray(lower, kv.values.dtype)
    upper = jnp.asarray(upper, kv.values.dtype)
    start = _search(kv, lower, strict=False)
    stop = _search(kv, upper, strict=True)
    return start.astype(jnp.int32), jnp.maximum(stop, start).astype(jnp.int32)
