"""MLV throughput benchmark: scenes per second at batch ≥ 1000, compile time apart, database size.

``run(args)`` returns a list with one row (``benchmark``, ``scenes_per_s``, ``compile_s``,
``peak_rss_mb`` and details) so that ``experiments/benchmark.py`` can call it with its own
namespace (it reads ``batch``, ``repeats`` and ``mag_sigma`` from it; other settings fall back to
this file's defaults), or from the command line::

    python experiments/bench_mlv.py --batch 1000 --repeats 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import time

import jax
import numpy as np

import jstarid as js
from jstarid.algorithms import mlv


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--batch", type=int, default=1000, help="scenes per timed call (≥ 1000)")
    p.add_argument("--repeats", type=int, default=3, help="timed calls after the compile call")
    p.add_argument("--chunk", type=int, default=None, help="Config.batch_chunk override")
    p.add_argument("--map-batch", type=int, default=None, help="Config.map_batch override")
    p.add_argument("--position-sigma", type=float, default=1.0, help="px")
    p.add_argument("--magnitude-sigma", type=float, default=0.3, help="mag")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--devices", type=int, default=None,
                   help="JAX CPU devices (default: one per core; 1 keeps each chunk on one device)")
    p.add_argument("--paper-voting", action="store_true")
    p.add_argument("--json", default=None, help="write the result dict here")
    return p.parse_args(argv)


def run(args) -> list[dict]:
    """Benchmark MLV on the mlv2021 camera; returns one row of timings (s), rates and DB size."""
    defaults = vars(parse_args([]))
    opt = {k: getattr(args, k, v) for k, v in defaults.items()}
    if not hasattr(args, "magnitude_sigma") and hasattr(args, "mag_sigma"):
        opt["magnitude_sigma"] = args.mag_sigma  # experiments/benchmark.py's name
    cfg = mlv.Config()
    if opt["chunk"] is not None:
        cfg = dataclasses.replace(cfg, batch_chunk=opt["chunk"])
    if opt["map_batch"] is not None:
        cfg = dataclasses.replace(cfg, map_batch=opt["map_batch"])
    if opt["paper_voting"]:
        cfg = dataclasses.replace(cfg, vertex_match=False, attitude_check=False,
                                  field_check=False)
    catalog = js.load_catalog(5.5)
    camera = js.camera_preset("mlv2021")
    t0 = time.perf_counter()
    db = mlv.build_database(catalog, camera, cfg, progress=False)
    db_seconds = time.perf_counter() - t0
    noise = js.NoiseConfig(position_sigma_px=opt["position_sigma"],
                           magnitude_sigma=opt["magnitude_sigma"])
    keys = jax.random.split(jax.random.key(opt["seed"]), opt["repeats"] + 1)
    batches = [js.simulate(k, catalog, camera, noise, batch_size=opt["batch"], capacity=64)
               for k in keys]
    jax.block_until_ready(batches[-1].xy)
    t0 = time.perf_counter()  # first call: compilation (and any buffer growth) + one batch
    first = mlv.identify(db, batches[0], cfg)
    first.ids.block_until_ready()
    first_seconds = time.perf_counter() - t0
    times, reports = [], []
    for scenes in batches[1:]:
        t0 = time.perf_counter()
        res = mlv.identify(db, scenes, cfg)
        res.ids.block_until_ready()
        times.append(time.perf_counter() - t0)
        reports.append(js.evaluate(scenes, res, "mlv"))
    steady = float(np.median(times))
    row = {
        "benchmark": "mlv", "camera": camera.name, "batch": opt["batch"],
        "noise": f"pos {opt['position_sigma']} px, mag {opt['magnitude_sigma']}",
        "scenes_per_s": round(opt["batch"] / steady),
        "compile_s": round(max(first_seconds - steady, 0.0), 2),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "backend": jax.default_backend(), "batch_chunk": cfg.batch_chunk,
        "map_batch": cfg.map_batch, "candidate_pool": mlv.default_pool(cfg, n_db_triangles=db.n_triangles),
        "paper_voting": bool(opt["paper_voting"]),
        "seconds_per_batch": round(steady, 3), "first_call_s": round(first_seconds, 2),
        "db_bytes": db.nbytes, "db_device_bytes": db.device_nbytes,
        "db_triangles": db.n_triangles, "db_build_s": round(db_seconds, 2),
        "db_cached": bool(db.info_dict().get("cached", False)),
        "identification_rate": float(np.mean([r["identification_rate"] for r in reports])),
        "misid_rate": float(np.mean([r["misid_rate"] for r in reports])),
    }
    return [row]


if __name__ == "__main__":
    a = parse_args()
    js.use_cpu_cores(a.devices)  # each chunk's scenes split over every core (one JAX device each)
    out = run(a)
    print(json.dumps(out, indent=1))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=2)
