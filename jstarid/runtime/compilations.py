"""Count the XLA programs a piece of code compiles, and the time XLA spends compiling them.

A sweep meets fresh scenes every call; once it has met a batch size, identifying more scenes of
that size and settings should compile nothing. :class:`CountCompilations` measures that (the
compile-budget benchmark, ``experiments/bench_compile.py``, and the tests that hold an algorithm
to it): it listens to ``jax.monitoring``'s backend-compile events, which JAX sends once per program
XLA compiles (a program loaded from JAX's persistent cache or jstarid's program store sends none).

    with CountCompilations() as count:
        algo.identify(db, scenes, config)
    count.programs, count.seconds
"""

from __future__ import annotations

import jax

__all__ = ["BACKEND_COMPILE_EVENT", "CountCompilations"]

#: the duration event JAX records for every program XLA compiles
BACKEND_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"


class CountCompilations:
    """Context manager: ``programs`` (int) XLA compiled inside it and ``seconds`` (float) it took.

    The counts are live while the block runs and final after it. Every thread's compilations count
    (JAX's events are process-wide).
    """

    def __init__(self):
        self.programs = 0
        self.seconds = 0.0

    def _on_duration(self, event: str, duration_secs: float, **_) -> None:
        if event == BACKEND_COMPILE_EVENT:
            self.programs += 1
            self.seconds += float(duration_secs)

    def __enter__(self) -> CountCompilations:
        jax.monitoring.register_event_duration_secs_listener(self._on_duration)
        return self

    def __exit__(self, *exc) -> None:
        jax.monitoring.unregister_event_duration_listener(self._on_duration)
