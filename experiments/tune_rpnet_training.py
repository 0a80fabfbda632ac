"""RpNet training grid: seeds × learning rates (× classifier widths), trained side by side in one vmap.

For each classifier width (a loop: the shapes differ), every (seed, DAE rate, classifier rate) of the
product trains at once with :func:`jstarid.algorithms.rpnet.train_grid` — one vmapped step per batch,
the batch drawn once for all members. Each member is then scored on held-out training samples
(top-1 guide accuracy per noise family) and end to end: ``rpnet.identify`` on the mixed test set of
``experiments/tune_rpnet.py`` (:func:`~jstarid.algorithms.rpnet.tune.mixed_noise`: one quarter per
noise family of Figs. 8–11). ``--time-single`` also trains the first member alone with
:func:`~jstarid.algorithms.rpnet.train.train` (the same network) to compare the grid's wall time with
G separate runs. ``--seed`` draws the test scenes; ``--seeds`` are the members' training seeds.

Usage::

    python experiments/tune_rpnet_training.py --dae-lrs 3e-4 1e-3 3e-3 --clf-lrs 1e-3 3e-3
    python experiments/tune_rpnet_training.py --seeds 0 1 2 --clf-widths 256 512 --time-single
    python experiments/tune_rpnet_training.py --quick     # 50 + 50 steps, 200 scenes: a smoke run

Writes results/tune_rpnet_training/{config.json, results.json, table.md, held_out.png}.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms import rpnet
from jstarid.algorithms.rpnet import train as rp_train
from jstarid.algorithms.rpnet.data import FAMILIES
from jstarid.algorithms.rpnet.tune import mixed_noise
from jstarid.papers import rpnet as paper


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/tune_rpnet_training", seed=5,
                  quick="50 + 50 steps, 200 scenes")
    p.add_argument("--network", choices=("quick", "table3"), default="quick", help="the base training preset")
    p.add_argument("--seeds", type=int, nargs="+", default=None, help="init seeds (default: the config's)")
    p.add_argument("--dae-lrs", type=float, nargs="+", default=None, help="stage-1 rates (default: config)")
    p.add_argument("--clf-lrs", type=float, nargs="+", default=None, help="stage-2 rates (default: config)")
    p.add_argument("--clf-widths", type=int, nargs="+", default=None,
                   help="classifier hidden widths, one vmapped group each (default: the config's)")
    p.add_argument("--dae-steps", type=int, default=None)
    p.add_argument("--clf-steps", type=int, default=None)
    p.add_argument("--scenes", type=int, default=None,
                   help="end-to-end test scenes (multiple of 4; 0: skip; default 2000, 200 with --quick)")
    p.add_argument("--time-single", action="store_true", help="also train the first member alone")
    return p.parse_args(argv)


def _base_config(args) -> rpnet.Config:
    cfg = ex.with_overrides(rpnet.Config.quick() if args.network == "quick" else rpnet.Config(), args.set)
    t = cfg.training
    dae, clf = (50, 50) if args.quick else (args.dae_steps, args.clf_steps)
    t = dataclasses.replace(t, dae_steps=t.dae_steps if dae is None else dae,
                            clf_steps=t.clf_steps if clf is None else clf,
                            eval_every=25 if args.quick else t.eval_every)
    return dataclasses.replace(cfg, training=t)


def _end_to_end(db, scenes, fam, camera) -> dict:
    res = rpnet.identify(db, scenes)
    rep = js.evaluate(scenes, res, "rpnet", camera=camera)
    per_family = {name: js.evaluate(scenes[np.nonzero(fam == f)[0]], res[np.nonzero(fam == f)[0]], "rpnet",
                                    camera=camera)["identification_rate"] for f, name in enumerate(FAMILIES)}
    return {"identification_rate": rep["identification_rate"], "misid_rate": rep["misid_rate"],
            "per_family": per_family}


def plot(results, path):
    """Each member's held-out accuracy during classifier training, from the saved results."""
    series = [js.plotting.Series(
        r["held_out_curve"]["steps"], [100 * a for a in r["held_out_curve"]["accuracy"]],
        f"w {r['clf_width']}, seed {r['seed']}, lr {r['dae_lr']:.0e}/{r['clf_lr']:.0e}", ".-")
        for r in results["members"]]
    js.plotting.save_panels([js.plotting.Panel(
        series, xlabel="classifier step", ylabel="held-out top-1 guide accuracy (%)",
        title="RpNet training grid (DAE / classifier learning rates)")], path, size=(7.0, 4.5))


def table(results, network, t, n_scenes) -> str:
    groups = results["groups"]
    lines = [f"# RpNet training grid, `{network}` base ({results['dae_steps']} DAE + {results['clf_steps']} "
             f"classifier steps at batch {t.batch_size}; {groups[0]['members']} members per width, one "
             "vmapped step)", "",
             f"End to end: {n_scenes} scenes, one quarter per noise family (`tune_rpnet.py`'s test set).", "",
             "| width | seed | DAE lr | clf lr | held-out MSE | held-out acc % | pos / mag / miss / false % "
             "| identified % | misid % |", "|---|---|---|---|---|---|---|---|---|"]
    for r in results["members"]:
        fam_acc = " / ".join(f"{100 * r['held_out_per_family'][f]:.1f}" for f in FAMILIES)
        e2e = r.get("end_to_end", {})
        lines.append(f"| {r['clf_width']} | {r['seed']} | {r['dae_lr']:g} | {r['clf_lr']:g} | "
                     f"{r['held_out_mse']:.5f} | {100 * r['best_held_out_accuracy']:.2f} | {fam_acc} | "
                     f"{100 * e2e.get('identification_rate', np.nan):.2f} | "
                     f"{100 * e2e.get('misid_rate', np.nan):.3f} |")
    lines += [""] + [f"Width {g['width']}: the grid of {g['members']} took {g['seconds']:.0f} s."
                     for g in groups]
    return "\n".join(lines) + "\n"


def main(argv=None) -> list[dict]:
    args = parse_args(argv)
    cfg = _base_config(args)
    t = cfg.training
    catalog = rpnet.load_guide_catalog(cfg)
    camera = js.camera_preset(paper.CAMERA)
    rows = rpnet.guide_rows(catalog, cfg)
    seeds, dae_lrs, clf_lrs = rpnet.grid_members(
        seeds=args.seeds or (t.seed,), dae_lrs=args.dae_lrs or (t.dae_lr,),
        clf_lrs=args.clf_lrs or (t.clf_lr,))
    widths = args.clf_widths or (cfg.clf_width,)
    n_scenes = args.scenes if args.scenes is not None else (200 if args.quick else 2000)
    scenes = fam = None
    if n_scenes:
        noise, fam = mixed_noise(n_scenes)
        k_rows, k_sim = jax.random.split(jax.random.key(args.seed))
        boresight = np.asarray(rows)[np.asarray(jax.random.randint(k_rows, (n_scenes,), 0, len(rows)))]
        scenes = js.simulate(k_sim, catalog, camera, noise, capacity=128, boresight_ids=boresight)
    dae_steps, clf_steps = t.steps(len(rows))

    members, groups = [], []
    for width in widths:
        cfg_w = dataclasses.replace(cfg, clf_width=int(width))
        grid = rpnet.train_grid(catalog, camera, cfg_w, rows, seeds=seeds, dae_lrs=dae_lrs, clf_lrs=clf_lrs)
        groups.append({"width": int(width), "members": int(grid.size), "seconds": grid.seconds})
        samples = grid.size * (dae_steps + clf_steps) * t.batch_size
        print(f"width {width}: {grid.size} members in {grid.seconds:.1f} s "
              f"({samples / grid.seconds:,.0f} member-samples/s)", flush=True)
        single_s = None
        if args.time_single:
            first = dataclasses.replace(t, seed=int(seeds[0]), dae_lr=float(dae_lrs[0]),
                                        clf_lr=float(clf_lrs[0]))
            with ex.Stopwatch() as clock:
                rp_train.train(catalog, camera, dataclasses.replace(cfg_w, training=first), rows,
                               progress=False)
            single_s = clock.seconds
            print(f"  one member alone (train): {single_s:.1f} s; the grid took "
                  f"{grid.seconds / single_s:.2f}× that for {grid.size} members", flush=True)
        for g in range(grid.size):
            row = {"clf_width": int(width), "seed": int(seeds[g]), "dae_lr": float(dae_lrs[g]),
                   "clf_lr": float(clf_lrs[g]), "held_out_mse": float(grid.dae_eval[-1, g]),
                   "best_held_out_accuracy": float(grid.best_accuracy[g]),
                   "held_out_per_family": dict(zip(FAMILIES, grid.clf_eval_family[
                       int(np.argmax(grid.clf_eval[:, g])), g].astype(float).tolist(), strict=True)),
                   "held_out_curve": {"steps": np.asarray(grid.clf_eval_steps).tolist(),
                                      "accuracy": np.asarray(grid.clf_eval[:, g], float).tolist()},
                   "grid_seconds": grid.seconds, "single_seconds": single_s}
            if scenes is not None:
                db = rpnet.database_from_variables(catalog, camera, cfg_w, rpnet.member_variables(grid, g))
                row["end_to_end"] = _end_to_end(db, scenes, fam, camera)
            members.append(row)
            e2e = row.get("end_to_end", {})
            print(f"  seed {row['seed']} lr {row['dae_lr']:.0e}/{row['clf_lr']:.0e}: held-out "
                  f"{100 * row['best_held_out_accuracy']:.2f} %, identified "
                  f"{100 * e2e.get('identification_rate', np.nan):.2f} %, misid "
                  f"{100 * e2e.get('misid_rate', np.nan):.3f} %", flush=True)
    results = {"members": members, "groups": groups, "dae_steps": dae_steps, "clf_steps": clf_steps}
    text = table(results, args.network, t, n_scenes)
    ex.write(args.out, config={"args": vars(args), "rpnet_config": cfg, "members_per_width": int(seeds.size),
                               "widths": list(widths), "dae_steps": dae_steps, "clf_steps": clf_steps,
                               "devices": str(jax.devices())},
             results=results, table=text, figures={"held_out.png": plot})
    print(text)
    return members


if __name__ == "__main__":
    # one device with every core: the grid's batched products use them all (as train_rpnet.py does)
    js.enable_compilation_cache()
    main()
