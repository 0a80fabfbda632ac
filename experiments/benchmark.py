"""Throughput benchmarks, side by side in one run.

    python experiments/benchmark.py                       # all available benchmarks
    python experiments/benchmark.py --only simulate --batch 10000
    python experiments/benchmark.py --only centroid --images 32

Each benchmark reports compile time (first call) apart from steady-state throughput (best of
``--repeats`` timed calls after compilation) and the process's peak resident memory. Results are also
written to ``results/benchmark/results.json``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import resource
import sys
import time
from pathlib import Path

import jax
import numpy as np

import jstarid as js

HERE = Path(__file__).resolve().parent


def peak_rss_mb() -> float:
    """Peak resident set size of this process (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def time_call(fn, repeats: int):
    """(compile + first-call seconds, best steady-state seconds) of ``fn(i)`` (i = call number)."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(0))
    first = time.perf_counter() - t0
    best = np.inf
    for i in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(i + 1))
        best = min(best, time.perf_counter() - t0)
    return first, best


def bench_simulate(args) -> list[dict]:
    """``js.simulate`` scenes/s at batch ``--batch``, capacity 64, every noise model on.

    Two rows per camera, from one process: the batch on one device (``shard=False``) and split over
    every device (``shard=True``; :func:`main` exposes each CPU core as a device).
    """
    cat = js.load_catalog(6.0)
    rows = []
    noise = js.NoiseConfig(position_sigma_px=1.0, magnitude_sigma=args.mag_sigma, n_missing=1,
                           n_false=2)
    layouts = [False, True] if jax.device_count() > 1 else [False]
    for name in args.cameras.split(","):
        cam = js.camera_preset(name)
        for shard in layouts:
            def run(i, cam=cam, shard=shard):
                return js.simulate(jax.random.key(i), cat, cam, noise, batch_size=args.batch, capacity=64,
                                   shard=shard)
            first, best = time_call(run, args.repeats)
            rows.append({"benchmark": "simulate", "camera": name, "batch": args.batch,
                         "devices": jax.device_count() if shard else 1,
                         "noise": f"pos 1 px, mag {args.mag_sigma:.2f}, 1 missing, 2 false",
                         "compile_s": round(first - best, 2), "scenes_per_s": round(args.batch / best),
                         "peak_rss_mb": round(peak_rss_mb())})
            print(rows[-1], flush=True)
    return rows


def bench_centroid(args) -> list[dict]:
    """``js.extract_centroids`` images/s on ``--images`` 1024×768 frames (``tetra3_test`` size).

    The frames are rendered from simulated scenes (Gaussian PSFs, sky 1000, read noise 10 counts), so
    the benchmark needs no image files; the real test images are of the same size.
    """
    cam = js.camera_preset("tetra3_test")
    cat = js.load_catalog(7.0)
    scenes = js.simulate(jax.random.key(0), cat, cam, batch_size=args.images, capacity=64)
    rng = np.random.default_rng(0)
    images = np.empty((args.images, cam.height, cam.width), np.float32)
    yy, xx = np.mgrid[0:15, 0:15]
    for i in range(args.images):
        img = 1000.0 + rng.normal(0.0, 10.0, (cam.height + 14, cam.width + 14))
        for (x, y), m, v in zip(np.asarray(scenes.xy[i]), np.asarray(scenes.mag[i]),
                                np.asarray(scenes.valid[i]), strict=True):
            if v:
                x0, y0 = int(x), int(y)
                psf = np.exp(-((xx - 7 - (x - x0)) ** 2 + (yy - 7 - (y - y0)) ** 2) / (2 * 0.8 ** 2))
                img[y0:y0 + 15, x0:x0 + 15] += 10 ** (-0.4 * (m - 16.7)) * psf / psf.sum()
        images[i] = img[7:-7, 7:-7]
    rows = []
    cfg = js.CentroidConfig(sample_stride=args.sample_stride)
    for shard in [False, True] if jax.device_count() > 1 else [False]:
        first, best = time_call(lambda i, shard=shard: js.extract_centroids(
            images, cfg, capacity=64, shard=shard).xy, args.repeats)
        rows.append({"benchmark": "centroid", "camera": "tetra3_test", "batch": args.images,
                     "sample_stride": args.sample_stride, "devices": jax.device_count() if shard else 1,
                     "compile_s": round(first - best, 2), "scenes_per_s": round(args.images / best, 1),
                     "peak_rss_mb": round(peak_rss_mb())})
        print(rows[-1], flush=True)
    return rows


def _external(name):
    """Benchmarks contributed by algorithm modules: experiments/bench_<name>.py with ``run(args)``."""
    path = HERE / f"bench_{name}.py"
    if not path.exists():
        return None
    spec = importlib.util.spec_from_file_location(f"bench_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.run


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--only", default="simulate,centroid,sgm,mlv,rpnet",
                   help="comma-separated benchmarks")
    p.add_argument("--images", type=int, default=32, help="frames per centroid-extraction call")
    p.add_argument("--sample-stride", type=int, default=2,
                   help="CentroidConfig.sample_stride of the centroid benchmark (1: full medians)")
    p.add_argument("--batch", type=int, default=10_000)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--cameras", default="sgm2022,mlv2021,rpnet2019")
    p.add_argument("--mag-sigma", type=float, default=0.1)
    p.add_argument("--out", default="results/benchmark")
    p.add_argument("--devices", type=int, default=None,
                   help="JAX CPU devices (default: one per core); 1 keeps the batch on one device")
    args = p.parse_args(argv)
    js.use_cpu_cores(args.devices)  # before the first JAX computation
    env = {"python": sys.version.split()[0], "jax": jax.__version__, "devices": str(jax.devices()),
           "cpu_count": os.cpu_count(), "machine": platform.machine()}
    print(env)
    rows = []
    for name in args.only.split(","):
        if name == "simulate":
            rows += bench_simulate(args)
        elif name == "centroid":
            rows += bench_centroid(args)
        else:
            fn = _external(name)
            if fn is None:
                print(f"({name}: no benchmark available yet)")
                continue
            rows += fn(args)
    print("\n| benchmark | setting | scenes/s | compile s | peak RSS MiB |\n|---|---|---|---|---|")
    for r in rows:
        setting = ", ".join(f"{k}={v}" for k, v in r.items()
                            if k not in ("benchmark", "scenes_per_s", "compile_s", "peak_rss_mb"))
        print(f"| {r['benchmark']} | {setting} | {r['scenes_per_s']} | {r['compile_s']} | "
              f"{r['peak_rss_mb']} |")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps({"env": env, "args": vars(args), "rows": rows},
                                                 indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
