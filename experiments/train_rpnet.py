"""Train (or load) the RpNet networks for the rpnet2019 camera and report held-out accuracy.

Usage::

    python experiments/train_rpnet.py --config quick        # ≈ 10 min on 2 CPU cores, smoke scale
    python experiments/train_rpnet.py --config paper        # Table 3 scale (GPU)
    python experiments/train_rpnet.py --config quick --dae-steps 50 --clf-steps 50 --no-cache

Writes ``results/train_rpnet_<config>/{config.json, results.json}`` and caches the checkpoint under
``jstarid.catalog.cache_dir() / "rpnet"`` (unless ``--no-cache``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np

import jstarid as js
from jstarid.algorithms import rpnet


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", choices=("quick", "paper"), default="quick")
    ap.add_argument("--dae-steps", type=int, default=None)
    ap.add_argument("--clf-steps", type=int, default=None)
    ap.add_argument("--batch-size", type=int, default=None)
    ap.add_argument("--pool-batches", type=int, default=None)
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--eval-scenes", type=int, default=512, help="identification scenes after training")
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)

    cfg = rpnet.Config.quick() if args.config == "quick" else rpnet.Config()
    overrides = {k: v for k, v in (("dae_steps", args.dae_steps), ("clf_steps", args.clf_steps),
                                   ("batch_size", args.batch_size), ("pool_batches", args.pool_batches),
                                   ("seed", args.seed)) if v is not None}
    cfg = dataclasses.replace(cfg, training=dataclasses.replace(cfg.training, **overrides))
    cat = rpnet.load_guide_catalog(cfg)
    cam = js.camera_preset("rpnet2019")
    out = args.out or Path("results") / f"train_rpnet_{args.config}"
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps({"config": dataclasses.asdict(cfg), "catalog": cat.settings,
                                                 "camera": cam.name, "fingerprint": cfg.fingerprint()},
                                                indent=2, default=str))

    t0 = time.perf_counter()
    db = rpnet.build_database(cat, cam, cfg, cache=not args.no_cache)
    train_s = time.perf_counter() - t0
    results = {"n_classes": db.n_classes, "build_seconds": train_s, "checkpoint": str(db.path)}
    if db.history is not None:
        h = db.history
        results.update(dae_eval=h["dae_eval"], clf_eval=h["clf_eval"],
                       best_held_out_accuracy=h["best_held_out_accuracy"],
                       final_dae_loss=float(np.mean(h["dae_loss"][-50:])),
                       final_clf_loss=float(np.mean(h["clf_loss"][-50:])))

    if args.eval_scenes:
        rng = np.random.default_rng(12345)
        rows = rng.choice(db.guide_rows, args.eval_scenes)
        noise = js.NoiseConfig(position_sigma_px=0.5)
        scenes = js.simulate(jax.random.key(12345), cat, cam, noise, capacity=96, boresight_ids=rows)
        t0 = time.perf_counter()
        res = rpnet.identify(db, scenes)
        res.ids.block_until_ready()
        rep = js.evaluate(scenes, res, "rpnet", camera=cam)
        rep["identify_seconds"] = time.perf_counter() - t0
        results["identification_position_0.5px"] = rep
        print({k: rep[k] for k in ("identification_rate", "misid_rate", "failure_rate")})
    (out / "results.json").write_text(json.dumps(results, indent=2, default=str))
    print(json.dumps({k: v for k, v in results.items() if k not in ("dae_eval", "clf_eval")}, indent=1,
                     default=str)[:2000])


if __name__ == "__main__":
    js.enable_compilation_cache()  # later runs skip XLA compilation (a command-line run only)
    main()
