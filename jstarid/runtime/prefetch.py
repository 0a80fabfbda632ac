"""Make the next items of a sequence while the caller works on the current one.

A training loop alternates two kinds of compiled call: drawing a batch (the simulator: gathers,
sorts and many small ops that leave cores idle) and the optimiser step (large matmuls). Run one
after the other, the cores idle through part of each. :func:`prefetch` draws the items in a
background thread, ``depth`` ahead, so XLA runs the two at once; JAX releases the GIL while a
computation runs. The items and their order are those of ``[make(i) for i in indices]``: each is a
pure function of its index, so the thread changes timing only, never a result.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

__all__ = ["prefetch"]

T = TypeVar("T")

_DONE = object()


class _Failure:
    def __init__(self, error: BaseException):
        self.error = error


def prefetch(make: Callable[[int], T], indices: Iterable[int], depth: int = 2) -> Iterator[T]:
    """``make(i)`` for each ``i`` of ``indices``, in order, drawn up to ``depth`` items ahead.

    Args:
        make: item of an index; called from one background thread, in the order of ``indices``.
        indices: the indices (e.g. ``range(start, steps)``).
        depth: items made ahead of the consumer (≥ 1); each holds its memory until consumed.

    Yields:
        ``make(i)`` in the order of ``indices``. An exception raised by ``make`` is raised here, at
        the item it would have produced. Closing the iterator early (``break``, an exception in the
        loop body) stops the thread after the item it is making.

    Raises:
        ValueError: ``depth`` < 1.
    """
    if int(depth) < 1:
        raise ValueError(f"depth must be at least 1, got {depth!r}")
    items: queue.Queue = queue.Queue(maxsize=int(depth))
    stop = threading.Event()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                items.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce():
        try:
            for i in indices:
                if stop.is_set() or not put(make(i)):
                    return
        except BaseException as error:  # handed to the consumer, raised there
            put(_Failure(error))
            return
        put(_DONE)

    worker = threading.Thread(target=produce, name="jstarid-prefetch", daemon=True)
    worker.start()
    try:
        while True:
            item = items.get()
            if item is _DONE:
                return
            if isinstance(item, _Failure):
                raise item.error
            yield item
    finally:
        stop.set()
        worker.join()
