"""Throughput benchmarks, side by side in one run.

    python experiments/benchmark.py                       # all benchmarks
    python experiments/benchmark.py --only simulate --batch 10000
    python experiments/benchmark.py --only render,centroid --images 64
    python experiments/benchmark.py --only compile        # the compile budget (bench_compile.py)

``simulate``, ``render`` and ``centroid`` run here; ``sgm``, ``mlv``, ``rpnet`` and ``compile`` run
``experiments/bench_<name>.py`` in a subprocess each (``--batch``, ``--repeats``, ``--devices``,
``--seed`` and, to MLV, ``--mag-sigma`` passed on; SGM keeps its own batch of 1,000, and
``compile`` its batch sizes 1, 100 and 1,000) and their rows join the table. Each benchmark reports
compile time (first call) apart from steady-state throughput (median of ``--repeats`` timed calls
after compilation) and the process's peak resident memory; ``compile`` reports, per algorithm and
batch size, the programs compiled and the rate on fresh scenes (its module docstring).

Writes results/benchmark/{config.json, results.json, table.md}.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.random_streams import normals

HERE = Path(__file__).resolve().parent
SCRIPTS = ("sgm", "mlv", "rpnet", "compile")  # experiments/bench_<name>.py


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/benchmark", seed=0)
    p.add_argument("--only", default="simulate,render,centroid,sgm,mlv,rpnet,compile",
                   help="comma-separated benchmarks")
    p.add_argument("--images", type=int, default=32, help="frames per render and centroid-extraction call")
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


def bench_render(args) -> list[dict]:
    """``js.render`` frames/s: ``--images`` frames per call of each camera, its default sensor
    (``js.sensor_for_camera``), stars simulated to V 9 on ``tetra3_test`` (as its real frames show)."""
    rows = []
    for name in args.cameras.split(",") + ["tetra3_test"]:
        cam = js.camera_preset(name)
        deep = dataclasses.replace(cam, mag_limit=9.0) if name == "tetra3_test" else cam
        scenes = js.simulate(jax.random.key(args.seed), js.load_catalog(deep.mag_limit), deep,
                             batch_size=args.images, capacity=256)
        sensor = js.sensor_for_camera(cam)
        for shard in [False, True] if jax.device_count() > 1 else [False]:
            def run(i, shard=shard, scenes=scenes, deep=deep, sensor=sensor):
                return js.render(jax.random.key(i), scenes, deep, sensor, shard=shard)
            first, steady = ex.time_call(run, args.repeats)
            stars = round(float(np.asarray(scenes.valid).sum(1).mean()))
            rows.append({"benchmark": "render", "camera": name, "size": f"{cam.width}x{cam.height}",
                         "batch": args.images, "devices": jax.device_count() if shard else 1,
                         "stars_per_frame": stars, "compile_s": round(first - steady, 2),
                         "scenes_per_s": round(args.images / steady, 1),
                         "peak_rss_mb": round(ex.peak_rss_mb())})
            print(rows[-1], flush=True)
        rows += _render_floor(args, cam)
    return rows


def _render_floor(args, cam) -> list[dict]:
    """What bounds the renderer on this machine, for the same frames: writing a float32 frame of the
    camera's size from one fused elementwise pass (the memory floor: no renderer that returns float32
    frames can beat it) and drawing one standard normal per pixel (the renderer's noise stream)."""
    shape = (args.images, cam.height, cam.width)
    parts = {
        "write float32 frames": jax.jit(lambda i: jax.lax.broadcasted_iota(jnp.float32, shape, 2)
                                        + i.astype(jnp.float32)),
        "one normal per pixel": jax.jit(lambda i: jax.vmap(lambda s: normals(s, 101, shape[1:]))(
            jnp.stack([jnp.arange(shape[0], dtype=jnp.uint32) + i] * 2, axis=1))),
    }
    rows = []
    for part, fn in parts.items():
        first, steady = ex.time_call(lambda i, fn=fn: fn(jnp.uint32(i)), args.repeats)
        rows.append({"benchmark": "render floor", "part": part, "size": f"{cam.width}x{cam.height}",
                     "batch": args.images, "devices": 1, "compile_s": round(first - steady, 2),
                     "scenes_per_s": round(args.images / steady, 1), "peak_rss_mb": round(ex.peak_rss_mb())})
        print(rows[-1], flush=True)
    return rows


def bench_centroid(args) -> list[dict]:
    """``js.extract_centroids`` images/s on ``--images`` 1024×768 frames (``tetra3_test`` size).

    The frames are rendered (``js.render``, the ``tetra3_test`` sensor fitted to the real frames) from
    scenes simulated to V 9, so the benchmark needs no image files.
    """
    cam = js.camera_preset("tetra3_test")
    deep = dataclasses.replace(cam, mag_limit=9.0)
    scenes = js.simulate(jax.random.key(args.seed), js.load_catalog(9.0), deep, batch_size=args.images,
                         capacity=256)
    images = np.asarray(js.render(jax.random.key(args.seed + 1), scenes, deep, js.sensor_for_camera(cam)))
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
    own_batches = name in ("sgm", "compile")
    flags = [] if own_batches else ["--batch", str(args.batch), "--repeats", str(args.repeats)]
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


# Columns of the two tables; a row without a key prints "–".
STEADY_COLUMNS = [
    ("benchmark", "benchmark", "{}"), ("camera", "camera", "{}"), ("batch", "B", "{:,}"),
    ("devices", "devices", "{}"), ("setting", "setting", "{}"),
    ("scenes_per_s", "scenes/s (fresh inputs, compilation excluded)", "{:,}"),
    ("compile_s", "compile s (first calls − steady)", "{}"), ("peak_rss_mb", "peak RSS MiB", "{:,}")]
COMPILE_COLUMNS = [
    ("algorithm", "algorithm", "{}"), ("camera", "camera", "{}"), ("batch", "B", "{:,}"),
    ("first_call_s", "first call s", "{}"), ("programs", "programs compiled", "{}"),
    ("compile_s", "XLA compile s", "{}"), ("later_programs", "programs in later calls", "{}"),
    ("scenes_per_s", "scenes/s, fresh scenes (compilation included)", "{:,}"),
    ("identified", "identified (strict)", "{:.1%}")]
SETTING_KEYS = ("noise", "sigma_px", "config", "part", "size", "sample_stride", "stars_per_frame")


def benchmark_tables(rows: list[dict], note: str = "") -> str:
    """The markdown of a benchmark run: steady throughput, then the compile budget.

    Steady rows: the median of the timed calls after the first, each on inputs no earlier call saw
    (compilation excluded; ``compile s`` is what the first call took beyond a steady one).
    Compile-budget rows (``bench_compile.py``): the first call at each batch size, then the median of
    the calls on fresh scenes of that size with any compilation they still cause.
    """
    steady, budget = [], []
    for r in rows:
        if r["benchmark"].startswith("compile "):
            budget.append({**r, "algorithm": r["benchmark"].removeprefix("compile ")})
            continue
        setting = ", ".join(f"{k} {r[k]}" if k != "noise" else str(r[k]) for k in SETTING_KEYS if k in r)
        steady.append({**r, "setting": setting or None,
                       "camera": r.get("camera", "sgm2022" if r["benchmark"] == "sgm" else None)})
    parts = []
    if steady:
        parts += ["**Steady throughput**: the median of the timed calls after the first, each on inputs "
                  "no earlier call saw; compilation excluded.\n", ex.markdown_table(steady, STEADY_COLUMNS)]
    if budget:
        parts += ["**Compile budget** (`experiments/bench_compile.py`, no persistent cache): the first "
                  "call of each batch size, then calls on fresh scenes of that size, any compilation "
                  "they still cause included.\n", ex.markdown_table(budget, COMPILE_COLUMNS)]
    text = "\n".join(parts)
    return text + (f"\n{note}\n" if note else "")


def main(argv=None) -> int:
    args = parse_args(argv)
    js.use_cpu_cores(args.devices)  # before the first JAX computation
    print(ex.machine())
    rows = []
    with ex.Stopwatch() as clock:
        for name in args.only.split(","):
            if name == "simulate":
                rows += bench_simulate(args)
            elif name == "centroid":
                rows += bench_centroid(args)
            elif name == "render":
                rows += bench_render(args)
            elif name in SCRIPTS:
                rows += bench_script(name, args)
            else:
                print(f"({name}: no such benchmark)")
    table = benchmark_tables(rows, note=f"{ex.machine()['devices']}; {clock.seconds:.0f} s in all.")
    print("\n" + table)
    ex.write(args.out, config={"args": vars(args)}, results={"rows": rows}, table=table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
