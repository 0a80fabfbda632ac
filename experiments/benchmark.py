"""Throughput benchmarks, side by side in one run.

    python experiments/benchmark.py                       # all benchmarks
    python experiments/benchmark.py --only simulate --batch 10000
    python experiments/benchmark.py --only centroid --images 32

``simulate`` and ``centroid`` run here; ``sgm``, ``mlv`` and ``rpnet`` run
``experiments/bench_<name>.py`` in a subprocess each (``--batch``, ``--repeats``, ``--devices``,
``--seed`` and, to MLV, ``--mag-sigma`` passed on; SGM keeps its own batch of 1,000) and their rows
join the table. Each benchmark reports compile time (first call) apart from steady-state throughput
(median of ``--repeats`` timed calls after compilation) and the process's peak resident memory.

Writes results/benchmark/{config.json, results.json, table.md}.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex

HERE = Path(__file__).resolve().parent
SCRIPTS = ("sgm", "mlv", "rpnet")  # experiments/bench_<name>.py


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/benchmark", seed=0)
    p.add_argument("--only", default="simulate,centroid,sgm,mlv,rpnet", help="comma-separated benchmarks")
    p.add_argument("--images", type=int, default=32, help="frames per centroid-extraction call")
    p.add_argument("--sample-stride", type=int, default=2,
                   help="CentroidConfig.sample_stride of the centroid benchmark (1: full medians)")
    p.add_argument("--batch", type=int, default=10_000,
                   help="scenes per call (simulate, mlv, rpnet; sgm uses bench_sgm.py's 1,000)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--cameras", default="sgm2022,mlv2021,rpnet2019")
    p.add_argument("--mag-sigma", type=float, default=0.1, help="magnitude noise σ (simulate, mlv)")
    p.add_argument("--devices", type=int, default=None,
                   help="JAX CPU devices (default: one per core); 1 keeps the batch on one device")
    args = p.parse_args(argv)
    if args.set:
        p.error("--set: give an algorithm's overrides to its own experiments/bench_<name>.py")
    return args


def bench_simulate(args) -> list[dict]:
    """``js.simulate`` scenes/s at batch ``--batch``, capacity 64, every noise model on.

    Two rows per camera, from one process: the batch on one device (``shard=False``) and split over
    every device (``shard=True``; :func:`main` exposes each CPU core as a device).
    """
    cat = js.load_catalog(6.0)
    rows = []
    noise = js.NoiseConfig(position_sigma_px=1.0, magnitude_sigma=args.mag_sigma, n_missing=1, n_false=2)
    layouts = [False, True] if jax.device_count() > 1 else [False]
    for name in args.cameras.split(","):
        cam = js.camera_preset(name)
        for shard in layouts:
            def run(i, cam=cam, shard=shard):
                return js.simulate(jax.random.key(args.seed + i), cat, cam, noise, batch_size=args.batch,
                                   capacity=64, shard=shard)
            first, steady = ex.time_call(run, args.repeats)
            rows.append({"benchmark": "simulate", "camera": name, "batch": args.batch,
                         "devices": jax.device_count() if shard else 1,
                         "noise": f"pos 1 px, mag {args.mag_sigma:.2f}, 1 missing, 2 false",
                         "compile_s": round(first - steady, 2), "scenes_per_s": round(args.batch / steady),
                         "peak_rss_mb": round(ex.peak_rss_mb())})
            print(rows[-1], flush=True)
    return rows


def bench_centroid(args) -> list[dict]:
    """``js.extract_centroids`` images/s on ``--images`` 1024×768 frames (``tetra3_test`` size).

    The frames are rendered from simulated scenes (Gaussian PSFs, sky 1000, read noise 10 counts), so
    the benchmark needs no image files; the real test images are of the same size.
    """
    cam = js.camera_preset("tetra3_test")
    cat = js.load_catalog(7.0)
    scenes = js.simulate(jax.random.key(args.seed), cat, cam, batch_size=args.images, capacity=64)
    rng = np.random.default_rng(args.seed)
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
        first, steady = ex.time_call(lambda i, shard=shard: js.extract_centroids(
            images, cfg, capacity=64, shard=shard).xy, args.repeats)
        rows.append({"benchmark": "centroid", "camera": "tetra3_test", "batch": args.images,
                     "sample_stride": args.sample_stride, "devices": jax.device_count() if shard else 1,
                     "compile_s": round(first - steady, 2), "scenes_per_s": round(args.images / steady, 1),
                     "peak_rss_mb": round(ex.peak_rss_mb())})
        print(rows[-1], flush=True)
    return rows


def bench_script(name: str, args) -> list[dict]:
    """The rows of ``experiments/bench_<name>.py``, run in a subprocess of its own."""
    flags = [] if name == "sgm" else ["--batch", str(args.batch), "--repeats", str(args.repeats)]
    if name == "mlv":
        flags += ["--magnitude-sigma", str(args.mag_sigma)]
    if args.devices is not None and name != "sgm":
        flags += ["--devices", str(args.devices)]
    with tempfile.TemporaryDirectory() as tmp:
        rows = Path(tmp) / "rows.json"
        command = [sys.executable, str(HERE / f"bench_{name}.py"), *flags, "--seed", str(args.seed),
                   "--out", tmp, "--json", str(rows)]
        if subprocess.run(command, check=False).returncode != 0 or not rows.exists():
            print(f"({name}: bench_{name}.py failed; no rows)", flush=True)
            return []
        return json.loads(rows.read_text())


def main(argv=None) -> int:
    args = parse_args(argv)
    js.use_cpu_cores(args.devices)  # before the first JAX computation
    print(ex.machine())
    rows = []
    for name in args.only.split(","):
        if name == "simulate":
            rows += bench_simulate(args)
        elif name == "centroid":
            rows += bench_centroid(args)
        elif name in SCRIPTS:
            rows += bench_script(name, args)
        else:
            print(f"({name}: no such benchmark)")
    lines = ["| benchmark | setting | scenes/s | compile s | peak RSS MiB |", "|---|---|---|---|---|"]
    for r in rows:
        setting = ", ".join(f"{k}={v}" for k, v in r.items()
                            if k not in ("benchmark", "scenes_per_s", "compile_s", "peak_rss_mb"))
        lines.append(f"| {r['benchmark']} | {setting} | {r['scenes_per_s']} | {r['compile_s']} | "
                     f"{r['peak_rss_mb']} |")
    table = "\n".join(lines) + "\n"
    print("\n" + table)
    ex.write(args.out, config={"args": vars(args)}, results={"rows": rows}, table=table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
