"""Compile budget: programs compiled, compile time, first call and steady rate on fresh scenes.

For each algorithm (its default config for its paper's camera, as a sweep runs it) and each batch
size B, in one process:

1. the first ``identify`` call on B fresh scenes: its wall time, the XLA programs it compiled and
   the seconds XLA spent compiling them (``jax.monitoring``'s backend-compile events);
2. ``--calls`` more calls, each on B *fresh* scenes of the same settings (a sweep meets new scenes
   every call; the same scenes twice would only time the in-memory program cache): the programs
   they compiled (none is the goal) and their median wall time as scenes/s — the rate a sweep sees
   once a batch size has been met, any compilation in those calls included.

The database (and RpNet's network) is built or loaded before anything is timed. By default
nothing persists between processes: the program store and XLA's cache stay off, so the first call
is what an empty cache costs. ``--warm`` turns both on (``js.enable_compilation_cache``): run it
twice, and the second run's first calls are what a later process pays.

Usage::

    python experiments/bench_compile.py                                  # sgm, mlv, rpnet at 1, 100, 1000
    python experiments/bench_compile.py --algorithms mlv --batches 1,100,1000,4096 --calls 3
    python experiments/bench_compile.py --warm                           # run twice: cache, then warm
    python experiments/benchmark.py --only compile                       # the same, in benchmark's table
    python experiments/bench_compile.py --outcomes a.npz                 # … and every call's outcome
    python experiments/bench_compile.py --compare a.npz b.npz            # two runs, scene by scene

``experiments/benchmark.py`` runs it in a subprocess (a process of its own, so that nothing it
measures was compiled before) and reads its rows from ``--json``. Writes
results/bench_compile/{config.json, results.json, table.md}.
"""

from __future__ import annotations

import time

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.runtime import CountCompilations
from jstarid.runtime.program_store import program_store_stats

#: each algorithm on its paper's camera (conventions §6)
CAMERAS = {"sgm": "sgm2022", "mlv": "mlv2021", "rpnet": "rpnet2019"}
NOISE = js.NoiseConfig(position_sigma_px=1.0, magnitude_sigma=0.1)
CAPACITY = 64


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/bench_compile", seed=0)
    p.add_argument("--algorithms", default="sgm,mlv,rpnet", help="comma-separated registry names")
    p.add_argument("--batches", default="1,100,1000", help="comma-separated batch sizes")
    p.add_argument("--calls", type=int, default=2, help="calls on fresh scenes after the first")
    p.add_argument("--camera", default=None, help="one camera for every algorithm (default: each "
                   "algorithm's paper camera: " + ", ".join(f"{a} {c}" for a, c in CAMERAS.items()) + ")")
    p.add_argument("--devices", type=int, default=None, help="JAX CPU devices (default: one per core)")
    p.add_argument("--json", default=None, help="also write the rows to this file")
    p.add_argument("--outcomes", default=None, help="also write every call's ids, ok and attitude to "
                   "this .npz (compare two runs' outcomes scene by scene: --compare)")
    p.add_argument("--compare", nargs=2, default=None, metavar=("A", "B"),
                   help="only compare two --outcomes files and print where they differ")
    p.add_argument("--warm", action="store_true",
                   help="turn on the program store and XLA's cache (run twice to see a warm process)")
    args = p.parse_args(argv)
    args.algorithms = [a.strip() for a in args.algorithms.split(",") if a.strip()]
    args.batches = [int(b) for b in args.batches.split(",")]
    if args.calls < 1 or min(args.batches) < 1:
        p.error("--calls and every batch size must be ≥ 1")
    return args


def _timed_call(algo, db, config, scenes):
    """``(result, wall s, programs compiled, compile s, programs loaded from the store)``."""
    loaded = program_store_stats()["loaded"]
    with CountCompilations() as count:
        t0 = time.perf_counter()
        result = algo.identify(db, scenes, config)
        jax.block_until_ready(result.ids)
        wall = time.perf_counter() - t0
    return result, wall, count.programs, count.seconds, program_store_stats()["loaded"] - loaded


def compare_outcomes(path_a: str, path_b: str) -> int:
    """Print, per call of two ``--outcomes`` files, the scenes whose ids or ``ok`` differ and the
    largest attitude difference (rad); returns the number of differing scenes."""
    a, b = np.load(path_a), np.load(path_b)
    differing = 0
    for key in sorted(k for k in a.files if k.endswith("/ids")):
        call = key[:-len("/ids")]
        ids = np.any(a[key] != b[key], axis=1) | (a[call + "/ok"] != b[call + "/ok"])
        both = a[call + "/ok"] & b[call + "/ok"]
        att = np.abs(a[call + "/attitude"][both] - b[call + "/attitude"][both])
        differing += int(ids.sum())
        print(f"{call}: {int(ids.sum())} of {ids.size} scenes differ in ids or ok; "
              f"attitudes within {float(att.max(initial=0.0)):.2e}")
    return differing


def measure(name: str, camera_name: str, args, outcomes: dict | None = None) -> list[dict]:
    """One algorithm's rows, one per batch size (module docstring)."""
    camera = js.load_camera(camera_name)
    catalog = js.load_catalog(camera.mag_limit)
    algo = js.algorithms.get(name)
    config = ex.with_overrides(js.engine.default_config(name, camera=camera), args.set)
    db = algo.build_database(catalog, camera, config)
    key = jax.random.fold_in(jax.random.key(args.seed), sum(map(ord, name)))
    rows = []
    for batch in args.batches:
        def fresh(call, batch=batch):  # scenes no earlier call has seen
            return js.simulate(jax.random.fold_in(key, batch * 1000 + call), catalog, camera, NOISE,
                               batch_size=batch, capacity=CAPACITY)

        scenes = [fresh(c) for c in range(args.calls + 1)]
        calls = [_timed_call(algo, db, config, s) for s in scenes]
        if outcomes is not None:
            for c, (result, *_) in enumerate(calls):
                att = np.full((batch, 3, 3), np.nan) if result.attitude is None else result.attitude
                outcomes.update({f"{name}/{batch}/{c}/ids": np.asarray(result.ids),
                                 f"{name}/{batch}/{c}/ok": np.asarray(result.ok),
                                 f"{name}/{batch}/{c}/attitude": np.asarray(att)})
        _, first_s, programs, compile_s, loaded = calls[0]
        later = calls[1:]
        identified = [js.evaluate(s, c[0], "strict")["identification_rate"]
                      for s, c in zip(scenes, calls, strict=True)]
        steady_s = float(np.median([c[1] for c in later]))
        rows.append({"benchmark": f"compile {name}", "camera": camera_name, "batch": batch,
                     "first_call_s": round(first_s, 2), "programs": programs,
                     "compile_s": round(compile_s, 2), "loaded": loaded,
                     "later_programs": int(sum(c[2] for c in later)),
                     "scenes_per_s": round(batch / steady_s, 1),
                     "identified": round(float(np.mean(identified)), 4),
                     "peak_rss_mb": round(ex.peak_rss_mb())})
        print(rows[-1], flush=True)
    return rows


def main(argv=None):
    args = parse_args(argv)
    if args.compare:
        differing = compare_outcomes(*args.compare)
        print("outcomes identical" if not differing else f"{differing} scenes differ")
        return
    js.use_cpu_cores(args.devices)
    if args.warm:
        js.enable_compilation_cache()
    rows, outcomes = [], ({} if args.outcomes else None)
    with ex.Stopwatch() as clock:
        for name in args.algorithms:
            rows += measure(name, args.camera or CAMERAS.get(name, "sgm2022"), args, outcomes)
    if outcomes is not None:
        np.savez_compressed(args.outcomes, **outcomes)
    cache = "program store and XLA cache on" if args.warm else "no persistent cache"
    table = ex.markdown_table(rows, [
        ("benchmark", "benchmark", "{}"), ("camera", "camera", "{}"), ("batch", "B", "{:,}"),
        ("first_call_s", "first call s", "{}"), ("programs", "programs compiled", "{}"),
        ("compile_s", "XLA compile s", "{}"), ("loaded", "programs loaded", "{}"),
        ("later_programs", "programs in later calls", "{}"),
        ("scenes_per_s", "scenes/s, fresh scenes", "{:,}"), ("identified", "identified", "{:.1%}")],
        title="Compile budget",
        note=(f"{cache}; {ex.machine()['devices']}; {clock.seconds:.0f} s in all. First call: wall "
              "time of the first identify of that batch size (compilation included); XLA compile s: "
              "the part XLA spent compiling. scenes/s: median of "
              f"{args.calls} calls on fresh scenes of the same size (any compilation in them "
              f"included). Noise: 1 px, 0.1 mag; capacity {CAPACITY}."))
    ex.write(args.out, config={"args": vars(args)}, results={"rows": rows}, table=table)
    ex.dump_json(args.json, rows)
    print(table)


if __name__ == "__main__":
    main()
