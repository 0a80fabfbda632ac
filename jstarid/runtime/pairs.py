"""Pair kernels: one compiled kernel over many (scene, candidate) pairs of a few static sizes.

A search that tests candidates against each scene (SGM's spectral matching and its bounds, one per
image graph and database graph) has a flat list of pairs whose work depends on their sizes. The
pairs are grouped by their static sizes (e.g. the two graphs' padded vertex counts), each group is
cut into calls that fit a memory budget and padded to a power of two (:func:`_batches`), and each
call is split over every device (:func:`run_pairs`, on :func:`~jstarid.runtime.run_calls`).
Inside a call the kernel runs the pairs one after another and skips the padding
(:func:`skip_padding`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence

import jax
import numpy as np

from jstarid.runtime.batching import Call, run_calls
from jstarid.runtime.padding import coarse_size

__all__ = ["MIN_CALL_PAIRS", "run_pairs", "skip_padding"]

MIN_CALL_PAIRS = 64  # smallest compiled pair count of a kernel call
COARSE_PAIRS = 1024  # largest pair count padded in coarse steps (64, 256, 1,024); powers of two above


def skip_padding(fn, live, args, dead):
    """``lax.map`` of ``fn(*args_n)`` over pairs n, returning ``dead`` where ``live`` is False (on CPU the
    ``lax.cond`` runs one branch only, so padding costs nothing).

    Args:
        fn: ``fn(*args_n)`` → a pytree, one pair's result.
        live: (N,) bool, the real pairs.
        args: tuple of (N, …) arrays, one row per pair.
        dead: the result of a padding pair (the same pytree structure, shapes and dtypes as ``fn``'s).

    Returns:
        The pytree of (N, …) results.
    """
    def one(xs):
        return jax.lax.cond(xs[0], lambda a: fn(*a), lambda a: dead, xs[1:])

    return jax.lax.map(one, (live, *args))


def _batches(n_pairs: int, per_pair_bytes: int, budget_bytes: int) -> Iterator[tuple[int, int, int]]:
    """Slices ``(lo, hi, padded)`` of ≤ the budget, each padded to :func:`~.padding.coarse_size` ≥
    :data:`MIN_CALL_PAIRS` (64, 256, 1,024, then powers of two up to the budget's call).

    A few sizes bound the compilations per kernel, so a fresh batch's groups meet sizes compiled
    already; the floor of 64 merges the small sizes of a small batch into one compilation
    (docs/design/sgm.md). Padding pairs are skipped by the kernels.
    """
    cap = max(MIN_CALL_PAIRS,
              1 << int(math.floor(math.log2(max(budget_bytes // max(per_pair_bytes, 1), 16)))))
    for lo in range(0, n_pairs, cap):
        hi = min(lo + cap, n_pairs)
        yield lo, hi, coarse_size(hi - lo, MIN_CALL_PAIRS, min(cap, COARSE_PAIRS))


def run_pairs(kernel, key_sizes, image, n_i, scene, cand, per_pair_bytes: Callable[..., int], budget: int,
              size_names: Sequence[str], out_tails: Sequence[tuple], tables, **static) -> list[np.ndarray]:
    """Run a pair kernel over flat (scene, candidate) pairs grouped by static size, each call's
    pairs split over every device (:func:`jstarid.runtime.map_batch`; with
    ``--xla_force_host_platform_device_count=n`` that uses n CPU cores).

    Args:
        kernel: a module-level function called as ``kernel(image_i, n_i, cand, *tables, **static,
            **sizes)`` with the scenes' square table cut to the group's first size k
            (``image[scene, :k, :k]``); calls are filled to a power of two with padding pairs
            (``cand`` −1) that the kernel must skip or give a harmless value.
        key_sizes: (N, k) int static sizes of each pair (e.g. SGM's (p, q) or (r, skip)); pairs are
            grouped by row.
        image: (B, K, K) per-scene NumPy table the kernel reads (e.g. SGM's adjacencies, or sorted
            rows). n_i: (B,) the scenes' counts (e.g. vertices).
        scene, cand: (N,) int scene row and candidate row (into ``tables``) of each pair.
        per_pair_bytes: function of the sizes → bytes one pair needs inside the kernel.
        budget: bytes per call. size_names: the kernel's static keyword for each column of ``key_sizes``.
        out_tails: trailing shape of each output (a per-vertex axis, returned at the group's size, is
            given as K and padded with −1).
        tables: tuple of arrays every pair reads, ideally already on every device
            (:func:`~jstarid.runtime.on_every_device`).
        **static: the kernel's other (hashable) keyword arguments.

    Returns:
        List of the kernel outputs in pair order (NumPy arrays of shape (N,) + tail).
    """
    n_dev = jax.local_device_count()
    groups = {}
    for idx, key in enumerate(map(tuple, key_sizes)):
        groups.setdefault(key, []).append(idx)
    calls = []
    for sizes, members in groups.items():
        members = np.asarray(members)
        for lo, hi, padded in _batches(members.size, per_pair_bytes(*sizes), budget):
            # the real pairs are dealt round-robin to the devices' equal slices so each gets its share
            calls.append(Call(rows=members[lo:hi], size=padded, slots=_spread(hi - lo, padded, n_dev),
                              static=tuple(zip(size_names, sizes, strict=True))))

    def args(call):
        # padding pairs repeat the call's first scene with candidate −1 (the kernels skip them)
        k = dict(call.static)[size_names[0]]
        fill = np.full(call.size, call.rows[0])
        fill[call.slots] = call.rows
        cand_fill = np.full(call.size, -1, np.int32)
        cand_fill[call.slots] = cand[call.rows]
        # host arrays go straight to their devices' slices (no staging copy on one device)
        return (np.ascontiguousarray(image[scene[fill], :k, :k]), n_i[scene[fill]].astype(np.int32),
                cand_fill)

    return run_calls(kernel, calls, args, tuple(tables), static=static, n_rows=scene.size,
                     tails=out_tails, fills=[-1] * len(out_tails))


def _spread(n: int, padded: int, n_dev: int) -> np.ndarray:
    """Slots (n,) in a call of ``padded`` pairs for n real pairs: k-th pair → device k mod n_dev."""
    if n_dev <= 1 or padded % n_dev:
        return np.arange(n)
    k = np.arange(n)
    return (k % n_dev) * (padded // n_dev) + k // n_dev
