"""Scale-out past one machine: each JAX process takes its share of a sweep's scenes.

With ``jax.distributed.initialize(...)`` called first (one process per host, or several on one
machine), :func:`share` gives this process a contiguous block of the global scene rows and
:func:`gather` assembles every process's per-scene arrays once, in row order, on every process.
Scenes are simulated in full by every process (cheap: about 300,000 scenes/s on 2 cores) so that
each process's block is exactly the rows a one-process run would draw; an algorithm's result for a
scene does not depend on the rest of its batch (the contract test), so the gathered table equals
the one-process table bit for bit. Within a process the batch is sharded over its local devices.
"""

from __future__ import annotations

from collections.abc import Mapping

import jax
import numpy as np

__all__ = ["gather", "initialize", "process_count", "share"]


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, *, timeout_s: int = 300) -> None:
    """Join a multi-process run (``jax.distributed.initialize``); call before any JAX computation.

    On a cluster whose scheduler JAX recognises (SLURM, Open MPI, Cloud TPU) every argument may be
    left out: JAX reads them from the environment. Elsewhere give all three, the same coordinator
    (``host:port`` of process 0) to every process.

    Raises:
        ValueError: only some of the three arguments given.
    """
    given = [a is not None for a in (coordinator, num_processes, process_id)]
    if any(given) and not all(given):
        raise ValueError("give --coordinator, --num-processes and --process-id together (or none, "
                         "on a cluster JAX detects)")
    kwargs = {"initialization_timeout": timeout_s}
    if all(given):
        kwargs.update(coordinator_address=coordinator, num_processes=num_processes,
                      process_id=process_id)
    jax.distributed.initialize(**kwargs)


def process_count() -> int:
    """How many JAX processes take part (1 without ``jax.distributed``)."""
    return jax.process_count()


def share(n_rows: int, index: int | None = None, count: int | None = None) -> slice:
    """This process's contiguous block of ``n_rows`` rows (sizes differ by at most one).

    Args:
        n_rows: global rows. index, count: process index and count (default: JAX's).
    """
    index = jax.process_index() if index is None else index
    count = jax.process_count() if count is None else count
    bounds = np.linspace(0, n_rows, count + 1).round().astype(int)
    return slice(int(bounds[index]), int(bounds[index + 1]))


def gather(arrays: Mapping[str, np.ndarray], n_rows: int) -> dict[str, np.ndarray]:
    """Every process's ``(rows_i, ...)`` arrays joined into ``(n_rows, ...)`` arrays, on every process.

    One process: returned as they are. Several: each block is padded to the largest share and
    all-gathered with :func:`jax.experimental.multihost_utils.process_allgather` (the blocks come
    back in process order, which is row order by :func:`share`).
    """
    count = jax.process_count()
    if count == 1:
        return {k: np.asarray(v) for k, v in arrays.items()}
    from jax.experimental import multihost_utils

    sizes = [share(n_rows, i, count).stop - share(n_rows, i, count).start for i in range(count)]
    width = max(sizes)
    out = {}
    for name, value in arrays.items():
        value = np.asarray(value)
        pad = np.zeros((width - value.shape[0],) + value.shape[1:], value.dtype)
        stacked = np.asarray(multihost_utils.process_allgather(np.concatenate([value, pad])))
        out[name] = np.concatenate([stacked[i, :sizes[i]] for i in range(count)])
    return out
