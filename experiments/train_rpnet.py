"""Train (or load) the RpNet networks for the rpnet2019 camera and report held-out accuracy.

Usage::

    python experiments/train_rpnet.py --network quick        # ≈ 10 min on 2 CPU cores, smoke scale
    python experiments/train_rpnet.py --network table3        # Table 3 scale (GPU)
    python experiments/train_rpnet.py --network quick --dae-steps 50 --clf-steps 50 --no-cache

``--seed`` is the training seed (``Training.seed``); ``--dae-steps``, ``--clf-steps``,
``--batch-size`` and ``--pool-batches`` change the training schedule, ``--set`` the other
:class:`~jstarid.algorithms.rpnet.Config` fields. Writes
results/train_rpnet_<network>/{config.json, results.json} and caches the checkpoint under
``jstarid.catalog.cache_dir() / "rpnet"`` (unless ``--no-cache``).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms import rpnet
from jstarid.papers import rpnet as paper


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/train_rpnet_<network>", seed=0)
    p.add_argument("--network", choices=("quick", "table3"), default="quick", help="training preset")
    p.add_argument("--dae-steps", type=int, default=None)
    p.add_argument("--clf-steps", type=int, default=None)
    p.add_argument("--batch-size", type=int, default=None)
    p.add_argument("--pool-batches", type=int, default=None)
    p.add_argument("--eval-scenes", type=int, default=512, help="identification scenes after training")
    p.add_argument("--no-cache", action="store_true")
    args = p.parse_args(argv)
    args.out = Path(str(args.out).replace("<network>", args.network))
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    cfg = ex.with_overrides(rpnet.Config.quick() if args.network == "quick" else rpnet.Config(), args.set)
    schedule = {k: v for k, v in (("dae_steps", args.dae_steps), ("clf_steps", args.clf_steps),
                                  ("batch_size", args.batch_size), ("pool_batches", args.pool_batches))
                if v is not None}
    cfg = dataclasses.replace(cfg, training=dataclasses.replace(cfg.training, seed=args.seed, **schedule))
    cat = rpnet.load_guide_catalog(cfg)
    cam = js.camera_preset(paper.CAMERA)

    with ex.Stopwatch() as clock:
        db = rpnet.build_database(cat, cam, cfg, use_cache=not args.no_cache)
    results = {"n_classes": db.n_classes, "build_seconds": clock.seconds, "checkpoint": db.path}
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
        with ex.Stopwatch() as clock:
            res = rpnet.identify(db, scenes)
            res.ids.block_until_ready()
        rep = js.evaluate(scenes, res, "rpnet", camera=cam)
        rep["identify_seconds"] = clock.seconds
        results["identification_position_0.5px"] = rep
        print({k: rep[k] for k in ("identification_rate", "misid_rate", "failure_rate")})
    ex.write(args.out, config={"rpnet_config": cfg, "catalog": cat.settings, "camera": cam.name,
                               "fingerprint": cfg.fingerprint()}, results=results)
    summary = {k: v for k, v in ex.to_json(results).items() if k not in ("dae_eval", "clf_eval")}
    print(json.dumps(summary, indent=1)[:2000])
    return results


if __name__ == "__main__":
    js.enable_compilation_cache()  # later runs skip XLA compilation (a command-line run only)
    main()
