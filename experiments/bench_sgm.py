"""SGM throughput: scenes per second at position noise σ = 0, 1, 3 px (compile time reported apart).

Each level: simulate B scenes in mode (b) (main stars drawn from the catalog), call
``sgm.identify`` on the first 64 of them (compiles the common shape buckets), then call it on all B
scenes twice: the first call (``first_call_s``) may still compile a few shape buckets, the second
(``steady_s``) runs compiled code only; scenes/s = B / ``steady_s``. Side by side, the
straightforward NumPy implementation (``sgm_numpy_reference.py``: per-candidate ``np.linalg.eig``,
Python loops) runs on the first ``--numpy-scenes`` scenes; its ids are compared with ours without the
post-match verification and the leftover naming (``Config.paper``: the same algorithm; the
leftover naming also names stars of the circle that a J* with fewer vertices leaves unmatched).
Call :func:`run` from ``experiments/benchmark.py`` or run this file.

    python experiments/bench_sgm.py --batch 1000
    python experiments/bench_sgm.py --batch 1000 --sigmas 1 --set size_bucket=16
"""

from __future__ import annotations

import argparse
import json
import math
import time

import jax
import numpy as np
from reproduce_sgm import config_overrides

import jstarid as js
from jstarid.algorithms import sgm


def run(args) -> list[dict]:
    """Measure and print SGM throughput.

    Args:
        args: namespace (or any object) with ``batch`` (int), ``sigmas`` (floats, px), ``seed``
            (int), ``capacity`` (int), ``mag_limit`` (float) and optionally ``set`` (a list of
            ``"field=json"`` SGM :class:`~jstarid.algorithms.sgm.Config` overrides, e.g.
            ``["size_bucket=16"]``, to time a setting against the defaults).

    Returns:
        One dict per σ: ``benchmark``, ``sigma_px``, ``batch``, ``warmup_s`` (compile + 64 scenes),
        ``first_call_s`` (B scenes, may compile more), ``steady_s`` (B scenes, compiled),
        ``scenes_per_s``, ``compile_s`` (warm-up estimate), ``matched_per_scene`` /
        ``pruned_per_scene`` (spectral matchings run and candidates the bound removed, mean per
        scene; from ``identify(..., diagnostics=True)``), the tail of the matchings per scene
        (:func:`matching_tail`: ``matched_median``, ``matched_p90``, ``matched_p99``,
        ``matched_top5_share``), ``accuracy``,
        ``failure_rate``, ``misid_rate``, ``numpy_scenes_per_s``, ``speedup_vs_numpy``,
        ``numpy_ids_agree`` (fraction of the NumPy scenes with identical ids), ``peak_rss_mb``.
    """
    import importlib.util
    import resource
    from pathlib import Path
    spec = importlib.util.spec_from_file_location(
        "sgm_numpy_reference", Path(__file__).resolve().parent / "sgm_numpy_reference.py")
    ref = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ref)
    # from benchmark.py (no ``sigmas``): its --batch is sized for the simulator; SGM uses 1,000
    batch = max(int(args.batch) if hasattr(args, "sigmas") else 1000, 64)
    sigmas = getattr(args, "sigmas", (0.0, 1.0, 3.0))
    n_np = int(getattr(args, "numpy_scenes", 5))
    cat = js.load_catalog(getattr(args, "mag_limit", 6.0))
    cam = js.camera_preset("sgm2022")
    overrides = config_overrides(getattr(args, "set", None) or [])
    cfg = sgm.Config(**overrides)
    db = sgm.build_database(cat, cam, cfg)
    seed = int(getattr(args, "seed", 0))
    rng = np.random.default_rng(seed)
    rows = rng.choice(len(cat), batch, replace=batch > len(cat))
    out = []
    for sigma in sigmas:
        scenes = js.simulate(jax.random.key(seed), cat, cam,
                             js.NoiseConfig(position_sigma_px=float(sigma)),
                             capacity=int(getattr(args, "capacity", 128)), boresight_ids=rows)
        jax.block_until_ready(scenes.xy)
        t0 = time.perf_counter()
        sgm.identify(db, scenes[:64], cfg, with_attitude=False)
        warm = time.perf_counter() - t0
        t0 = time.perf_counter()
        first_res, info = sgm.identify(db, scenes, cfg, with_attitude=False, diagnostics=True)
        jax.block_until_ready(first_res.ids)
        first = time.perf_counter() - t0  # may compile the buckets the warm-up did not meet
        t0 = time.perf_counter()
        res = sgm.identify(db, scenes, cfg, with_attitude=False)
        jax.block_until_ready(res.ids)
        steady = time.perf_counter() - t0
        ev = js.evaluate(scenes, res, "sgm", camera=cam, radius_deg=cfg.radius_deg)
        # the NumPy baseline on the first scenes, checked against ours without verification
        xy, valid = np.asarray(scenes.xy, np.float64), np.asarray(scenes.valid)
        np_rate, agree = float("nan"), float("nan")
        if n_np > 0:
            t0 = time.perf_counter()
            np_ids = [ref.identify_scene(db, xy[s], valid[s], cfg)[0] for s in range(n_np)]
            np_rate = n_np / (time.perf_counter() - t0)
            paper = sgm.identify(db, scenes[:n_np], sgm.Config.paper(**overrides),
                                 with_attitude=False)
            agree = float(np.mean([np.array_equal(a, b)
                                   for a, b in zip(np_ids, np.asarray(paper.ids), strict=True)]))
        row = {"benchmark": "sgm", "sigma_px": float(sigma), "batch": batch, "warmup_s": warm,
               "first_call_s": first, "steady_s": steady, "scenes_per_s": round(batch / steady, 2),
               "compile_s": round(warm, 1), "accuracy": ev["accuracy"],
               "matched_per_scene": round(float(np.mean(info.n_matched)), 2),
               "pruned_per_scene": round(float(np.mean(info.n_pruned)), 1),
               **matching_tail(info.n_matched),
               "failure_rate": ev["failure_rate"], "misid_rate": ev["misid_rate"],
               "numpy_scenes": n_np, "numpy_scenes_per_s": round(np_rate, 3),
               "speedup_vs_numpy": round(batch / steady / np_rate, 1), "numpy_ids_agree": agree,
               "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}
        out.append(row)
        print(f"SGM σ={sigma:.1f}px  B={batch}  {row['scenes_per_s']:.2f} scenes/s  "
              f"(batch {steady:.1f}s, first call {first:.1f}s, warm-up {warm:.1f}s)  "
              f"spectral matchings/scene {row['matched_per_scene']:.2f} (pruned "
              f"{row['pruned_per_scene']:.1f}; median {row['matched_median']:g}, 99th pct "
              f"{row['matched_p99']:g}, top 5 % of scenes {100 * row['matched_top5_share']:.0f} %)  "
              f"acc={ev['accuracy']:.4f} "
              f"fail={ev['failure_rate']:.4f} misid={ev['misid_rate']:.4f}  NumPy "
              f"{np_rate:.3f} scenes/s → ×{row['speedup_vs_numpy']}, ids agree {agree:.2f}  "
              f"peak RSS {row['peak_rss_mb']} MB", flush=True)
    return out


def matching_tail(n_matched) -> dict:
    """How the spectral matchings spread over the scenes of a batch.

    Under noise a few scenes hold most of the work: Algorithm 1 must show that every candidate of
    the Δw levels below the one that succeeds fails, and a scene whose MST weight lies far from its
    true graph's (e.g. a star crossed the neighbor circle) succeeds only at a wide Δw, after matching
    the hundreds of candidates the bound cannot exclude. The mean alone hides that.

    Args:
        n_matched: (B,) spectral matchings run per scene.

    Returns:
        ``matched_median``, ``matched_p90``, ``matched_p99`` (per scene) and ``matched_top5_share``
        (the share of all matchings run for the ⌈5 %⌉ of scenes with the most; 0 when none ran).
    """
    n = np.sort(np.asarray(n_matched, np.float64))[::-1]
    top = n[: max(1, math.ceil(0.05 * n.size))]
    total = float(np.sum(n))
    q50, q90, q99 = np.quantile(n, [0.5, 0.9, 0.99])
    return {"matched_median": round(float(q50), 1), "matched_p90": round(float(q90), 1),
            "matched_p99": round(float(q99), 1),
            "matched_top5_share": round(float(np.sum(top)) / total, 3) if total > 0 else 0.0}


def _parser():
    p = argparse.ArgumentParser(description="SGM throughput (scenes/s)")
    p.add_argument("--batch", type=int, default=1000)
    p.add_argument("--sigmas", type=float, nargs="+", default=[0.0, 1.0, 3.0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--capacity", type=int, default=128)
    p.add_argument("--mag-limit", type=float, default=6.0)
    p.add_argument("--numpy-scenes", type=int, default=5,
                   help="scenes for the NumPy baseline (0: skip it)")
    p.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="SGM Config overrides, e.g. size_bucket=16 power_tol=1e-4")
    p.add_argument("--json", default=None, help="also write the rows to this file")
    return p


if __name__ == "__main__":
    js.use_cpu_cores()  # SGM's pair kernels split over every core (one JAX device each)
    a = _parser().parse_args()
    rows = run(a)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=2)
