"""Keep a long-running process clear of Linux's limit on memory mappings.

Each compiled XLA CPU executable holds about six memory mappings, and JAX keeps every executable
it compiled. A process that compiles thousands of kernels (a long sweep, a notebook session, the
test suite, the focal-length retries on batches of many sizes) reaches ``vm.max_map_count``
(65,530 by default): XLA's next compile then fails to map its code ("LLVM ERROR: Unable to
allocate section memory", or a C++ exception that crashed the unwinder). :func:`relieve` drops
JAX's compiled caches once the process holds more than a share of that limit; the kernels still
needed are compiled again (seconds), which is better than an abort.
"""

from __future__ import annotations

import gc

import jax

from jstarid.runtime.program_store import forget_programs

__all__ = ["map_count", "map_limit", "relieve"]

SHARE = 0.7  # drop the caches past this share of the limit
DEFAULT_LIMIT = 65_530  # Linux's default vm.max_map_count


def map_count() -> int:
    """Memory mappings this process holds (0 where ``/proc`` is not there: no such limit)."""
    try:
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


def map_limit() -> int:
    """The system's ``vm.max_map_count`` (the Linux default where it cannot be read)."""
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return DEFAULT_LIMIT


def relieve(limit: int | None = None) -> bool:
    """Drop JAX's compiled caches if this process holds more than ``limit`` memory mappings.

    Args:
        limit: mappings allowed; ``None``: :data:`SHARE` × :func:`map_limit`.

    Returns:
        Whether the caches were dropped.
    """
    limit = int(SHARE * map_limit()) if limit is None else int(limit)
    if map_count() <= limit:
        return False
    jax.clear_caches()
    forget_programs()
    gc.collect()
    return True
