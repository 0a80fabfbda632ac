"""What a compiled program costs in memory: JAX's staging caches against the executable.

Compiles SGM's triangle-screen kernel (:mod:`jstarid.algorithms.sgm.screen`, split over every CPU
core by ``map_batch``) at ``--sizes`` graph sizes × ``--pairs`` pair counts in a fresh process, then
measures the resident memory (heap trimmed before each reading) after compiling, after
:func:`jstarid.runtime.release_staging` (staging caches dropped, executables kept), after calling
every shape again (must not stage anything: the executables are reused), and after
``jax.clear_caches()`` (executables dropped too). Per program: staging MB = what the release
freed, executable MB = what ``clear_caches`` freed after it.

    python experiments/probes/program_memory.py
    python experiments/probes/program_memory.py --sizes 16 --pairs 64 128
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms.sgm import screen
from jstarid.runtime import map_batch, staging_memory

COLUMNS = [("programs", "programs", "{}"), ("compiled_mb", "compiled MB", "{:.1f}"),
           ("staging_mb_per_program", "staging MB / program", "{:.2f}"),
           ("executable_mb_per_program", "executable MB / program", "{:.2f}"),
           ("staged_on_rerun", "staged on rerun", "{}"), ("rerun_s", "rerun s", "{:.3f}")]


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/program_memory")
    p.add_argument("--sizes", type=int, nargs="+", default=[16, 24, 32], help="padded graph sizes")
    p.add_argument("--pairs", type=int, nargs="+", default=[64, 128, 256, 512, 1024],
                   help="pairs per call")
    return p.parse_args(argv)


def resident_mb() -> float:
    """This process's resident memory now (MiB), after trimming the heap (Linux ``/proc``)."""
    staging_memory.trim_heap()
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


def run(args) -> dict:
    """Measure; returns the row of :data:`COLUMNS` (MB are MiB)."""
    static = dict(partners=4, fraction=0.6, min_matched=3)
    tol = jnp.float32(0.25)

    def pairs(n, r):  # the screen kernel's inputs: neighbor radii, azimuths, hypotheses, counts
        side = (jnp.zeros((n, r - 1)), jnp.zeros((n, r - 1)))
        return (*side, jnp.zeros((n, 8), jnp.int32), jnp.zeros((n, 8), bool), jnp.zeros(n, jnp.int32),
                *side, jnp.zeros(n, jnp.int32))

    shapes = [pairs(n, r) for r in args.sizes for n in args.pairs]

    def call_all():
        for batched in shapes:
            jax.block_until_ready(map_batch(screen._screen_kernel, batched, (tol,), static=static))

    jax.block_until_ready(shapes[-1][0] + 1)  # the backend and eager ops up before the first reading
    staging_memory.release_staging(min_new=0)
    start = resident_mb()
    call_all()
    compiled = resident_mb()
    staging_memory.release_staging(min_new=0)
    released = resident_mb()
    staged = staging_memory.programs_staged()
    t0 = time.perf_counter()
    call_all()
    rerun_s = time.perf_counter() - t0
    staged_on_rerun = staging_memory.programs_staged() - staged
    after_rerun = resident_mb()
    jax.clear_caches()
    cleared = resident_mb()
    n = len(shapes)
    return {"programs": n, "compiled_mb": compiled - start,
            "staging_mb_per_program": (compiled - released) / n,
            "executable_mb_per_program": (after_rerun - cleared) / n,
            "staged_on_rerun": staged_on_rerun, "rerun_s": rerun_s}


def main(argv=None) -> dict:
    args = parse_args(argv)
    row = run(args)
    print(ex.markdown_table([row], COLUMNS, title="Memory per compiled program"))
    ex.write(args.out, config={"args": vars(args)}, results={"row": row},
             table=ex.markdown_table([row], COLUMNS, title="Memory per compiled program"))
    return row


if __name__ == "__main__":
    js.use_cpu_cores()
    main()
