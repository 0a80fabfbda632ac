"""Persistent XLA compilation cache for the experiment scripts and the CLI (an edge utility).

SGM compiles one executable per padded graph-size bucket and pair count, so the first call of a
process spends most of its time compiling (on a 2-core CPU, a short noisy ``bench_sgm.py`` run spends
≈ 2 min before its first timed call without a cache, ≈ 40 s with a warm one). JAX can keep compiled
executables on disk (``jax_compilation_cache_dir``); :func:`enable_compilation_cache` turns that on
under the project's cache directory. The library itself never calls it: importing jstarid does not
change global JAX settings. Benchmarks leave it off so that their compile times stay honest.

It also turns on jstarid's program store (:mod:`jstarid.runtime.program_store`) beside it: JAX finds
a cached executable only after tracing and lowering the function again, which for SGM's hundreds of
small programs costs more than compiling them; the store keys programs by their call signature and
loads them without either.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

from jstarid.catalog import cache_dir

__all__ = ["enable_compilation_cache"]


def enable_compilation_cache(path: str | os.PathLike | None = None, *,
                             min_compile_time_s: float = 0.0, programs: bool = True) -> Path:
    """Keep compiled XLA executables on disk so later processes skip recompilation.

    A cache directory already chosen through ``JAX_COMPILATION_CACHE_DIR`` (or
    ``jax.config``) is kept unless ``path`` is given.

    Args:
        path: cache directory; default ``<jstarid cache>/xla`` (``$JSTARID_CACHE`` or
            ``~/.cache/jstarid``).
        min_compile_time_s: only executables that took at least this long (s) to compile are
            stored. Default 0, every one: the small programs of eager steps (tens of them in a
            first ``identify``, ≈ 25 ms each to build) read back faster than they build — MLV's
            first call on 100 scenes in a warm process took 3.0–3.2 s with all of them kept
            against 4.3 s with those under 0.5 s rebuilt.
        programs: also turn on the program store in ``<jstarid cache>/programs`` (the programs of
            jstarid's kernels, loaded without tracing; :mod:`jstarid.runtime.program_store`).

    Returns:
        The cache directory in use.

    The environment variable ``JSTARID_COMPILATION_CACHE=off`` turns this function into a no-op
    (both caches stay off).

    Raises:
        ValueError: ``min_compile_time_s`` is negative.
    """
    if min_compile_time_s < 0:
        raise ValueError(f"min_compile_time_s must be ≥ 0, got {min_compile_time_s}")
    if os.environ.get("JSTARID_COMPILATION_CACHE", "").lower() in ("0", "off", "false", "no"):
        # turned off from outside (the test suite: JAX's cache code segfaulted in its workers)
        return Path(jax.config.jax_compilation_cache_dir or cache_dir() / "xla")
    current = jax.config.jax_compilation_cache_dir
    if path is None and current:
        chosen = Path(current)
    else:
        chosen = Path(path) if path is not None else cache_dir() / "xla"
    chosen.mkdir(parents=True, exist_ok=True)
    if current and Path(current) != chosen:
        # JAX opens its cache once per process: start over so that the new directory is used
        from jax.experimental.compilation_cache import compilation_cache
        compilation_cache.reset_cache()
    jax.config.update("jax_compilation_cache_dir", str(chosen))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    if programs:
        from jstarid.runtime.program_store import enable_program_store
        enable_program_store(cache_dir() / "programs")
    return chosen
