"""Give back the memory JAX keeps for staging programs it has already compiled.

JAX keeps, besides each compiled executable, the Python-side artefacts of staging it: the traced
jaxpr and the lowered StableHLO module, and the heap they leave behind stays resident until glibc
is asked to trim it. ``python experiments/probes/program_memory.py`` (SGM's screen kernel at 15 shapes on
2 CPU devices) measures 6.5 MB resident per compiled program, of which the release below frees
2.9 MB and dropping the executable 2.1 MB. SGM compiles over a hundred programs for a batch of
1,000 noisy scenes (kernel × graph-size bucket × pair count); with the release in its search its
benchmark's peak fell from 2,986 to 1,730 MB at σ = 3 px (experiments/RESULTS.md, "Memory:
staging caches released").

:func:`release_staging` drops those caches once enough programs were compiled since the last
release and trims the heap. The executables stay in jit's own dispatch caches, so nothing is
compiled again; a later new shape is traced afresh (as on its first call). Call it at host-level
points between kernel calls (a search round, the end of a batch), never inside a traced function.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import threading

import jax

__all__ = ["programs_staged", "release_staging", "trim_heap"]

MIN_NEW_PROGRAMS = 8  # programs staged since the last release before another one is worth it

_LOWERING_EVENT = "/jax/core/compile/jaxpr_to_mlir_module_duration"
_lock = threading.Lock()
_count = {"staged": 0, "at_release": 0}


def _on_event(event: str, duration_secs: float, **_) -> None:
    if event == _LOWERING_EVENT:
        with _lock:
            _count["staged"] += 1


jax.monitoring.register_event_duration_secs_listener(_on_event)


def programs_staged() -> int:
    """Programs JAX has lowered in this process since jstarid was imported."""
    return _count["staged"]


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim`` (None on other C libraries)."""
    name = ctypes.util.find_library("c")
    try:
        trim = ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None
    if trim is not None:
        trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


def trim_heap() -> bool:
    """Return the C heap's free memory to the OS (glibc ``malloc_trim(0)``, a few ms).

    Returns:
        Whether memory was returned (False also where the C library has no such call).
    """
    trim = _malloc_trim()
    return bool(trim is not None and trim(0))


def _clear_staging_caches() -> bool:
    # jax.clear_caches() would also drop the executables (every kernel compiled again); its first
    # step clears the staging caches but has no public name (jax 0.10). The eager primitives'
    # callables are kept: without them every eager op is traced and lowered again
    try:
        from jax._src import util
    except ImportError:
        return False
    caches = getattr(util, "_caches", None)
    if caches is None:
        return False
    for cache in list(caches):
        if getattr(cache, "__name__", "") != "xla_primitive_callable":
            cache.cache_clear()
    return True


def release_staging(min_new: int = MIN_NEW_PROGRAMS) -> bool:
    """Drop JAX's staging caches and trim the heap if ``min_new`` programs were staged since the
    last release.

    Args:
        min_new: fewest newly staged programs that make a release worth its cost (a few ms, and
            the shared helper functions traced again by the next new program).

    Returns:
        Whether a release happened.
    """
    staged = programs_staged()
    if staged - _count["at_release"] < min_new:
        return False
    _count["at_release"] = staged
    _clear_staging_caches()
    trim_heap()
    return True
