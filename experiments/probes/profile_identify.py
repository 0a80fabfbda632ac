"""Where a steady ``identify`` call spends its time: a profile of one call on fresh scenes.

One algorithm at its default for a camera, 1 px and 0.1 mag by default (``--sigma``,
``--mag-sigma``): ``--warm`` calls on fresh batches of ``--batch`` scenes first (each new path of
the finishing stage compiles once: the first doubtful claim, the first retry), then one more fresh
batch under ``cProfile``. Prints the wall time of every call, the profiled call's rate, and the
jstarid functions by cumulative time (the steps of the pipeline: the algorithm's own passes, the
camera check, rival names, the false-match step).
Kernel time shows where a step blocks on its results (``program_store``'s ``__call__``,
``run_calls``). What the issue's throughput goals ask of each step: experiments/RESULTS.md,
Throughput.

Usage::

    python experiments/probes/profile_identify.py --algorithm mlv --camera mlv2021 --batch 1000
"""

from __future__ import annotations

import cProfile
import io
import pstats
import time

import jax

import jstarid as js
from jstarid import experiment as ex
from jstarid.runtime import CountCompilations


def parse_args(argv=None):
    parser = ex.parser(__doc__.splitlines()[0], out="results/profile_identify")
    parser.add_argument("--algorithm", default="mlv")
    parser.add_argument("--camera", default="mlv2021")
    parser.add_argument("--batch", type=int, default=1000)
    parser.add_argument("--warm", type=int, default=4, help="calls on fresh scenes before the profiled one")
    parser.add_argument("--capacity", type=int, default=64)
    parser.add_argument("--sigma", type=float, default=1.0, help="centroid noise σ (px)")
    parser.add_argument("--mag-sigma", type=float, default=0.1, help="magnitude noise σ (mag)")
    parser.add_argument("--lines", type=int, default=30, help="functions printed")
    return parser.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    js.use_cpu_cores()
    camera = js.load_camera(args.camera)
    catalog = js.load_catalog(camera.mag_limit)
    algo = js.algorithms.get(args.algorithm)
    config = ex.with_overrides(js.engine.default_config(args.algorithm, camera=camera), args.set)
    db = algo.build_database(catalog, camera, config)
    key = jax.random.key(args.seed)
    noise = js.NoiseConfig(position_sigma_px=args.sigma, magnitude_sigma=args.mag_sigma)

    def fresh(call):
        scenes = js.simulate(jax.random.fold_in(key, call), catalog, camera, noise, batch_size=args.batch,
                             capacity=args.capacity)
        return jax.block_until_ready(scenes)

    for call in range(args.warm):
        scenes = fresh(call)
        start = time.perf_counter()
        jax.block_until_ready(algo.identify(db, scenes, config).ids)
        print(f"warm-up call {call}: {time.perf_counter() - start:.2f} s", flush=True)
    scenes = fresh(args.warm)
    profile = cProfile.Profile()
    with CountCompilations() as compiled:
        start = time.perf_counter()
        profile.enable()
        result = algo.identify(db, scenes, config)
        jax.block_until_ready(result.ids)
        profile.disable()
        wall = time.perf_counter() - start
    report = js.evaluate(scenes, result, "strict")
    print(f"profiled call: {wall:.3f} s, {args.batch / wall:,.0f} scenes/s, {compiled.programs} programs "
          f"compiled ({compiled.seconds:.1f} s), identified {report['identification_rate']:.4f}, "
          f"misid {report['misid_rate']:.4f}")
    out = io.StringIO()
    pstats.Stats(profile, stream=out).sort_stats("cumulative").print_stats("jstarid", args.lines)
    print(out.getvalue())


if __name__ == "__main__":
    main()
