"""Identify time without compilation: wall time minus JAX's own tracing and compile events.

A sweep meets new array shapes at every level (SGM compiles one kernel per graph-size bucket and
pair count, RpNet's retries widen their buffers), so a level's first call would count compilation
as identification. JAX reports how long it spends tracing, lowering and compiling (or loading a
compiled program from the on-disk cache) through :mod:`jax.monitoring`; :class:`CompileClock` adds
those durations up, and the engine subtracts them from each chunk's wall time. What remains is the
steady-state time of the call (dispatch and host work included), without running anything twice.
"""

from __future__ import annotations

import time

import jax

__all__ = ["CompileClock", "COMPILE_EVENTS"]

# the jax.monitoring duration events that are compilation (jax 0.4.30 – 0.10)
COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
                  "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")

_total = [0.0]
_registered = [False]


def _listen(event: str, duration: float, **_) -> None:
    if event in COMPILE_EVENTS:
        _total[0] += duration


class CompileClock:
    """Wall and compile seconds of a ``with`` block (``wall``, ``compile``, ``steady`` after it).

    Block on the block's results inside it (``jax.block_until_ready``): JAX dispatches
    asynchronously.
    """

    def __enter__(self) -> CompileClock:
        if not _registered[0]:  # one process-wide listener (jax.monitoring cannot remove one)
            jax.monitoring.register_event_duration_secs_listener(_listen)
            _registered[0] = True
        self._start, self._compile0 = time.perf_counter(), _total[0]
        return self

    def __exit__(self, *exc) -> None:
        self.wall = time.perf_counter() - self._start
        self.compile = min(_total[0] - self._compile0, self.wall)
        self.steady = self.wall - self.compile
