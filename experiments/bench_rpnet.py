"""RpNet throughput: identification scenes/s at batch ≥ 4,096 and training samples/s of both stages.

    python experiments/bench_rpnet.py                       # quick checkpoint, batch 4096
    python experiments/bench_rpnet.py --network table3 --batch 8192
    python experiments/bench_rpnet.py --precision both      # bfloat16 and float32 network, same scenes
    python experiments/bench_rpnet.py --camera narrow_twin --train-steps 0  # V ≤ 10, the twin's frames

Rows (``benchmark``, ``scenes_per_s``, ``compile_s``, ``peak_rss_mb`` and details):

* ``rpnet``: ``rpnet.identify`` on mode-(b) ``rpnet2019`` scenes (guide star at the boresight, position
  σ 0.5 px; with ``--camera narrow_twin``: random attitudes, the noise and 128 detections of
  ``experiments/narrow_twin.py``, Hipparcos to V 10, ``Config.for_camera``), median of ``repeats``
  timed calls after a first (compiling) call; compile time is the
  first call minus the steady call; a batch below 4,096 is raised to 4,096 and the row says so.
  ``network_scenes_per_s`` times the network part alone (three inputs → logits → top-3) for
  reference. With ``--precision both`` the row is measured twice, as ``rpnet_bf16`` and
  ``rpnet_f32`` (``Config.network_bf16`` on and off), on the same scenes.
* ``rpnet_train_dae`` / ``rpnet_train_clf``: jit-compiled train steps of stage 1 (denoising
  autoencoder) and stage 2 (classifier on frozen codes) at the config's batch size, on a pre-drawn
  batch (``samples_per_s``) and with a fresh on-the-fly batch per step (``samples_per_s_with_data``,
  the rate a training run sees).

Needs a trained checkpoint for the config (``experiments/train_rpnet.py --network quick``); a missing
one is trained first (minutes for ``quick``). ``experiments/benchmark.py`` runs it in a subprocess
and reads its rows from ``--json``. Writes results/bench_rpnet/{config.json, results.json, table.md}.
"""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import optax

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms import rpnet
from jstarid.algorithms.rpnet import data as rp_data
from jstarid.algorithms.rpnet import train as rp_train
from jstarid.algorithms.rpnet.identify import network_candidates
from jstarid.algorithms.rpnet.model import use_bf16
from jstarid.papers import narrow_field as twin

MIN_BATCH = 4096
COLUMNS = [("benchmark", "row", "{}"), ("batch", "B", "{}"), ("scenes_per_s", "scenes (samples)/s", "{}"),
           ("compile_s", "compile s", "{}"), ("network_scenes_per_s", "network alone /s", "{}"),
           ("samples_per_s_with_data", "samples/s with data", "{}"),
           ("identification_rate", "identified", "{:.2%}"), ("misid_rate", "misid", "{:.2%}"),
           ("peak_rss_mb", "peak RSS MiB", "{}")]


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/bench_rpnet", seed=0)
    p.add_argument("--network", choices=("quick", "table3"), default="quick", help="trained network preset")
    p.add_argument("--batch", type=int, default=MIN_BATCH, help=f"scenes per timed call (≥ {MIN_BATCH})")
    p.add_argument("--repeats", type=int, default=3, help="timed calls after the compile call")
    p.add_argument("--camera", choices=("rpnet2019", "narrow_twin"), default="rpnet2019",
                   help="rpnet2019 (the paper's) or narrow_twin (random attitudes, the twin's noise)")
    p.add_argument("--position-sigma", type=float, default=None, help="px (default 0.5, twin 0.8)")
    p.add_argument("--train-steps", type=int, default=5, help="timed train steps per stage (0: skip)")
    p.add_argument("--precision", choices=("config", "both"), default="config",
                   help="network matmuls: the config's (Config.network_bf16), or both bfloat16 and "
                        "float32 side by side on the same scenes (rows rpnet_bf16 and rpnet_f32)")
    p.add_argument("--devices", type=int, default=None,
                   help="JAX CPU devices (default: one per core; 1 keeps each chunk on one device)")
    p.add_argument("--json", default=None, help="also write the rows to this file")
    return p.parse_args(argv)


def make_config(args) -> rpnet.Config:
    training = rpnet.Training.quick() if args.network == "quick" else rpnet.Training()
    base = rpnet.Config.for_camera(js.camera_preset(args.camera), training=training)
    return ex.with_overrides(base, args.set)


def position_sigma(args) -> float:
    """The rpnet2019 rows' centroid noise (px)."""
    return 0.5 if args.position_sigma is None else args.position_sigma


def draw_scenes(key, rows, catalog, camera, args, batch: int):
    """One timed batch: mode (b) on the guide ``rows`` (rpnet2019), random attitudes (narrow twin)."""
    if args.camera == "narrow_twin":
        noise = dict(twin.NOISE)
        if args.position_sigma is not None:
            noise["position_sigma_px"] = args.position_sigma
        return js.simulate(key, catalog, camera, js.NoiseConfig(**noise), batch_size=batch,
                           capacity=twin.CAPACITY)
    sigma = position_sigma(args)
    return js.simulate(key, catalog, camera, js.NoiseConfig(position_sigma_px=sigma), capacity=96,
                       boresight_ids=rows)


def bench_identify(db, catalog, camera, cfg, args, batch: int, note: str, name: str = "rpnet") -> dict:
    """One row named ``name``: identify scenes/s at batch ``batch``."""
    rng = np.random.default_rng(args.seed)
    sets = []
    for i in range(args.repeats + 1):
        rows = rng.choice(db.guide_rows, batch)
        sets.append(draw_scenes(jax.random.key(args.seed + i), rows, catalog, camera, args, batch))
    jax.block_until_ready(sets[-1].xy)
    results = {}

    def call(i):
        results[i] = rpnet.identify(db, sets[i], cfg)
        return results[i].ids

    first, steady = ex.time_call(call, args.repeats)
    reports = [js.evaluate(sets[i], results[i], "rpnet", camera=camera) for i in range(1, args.repeats + 1)]

    def net(i):  # the network part alone: three central detections → inputs → logits → top-3 (one jit)
        s = sets[i]
        return network_candidates(s.xy, s.valid, db.inference_weights, camera=camera, config=cfg,
                                  n_classes=db.n_classes, mag=s.mag)

    net_first, net_steady = ex.time_call(net, args.repeats)
    return {
        "benchmark": name, "camera": camera.name, "network_bf16": use_bf16(cfg.network_bf16),
        "config": args.network, "batch": batch, "batch_note": note,
        "noise": (f"the twin's ({twin.NOISE}), random attitudes" if args.camera == "narrow_twin" else
                  f"pos {position_sigma(args)} px, guide at boresight"),
        "scenes_per_s": round(batch / steady), "compile_s": round(max(first - steady, 0.0), 2),
        "peak_rss_mb": round(ex.peak_rss_mb()), "backend": jax.default_backend(),
        "batch_chunk": cfg.batch_chunk, "seconds_per_batch": round(steady, 3),
        "first_call_s": round(first, 2),
        "network_scenes_per_s": round(batch / net_steady),
        "network_compile_s": round(net_first - net_steady, 2), "n_classes": db.n_classes,
        "identification_rate": float(np.mean([r["identification_rate"] for r in reports])),
        "misid_rate": float(np.mean([r["misid_rate"] for r in reports])),
    }


def bench_train(db, catalog, camera, cfg, args) -> list[dict]:
    """Two rows: stage-1 and stage-2 train steps per second at the config's batch size."""
    t = cfg.training
    n_classes = db.n_classes
    tables = rp_data.build_tables(catalog, camera, cfg, db.guide_rows)
    bs = t.batch_size
    key = jax.random.key(args.seed)
    batches = [rp_data.make_batch(jax.random.fold_in(key, i), catalog, camera, cfg, tables, bs)
               for i in range(2)]
    jax.block_until_ready(batches[-1].noisy)
    variables = jax.tree_util.tree_map(jnp.asarray, db.variables)

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

    rows = [_train_row("rpnet_train_dae", dae, bs, args)]

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

    rows.append(_train_row("rpnet_train_clf", clf_fn, bs, args))
    return rows


def _train_row(name, fn, bs, args) -> dict:
    n = args.train_steps
    with ex.Stopwatch() as first:
        jax.block_until_ready(fn(0))
    jax.block_until_ready(fn(1, True))  # compile the data path too
    with ex.Stopwatch() as fixed:
        jax.block_until_ready([fn(i) for i in range(n)][-1])
    with ex.Stopwatch() as fresh:
        jax.block_until_ready([fn(i + 2, True) for i in range(n)][-1])
    per_step, per_step_data = fixed.seconds / n, fresh.seconds / n
    return {"benchmark": name, "config": args.network, "batch": bs, "steps_timed": n,
            "scenes_per_s": round(bs / per_step), "samples_per_s": round(bs / per_step),
            "samples_per_s_with_data": round(bs / per_step_data),
            "steps_per_s": round(1 / per_step, 2), "steps_per_s_with_data": round(1 / per_step_data, 2),
            "compile_s": round(max(first.seconds - per_step, 0.0), 2), "peak_rss_mb": round(ex.peak_rss_mb())}


def run(args) -> list[dict]:
    """Benchmark RpNet on one camera: the identify row(s) and the two training rows."""
    batch, note = args.batch, ""
    if batch < MIN_BATCH:
        note = f"batch {batch} raised to {MIN_BATCH} for rpnet"
        print(f"(rpnet: {note})", flush=True)
        batch = MIN_BATCH
    cfg = make_config(args)
    camera = js.camera_preset(args.camera)
    twin_camera = args.camera == "narrow_twin"
    catalog = js.load_catalog(twin.MAG_LIMIT) if twin_camera else rpnet.load_guide_catalog(cfg)
    db = rpnet.build_database(catalog, camera, cfg, progress=False)
    if args.precision == "both":
        variants = [(dataclasses.replace(cfg, network_bf16=bf16), "rpnet_bf16" if bf16 else "rpnet_f32")
                    for bf16 in (True, False)]
    else:
        variants = [(cfg, "rpnet")]
    rows = []
    for c, name in variants:
        rows.append(bench_identify(db, catalog, camera, c, args, batch, note, name=name))
        print(rows[-1], flush=True)
    if args.train_steps:
        for r in bench_train(db, catalog, camera, cfg, args):
            print(r, flush=True)
            rows.append(r)
    return rows


def main(argv=None) -> list[dict]:
    args = parse_args(argv)
    rows = run(args)
    print(json.dumps(rows, indent=1))
    ex.dump_json(args.json, rows)
    ex.write(args.out, config={"args": vars(args), "rpnet_config": make_config(args)}, results={"rows": rows},
             table=ex.markdown_table(rows, COLUMNS,
                                     title=f"RpNet throughput (`{args.network}` network, {args.camera})"))
    return rows


if __name__ == "__main__":
    js.use_cpu_cores(parse_args().devices)  # each chunk's scenes split over every core (one JAX device each)
    main()
