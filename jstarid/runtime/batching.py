"""Running a kernel over a batch in calls of a few static sizes: plan, pad, dispatch, collect.

Every batched stage of jstarid has the same host shell around a jit-compiled, sharded kernel: the
batch (scenes, or SGM's image–candidate pairs) is cut into calls whose sizes come from a small set
(so a handful of compilations serve any batch), each call is padded to its size, split over the
devices (:func:`~jstarid.runtime.map_batch`), every call is dispatched before any result is read
back (the devices work on one call while the host prepares the next), and the results are written
back to the rows they belong to. A kernel that flags an overflow of one of its fixed buffers is run
again on the flagged rows with a larger buffer (:func:`grow_until`). This module is that shell,
written once.

Inside one compiled call the same idea applies to rows of very different sizes:
:func:`map_by_width` sorts the rows by the size they need, cuts them into chunks and runs each
chunk with the smallest of a few widths that holds it.

A :class:`Call` names the batch rows it computes, its padded size, where in the call each real row
sits (``slots``; padding fills the rest) and its own static arguments (e.g. a column width).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.runtime.devices import map_batch
from jstarid.runtime.padding import pad_rows

__all__ = ["Call", "chunk_calls", "grow_until", "map_by_width", "run_calls", "take_rows"]


class Call(NamedTuple):
    """One kernel call of a plan.

    Attributes:
        rows: (n,) int batch rows the call computes.
        size: the call's (static) batch size, ≥ n; the other ``size − n`` entries are padding.
        slots: (n,) int position of each real row inside the call (default ``arange(n)``).
        static: the call's own static keyword arguments, as sorted ``(name, value)`` items.
    """

    rows: np.ndarray
    size: int
    slots: np.ndarray
    static: tuple = ()


def take_rows(tree, call: Call, *, mode: str = "zeros"):
    """The call's rows of a batched pytree (host arrays), placed at their slots in a padded call.

    Padding entries are zeros (``mode="zeros"``) or copies of the call's first row (``"edge"``).
    """
    def take(a):
        a = np.asarray(a)
        sel = a[call.rows]
        if mode == "zeros":
            out = np.zeros((call.size, *a.shape[1:]), a.dtype)
        else:
            out = np.repeat(sel[:1], call.size, axis=0)
        out[call.slots] = sel
        return out

    return jax.tree.map(take, tree)


def chunk_calls(rows: np.ndarray, chunk: int, *, static: Callable[[np.ndarray], dict] | None = None,
                size: Callable[[int], int] | None = None) -> list[Call]:
    """Consecutive chunks of ``rows`` (in the given order), at most ``chunk`` rows each.

    Args:
        rows: (n,) batch rows, in the order the chunks should take them (sort them first to group
            similar rows, e.g. by their number of detections).
        chunk: rows per call.
        static: function of a chunk's rows → its own static arguments (e.g. ``{"width": 32}``).
        size: function of a chunk's row count → its padded size (default: ``chunk``, one size).

    Returns:
        The calls, in order.
    """
    rows = np.asarray(rows)
    calls = []
    for lo in range(0, rows.size, chunk):
        sel = rows[lo:lo + chunk]
        extra = static(sel) if static is not None else {}
        calls.append(Call(rows=sel, size=chunk if size is None else int(size(sel.size)),
                          slots=np.arange(sel.size), static=tuple(sorted(extra.items()))))
    return calls


def run_calls(kernel, calls: Iterable[Call], args: Callable[[Call], tuple], replicated: tuple = (),
              *, n_rows: int, tails: Sequence[tuple], fills: Sequence[Any], static: dict | None = None,
              out: list[np.ndarray] | None = None, mesh=None) -> list[np.ndarray]:
    """Run ``kernel`` over a plan of calls and collect its outputs into host arrays.

    Args:
        kernel: a module-level function ``kernel(*batched, *replicated, **static)`` returning an
            array or a tuple of arrays, each with the call's batch axis first (see
            :func:`~jstarid.runtime.map_batch`, which splits each call over the devices).
        calls: the plan (:func:`chunk_calls` or any list of :class:`Call`).
        args: function of a call → its batched arguments, ``call.size`` rows each with the real
            rows at ``call.slots`` (:func:`take_rows` does this for whole-row arguments).
        replicated: arguments every device reads whole (tables; place them once with
            :func:`~jstarid.runtime.on_every_device`).
        n_rows: rows of the whole batch.
        tails: trailing shape of each output in the result. An output whose trailing axes come back
            shorter (e.g. a per-detection axis cut to the call's width) fills the leading part.
        fills: value of each output for rows no call computed (and past a short trailing axis).
        static: static keyword arguments shared by every call (merged with each call's own).
        out: existing result arrays to write into (rows not in the plan keep their values).
        mesh: the devices to split each call over (default: all; a one-device mesh runs each call
            whole on that device).

    Returns:
        One NumPy array per kernel output, (n_rows, *tail).
    """
    static = {} if static is None else static
    pending = []
    for call in calls:
        res = map_batch(kernel, args(call), replicated, static={**static, **dict(call.static)}, mesh=mesh)
        pending.append((call, res if isinstance(res, tuple) else (res,)))
    if out is None:
        out = []
        for k, (tail, fill) in enumerate(zip(tails, fills, strict=True)):
            dtype = np.asarray(pending[0][1][k]).dtype if pending else np.asarray(fill).dtype
            out.append(np.full((n_rows, *tail), fill, dtype))
    for call, res in pending:
        for o, r in zip(out, res, strict=True):
            r = np.asarray(r)[call.slots]
            o[(call.rows, *(slice(0, d) for d in r.shape[1:]))] = r
    return out


def grow_until(run: Callable[[int, np.ndarray], np.ndarray], rows: np.ndarray, start: int,
               limit: int) -> int:
    """Retry on overflow: run the rows with a buffer of ``start``, then the flagged ones with a
    doubled buffer, until none is flagged or the buffer reaches ``limit``.

    Args:
        run: ``run(capacity, rows)`` computes ``rows`` with that buffer (writing their results) and
            returns the (k,) bool overflow flags of those rows.
        rows: (n,) the rows to compute.
        start, limit: first and largest buffer.

    Returns:
        The largest buffer used.
    """
    capacity, rows = start, np.asarray(rows)
    while True:
        flagged = np.asarray(run(capacity, rows), bool)
        if not flagged.any() or capacity >= limit:
            return capacity
        rows, capacity = rows[flagged], min(2 * capacity, limit)


def map_by_width(make_fn: Callable[[int], Callable], args, need, widths: Sequence[int], chunk: int):
    """``fn(args)`` over a batch whose rows need different widths, inside jit (traceable).

    The rows are sorted by ``need``, cut into chunks of ``chunk`` rows (the last padded with copies
    of the last row), and each chunk runs ``make_fn(w)`` for the smallest ``w`` in ``widths`` that
    is ≥ its largest need (``lax.switch`` inside ``lax.map``); the results come back in the input
    order. A row in a sparse chunk does not pay for the widest row of the batch.

    Args:
        make_fn: ``width → fn``; ``fn(chunk_args)`` maps a pytree of (chunk, …) arrays to a pytree
            of (chunk, …) arrays, row by row (a row's result must not depend on the other rows).
        args: pytree of (B, …) arrays.
        need: (B,) int width each row needs.
        widths: static ascending widths, the last ≥ every need.
        chunk: static rows per chunk.

    Returns:
        The pytree of (B, …) results.
    """
    b = need.shape[0]
    n_chunks = -(-b // chunk)
    order = pad_rows(jnp.argsort(need), n_chunks * chunk, mode="edge")
    chunked = jax.tree.map(lambda a: a[order].reshape(n_chunks, chunk, *a.shape[1:]), args)
    most = need[order].reshape(n_chunks, chunk).max(axis=1)
    branch = jnp.searchsorted(jnp.asarray(widths), most)  # first width ≥ the chunk's need
    branches = [make_fn(w) for w in widths]
    out = jax.lax.map(lambda a: jax.lax.switch(a[0], branches, a[1]), (branch, chunked))
    flat = jax.tree.map(lambda a: a.reshape(n_chunks * chunk, *a.shape[2:]), out)
    inverse = jnp.argsort(order[:b])
    return jax.tree.map(lambda a: a[:b][inverse], flat)
