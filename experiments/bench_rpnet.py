"""RpNet throughput: identification scenes/s at batch ≥ 4,096 and training samples/s of both stages.

``run(args)`` returns rows like ``experiments/bench_mlv.py`` (``benchmark``, ``scenes_per_s``,
``compile_s``, ``peak_rss_mb`` and details) so that ``experiments/benchmark.py`` can call it with its
own namespace (it reads ``batch`` and ``repeats``; a batch below 4,096 is raised to 4,096 for RpNet and
the row says so), or from the command line::

    python experiments/bench_rpnet.py                       # quick checkpoint, batch 4096
    python experiments/bench_rpnet.py --config paper --batch 8192
    python experiments/bench_rpnet.py --precision both      # bfloat16 and float32 network, same scenes

Rows:

* ``rpnet``: ``rpnet.identify`` on mode-(b) ``rpnet2019`` scenes (guide star at the boresight, position
  σ 0.5 px), median of ``repeats`` timed calls after a first (compiling) call; compile time is the
  first call minus the steady call. ``network_scenes_per_s`` times the network part alone (three
  inputs → logits → top-3) for reference. With ``--precision both`` the row is measured twice, as
  ``rpnet_bf16`` and ``rpnet_f32`` (``Config.network_bf16`` on and off), on the same scenes.
* ``rpnet_train_dae`` / ``rpnet_train_clf``: jit-compiled train steps of stage 1 (denoising
  autoencoder) and stage 2 (classifier on frozen codes) at the config's batch size, on a pre-drawn
  batch (``samples_per_s``) and with a fresh on-the-fly batch per step (``samples_per_s_with_data``,
  the rate a training run sees).

Needs a trained checkpoint for the config (``experiments/train_rpnet.py --config quick``); a missing
one is trained first (minutes for ``quick``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

import jstarid as js
from jstarid.algorithms import rpnet
from jstarid.algorithms.rpnet import data as rp_data
from jstarid.algorithms.rpnet import train as rp_train
from jstarid.algorithms.rpnet.model import use_bf16

MIN_BATCH = 4096


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--config", choices=("quick", "paper"), default="quick")
    p.add_argument("--batch", type=int, default=MIN_BATCH, help=f"scenes per timed call (≥ {MIN_BATCH})")
    p.add_argument("--repeats", type=int, default=3, help="timed calls after the compile call")
    p.add_argument("--position-sigma", type=float, default=0.5, help="px")
    p.add_argument("--train-steps", type=int, default=5, help="timed train steps per stage (0: skip)")
    p.add_argument("--precision", choices=("config", "both"), default="config",
                   help="network matmuls: the config's (Config.network_bf16), or both bfloat16 and "
                        "float32 side by side on the same scenes (rows rpnet_bf16 and rpnet_f32)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--devices", type=int, default=None,
                   help="JAX CPU devices (default: one per core; 1 keeps each chunk on one device)")
    p.add_argument("--json", default=None, help="write the rows here")
    return p.parse_args(argv)


def _rss_mb() -> int:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


def _timed(fn, repeats):
    """(first-call seconds, median of ``repeats`` further calls) of ``fn(i)``."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(0))
    first = time.perf_counter() - t0
    times = []
    for i in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(i + 1))
        times.append(time.perf_counter() - t0)
    return first, float(np.median(times))


def bench_identify(db, catalog, camera, cfg, opt, name: str = "rpnet") -> dict:
    """One row named ``name``: identify scenes/s at batch ``opt['batch']``."""
    batch = opt["batch"]
    rng = np.random.default_rng(opt["seed"])
    noise = js.NoiseConfig(position_sigma_px=opt["position_sigma"])
    sets = []
    for i in range(opt["repeats"] + 1):
        rows = rng.choice(db.guide_rows, batch)
        sets.append(js.simulate(jax.random.key(opt["seed"] + i), catalog, camera, noise, capacity=96,
                                boresight_ids=rows))
    jax.block_until_ready(sets[-1].xy)
    results = {}

    def call(i):
        results[i] = rpnet.identify(db, sets[i], cfg)
        return results[i].ids

    first, steady = _timed(call, opt["repeats"])
    reports = [js.evaluate(sets[i], results[i], "rpnet", camera=camera) for i in range(1, opt["repeats"] + 1)]

    # the network part alone: three central detections → inputs → logits → top-3 (one jit)
    from jstarid.algorithms.rpnet.identify import network_candidates

    def net(i):
        s = sets[i]
        return network_candidates(s.xy, s.valid, db.inference_weights, camera=camera, config=cfg,
                                  n_classes=db.n_classes)

    net_first, net_steady = _timed(net, opt["repeats"])
    return {
        "benchmark": name, "camera": camera.name,
        "network_bf16": use_bf16(cfg.network_bf16),
        "config": opt["config"], "batch": batch,
        "batch_note": opt.get("batch_note", ""),
        "noise": f"pos {opt['position_sigma']} px, guide at boresight",
        "scenes_per_s": round(batch / steady), "compile_s": round(max(first - steady, 0.0), 2),
        "peak_rss_mb": _rss_mb(), "backend": jax.default_backend(), "batch_chunk": cfg.batch_chunk,
        "seconds_per_batch": round(steady, 3), "first_call_s": round(first, 2),
        "network_scenes_per_s": round(batch / net_steady),
        "network_compile_s": round(net_first - net_steady, 2),
        "n_classes": db.n_classes,
        "identification_rate": float(np.mean([r["identification_rate"] for r in reports])),
        "misid_rate": float(np.mean([r["misid_rate"] for r in reports])),
    }


def bench_train(db, catalog, camera, cfg, opt) -> list[dict]:
    """Two rows: stage-1 and stage-2 train steps per second at the config's batch size."""
    t = cfg.training
    n_classes = db.n_classes
    tables = rp_data.build_tables(catalog, camera, cfg, db.guide_rows)
    bs = t.batch_size
    key = jax.random.key(opt["seed"])
    batches = [rp_data.make_batch(jax.random.fold_in(key, i), catalog, camera, cfg, tables, bs)
               for i in range(2)]
    jax.block_until_ready(batches[-1].noisy)
    n = opt["train_steps"]
    variables = jax.tree_util.tree_map(jnp.asarray, db.variables)
    rows = []

    # stage 1: DAE
    tx = optax.adam(t.dae_lr)
    params = {"generator": variables["generator"], "decoder": variables["decoder"]}
    state = [params, tx.init(params)]
    step, _ = rp_train._make_dae_step(cfg, n_classes, tx)

    def dae(i, fresh=False):
        b = (rp_data.make_batch(jax.random.fold_in(key, 100 + i), catalog, camera, cfg, tables, bs)
             if fresh else batches[i % 2])
        state[0], state[1], mse = step(state[0], state[1], b.noisy, b.clean)
        return mse

    rows.append(_train_row("rpnet_train_dae", dae, n, bs, opt))

    # stage 2: classifier on frozen generator codes
    lr = optax.cosine_decay_schedule(t.clf_lr, 1000, alpha=0.01) if t.clf_lr_decay else t.clf_lr
    tx = optax.adam(lr)
    clf = variables["classifier"]
    state2 = [clf["params"], clf["batch_stats"], tx.init(clf["params"])]
    step2 = rp_train._make_clf_step(cfg, n_classes, tx)

    def clf_fn(i, fresh=False):
        b = (rp_data.make_batch(jax.random.fold_in(key, 200 + i), catalog, camera, cfg, tables, bs)
             if fresh else batches[i % 2])
        state2[0], state2[1], state2[2], ce = step2(state2[0], state2[1], state2[2], variables["generator"],
                                                    b.noisy, b.label)
        return ce

    rows.append(_train_row("rpnet_train_clf", clf_fn, n, bs, opt))
    return rows


def _train_row(name, fn, n, bs, opt) -> dict:
    t0 = time.perf_counter()
    jax.block_until_ready(fn(0))
    first = time.perf_counter() - t0
    jax.block_until_ready(fn(1, True))  # compile the data path too
    t0 = time.perf_counter()
    for i in range(n):
        out = fn(i)
    jax.block_until_ready(out)
    per_step = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    for i in range(n):
        out = fn(i + 2, True)
    jax.block_until_ready(out)
    per_step_data = (time.perf_counter() - t0) / n
    return {"benchmark": name, "config": opt["config"], "batch": bs, "steps_timed": n,
            "scenes_per_s": round(bs / per_step), "samples_per_s": round(bs / per_step),
            "samples_per_s_with_data": round(bs / per_step_data),
            "steps_per_s": round(1 / per_step, 2), "steps_per_s_with_data": round(1 / per_step_data, 2),
            "compile_s": round(max(first - per_step, 0.0), 2), "peak_rss_mb": _rss_mb()}


def run(args) -> list[dict]:
    """Benchmark RpNet on the rpnet2019 camera; returns the identify row and the two training rows.

    Args:
        args: namespace; reads ``config``, ``batch``, ``repeats``, ``position_sigma``, ``train_steps``,
            ``seed`` where present (this file's defaults otherwise). A ``batch`` below 4,096 is raised
            to 4,096 (RpNet's benchmark batch) and the row notes it.

    Returns:
        List of row dicts (see the module docstring).
    """
    defaults = vars(parse_args([]))
    opt = {k: getattr(args, k, v) for k, v in defaults.items()}
    if opt["batch"] < MIN_BATCH:
        opt["batch_note"] = f"batch {opt['batch']} raised to {MIN_BATCH} for rpnet"
        print(f"(rpnet: {opt['batch_note']})", flush=True)
        opt["batch"] = MIN_BATCH
    cfg = rpnet.Config.quick() if opt["config"] == "quick" else rpnet.Config()
    catalog = rpnet.load_guide_catalog(cfg)
    camera = js.camera_preset("rpnet2019")
    db = rpnet.build_database(catalog, camera, cfg, progress=False)
    if opt["precision"] == "both":
        rows = []
        for bf16 in (True, False):
            rows.append(bench_identify(db, catalog, camera,
                                       dataclasses.replace(cfg, network_bf16=bf16), opt,
                                       name="rpnet_bf16" if bf16 else "rpnet_f32"))
            print(rows[-1], flush=True)
    else:
        rows = [bench_identify(db, catalog, camera, cfg, opt)]
        print(rows[-1], flush=True)
    if opt["train_steps"]:
        train_rows = bench_train(db, catalog, camera, cfg, opt)
        for r in train_rows:
            print(r, flush=True)
        rows += train_rows
    return rows


if __name__ == "__main__":
    a = parse_args()
    js.use_cpu_cores(a.devices)  # each chunk's scenes split over every core (one JAX device each)
    out = run(a)
    print(json.dumps(out, indent=1))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=2)
