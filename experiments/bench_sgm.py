"""SGM throughput: scenes per second at position noise σ = 0, 1, 3 px (compile time reported apart).

Each level: simulate B scenes in mode (b) (main stars drawn from the catalog), call
``sgm.identify`` once (compiles every shape bucket the batch needs, and runs), then again on the same
scenes (steady state); scenes/s = B / (second call). Call :func:`run` from
``experiments/benchmark.py`` or run this file.

    python experiments/bench_sgm.py --batch 1000
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np

import jstarid as js
from jstarid.algorithms import sgm


def run(args) -> list[dict]:
    """Measure and print SGM throughput.

    Args:
        args: namespace (or any object) with ``batch`` (int), ``sigmas`` (floats, px), ``seed``
            (int), ``capacity`` (int) and ``mag_limit`` (float).

    Returns:
        One dict per σ: ``sigma_px``, ``batch``, ``first_call_s`` (compile + run), ``steady_s``,
        ``scenes_per_s``, ``compile_s_est`` (first − steady), ``accuracy``, ``failure_rate``,
        ``misid_rate``, ``device``.
    """
    cat = js.load_catalog(args.mag_limit)
    cam = js.camera_preset("sgm2022")
    cfg = sgm.Config()
    db = sgm.build_database(cat, cam, cfg)
    rng = np.random.default_rng(args.seed)
    rows = rng.choice(len(cat), args.batch, replace=args.batch > len(cat))
    out = []
    for sigma in args.sigmas:
        scenes = js.simulate(jax.random.key(args.seed), cat, cam,
                             js.NoiseConfig(position_sigma_px=float(sigma)),
                             capacity=args.capacity, boresight_ids=rows)
        jax.block_until_ready(scenes.xy)
        t0 = time.perf_counter()
        sgm.identify(db, scenes, cfg, with_attitude=False)
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = sgm.identify(db, scenes, cfg, with_attitude=False)
        jax.block_until_ready(res.ids)
        steady = time.perf_counter() - t0
        ev = js.evaluate(scenes, res, "sgm", camera=cam, radius_deg=cfg.radius_deg)
        row = {"sigma_px": float(sigma), "batch": int(args.batch), "first_call_s": first,
               "steady_s": steady, "scenes_per_s": args.batch / steady,
               "compile_s_est": max(first - steady, 0.0), "accuracy": ev["accuracy"],
               "failure_rate": ev["failure_rate"], "misid_rate": ev["misid_rate"],
               "device": str(jax.devices()[0])}
        out.append(row)
        print(f"SGM σ={sigma:.1f}px  B={args.batch}  {row['scenes_per_s']:.2f} scenes/s  "
              f"(steady {steady:.1f}s, first call {first:.1f}s)  acc={ev['accuracy']:.4f} "
              f"fail={ev['failure_rate']:.4f} misid={ev['misid_rate']:.4f}", flush=True)
    return out


def _parser():
    p = argparse.ArgumentParser(description="SGM throughput (scenes/s)")
    p.add_argument("--batch", type=int, default=1000)
    p.add_argument("--sigmas", type=float, nargs="+", default=[0.0, 1.0, 3.0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--capacity", type=int, default=128)
    p.add_argument("--mag-limit", type=float, default=6.0)
    p.add_argument("--json", default=None, help="also write the rows to this file")
    return p


if __name__ == "__main__":
    a = _parser().parse_args()
    rows = run(a)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=2)
