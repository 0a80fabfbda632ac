"""MLV throughput: scenes per second at batch ≥ 1000, compile time apart, database size.

    python experiments/bench_mlv.py --batch 1000 --repeats 3
    python experiments/bench_mlv.py --set batch_chunk=2048 map_batch=256
    python experiments/bench_mlv.py --paper          # the paper's algorithm alone
    python experiments/bench_mlv.py --camera narrow_twin  # V ≤ 10, the twin's noise, its defaults
    python experiments/bench_mlv.py --camera tetra3_test --set max_candidate_capacity=null  # all vote

``experiments/benchmark.py`` runs it in a subprocess and reads its rows from ``--json``. Writes
results/bench_mlv/{config.json, results.json, table.md}.
"""

from __future__ import annotations

import json

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms import mlv
from jstarid.papers import narrow_field as twin

COLUMNS = [("batch", "B", "{}"), ("noise", "noise", "{}"), ("paper", "paper alone", "{}"),
           ("scenes_per_s", "scenes/s", "{}"), ("compile_s", "compile s", "{}"),
           ("identification_rate", "identified", "{:.4%}"), ("misid_rate", "misid", "{:.4%}"),
           ("db_triangles", "DB triangles", "{:,}"), ("db_bytes", "DB bytes", "{:,}"),
           ("peak_rss_mb", "peak RSS MiB", "{}")]


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/bench_mlv", seed=0)
    p.add_argument("--paper", action="store_true",
                   help="start from Config.paper(): the paper's algorithm alone")
    p.add_argument("--batch", type=int, default=1000, help="scenes per timed call (≥ 1000)")
    p.add_argument("--repeats", type=int, default=3, help="timed calls after the compile call")
    p.add_argument("--camera", default="mlv2021",
                   help="mlv2021 (the paper's, V ≤ 5.5), tetra3_test (the real frames' camera, "
                        "V ≤ 7, 24 detections per scene) or narrow_twin (V ≤ 10, the noise of "
                        "experiments/narrow_twin.py, 128 detections per scene); MLV with "
                        "Config.for_camera")
    p.add_argument("--position-sigma", type=float, default=None, help="px (default 1, twin 0.8)")
    p.add_argument("--magnitude-sigma", type=float, default=None, help="mag (default 0.3, twin 0.2)")
    p.add_argument("--devices", type=int, default=None,
                   help="JAX CPU devices (default: one per core; 1 keeps each chunk on one device)")
    p.add_argument("--json", default=None, help="also write the rows to this file")
    return p.parse_args(argv)


def settings(args):
    """``(camera, catalog depth, noise, capacity, config)`` of the benchmark."""
    camera = js.camera_preset(args.camera)
    if args.camera == "narrow_twin":
        noise = {**twin.NOISE,
                 **{k: v for k, v in (("position_sigma_px", args.position_sigma),
                                      ("magnitude_sigma", args.magnitude_sigma)) if v is not None}}
        noise, depth, capacity = js.NoiseConfig(**noise), twin.MAG_LIMIT, twin.CAPACITY
    elif args.camera == "mlv2021":
        noise = js.NoiseConfig(position_sigma_px=1.0 if args.position_sigma is None else args.position_sigma,
                               magnitude_sigma=0.3 if args.magnitude_sigma is None else args.magnitude_sigma)
        depth, capacity = 5.5, 64
    elif args.camera == "tetra3_test":
        noise = js.NoiseConfig(position_sigma_px=1.0 if args.position_sigma is None else args.position_sigma,
                               magnitude_sigma=0.2 if args.magnitude_sigma is None else args.magnitude_sigma)
        depth, capacity = 7.0, 24
    else:
        raise ValueError(f"--camera must be mlv2021, tetra3_test or narrow_twin, got {args.camera!r}")
    base = mlv.Config.paper() if args.paper else mlv.Config.for_camera(camera)
    return camera, depth, noise, capacity, ex.with_overrides(base, args.set)


def run(args) -> list[dict]:
    """Benchmark MLV on one camera; returns one row of timings (s), rates and DB size."""
    camera, depth, noise, capacity, cfg = settings(args)
    catalog = js.load_catalog(depth)
    with ex.Stopwatch() as build:
        db = mlv.build_database(catalog, camera, cfg, progress=False)
    keys = jax.random.split(jax.random.key(args.seed), args.repeats + 1)
    batches = [js.simulate(k, catalog, camera, noise, batch_size=args.batch, capacity=capacity)
               for k in keys]
    jax.block_until_ready(batches[-1].xy)
    results = {}

    def call(i):  # the first call compiles (and grows any buffer); the others run compiled code
        results[i] = mlv.identify(db, batches[i], cfg)
        return results[i].ids

    first, steady = ex.time_call(call, args.repeats)
    reports = [js.evaluate(batches[i], results[i], "mlv") for i in range(1, args.repeats + 1)]
    return [{
        "benchmark": "mlv", "camera": camera.name, "batch": args.batch,
        "noise": f"pos {noise.position_sigma_px} px, mag {noise.magnitude_sigma}"
                 + (f", {noise.n_false} false" if noise.n_false else ""),
        "scenes_per_s": round(args.batch / steady), "compile_s": round(max(first - steady, 0.0), 2),
        "peak_rss_mb": round(ex.peak_rss_mb()), "backend": jax.default_backend(),
        "batch_chunk": cfg.batch_chunk, "map_batch": cfg.map_batch,
        "candidate_pool": mlv.default_pool(cfg, n_db_triangles=db.n_triangles), "paper": args.paper,
        "seconds_per_batch": round(steady, 3), "first_call_s": round(first, 2),
        "db_bytes": db.nbytes, "db_device_bytes": db.device_nbytes,
        "db_triangles": db.n_triangles, "db_build_s": round(build.seconds, 2),
        "db_cached": bool(db.info_dict().get("cached", False)),
        "identification_rate": float(np.mean([r["identification_rate"] for r in reports])),
        "misid_rate": float(np.mean([r["misid_rate"] for r in reports])),
    }]


def main(argv=None) -> list[dict]:
    args = parse_args(argv)
    rows = run(args)
    print(json.dumps(rows, indent=1))
    ex.dump_json(args.json, rows)
    cfg = settings(args)[-1]
    ex.write(args.out, config={"args": vars(args), "mlv_config": cfg}, results={"rows": rows},
             table=ex.markdown_table(rows, COLUMNS, title=f"MLV throughput ({args.camera})"))
    return rows


if __name__ == "__main__":
    js.use_cpu_cores(parse_args().devices)  # each chunk's scenes split over every core (one JAX device each)
    main()
