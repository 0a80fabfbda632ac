"""Grid search of RpNet's weight-searching weights (eqs. 9–11; paper Table 5), vectorized.

The network runs once on a mixed test set (the four noise families of the paper's Figs. 8–11, one
quarter each, guide star at the boresight, random roll); every (po, pr) pair of weight triples on the
simplex (eq. 9, step ``--step``, decreasing order) is then scored in one ``vmap`` over the stored
probability tables (:func:`jstarid.algorithms.rpnet.tune.weight_grid_search`). The figure of merit is
the rate of scenes whose confident pair is correct. The best weights and Table 5's are then run
end to end on the same scenes through the sweep engine (``js.compare``, rpnet criterion).

Usage::

    python experiments/tune_rpnet.py --network quick --scenes 2000
    python experiments/tune_rpnet.py --quick                # 400 scenes, step 0.1
    python experiments/tune_rpnet.py --set pair_tol_px=null --out results/tune_rpnet_quick_paper_check

(``pair_tol_px=null``: the paper's pair check alone, eq. 10, without the observed-angle test.)

Writes results/tune_rpnet_<network>/{config.json, results.json, table.md}.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms import rpnet
from jstarid.algorithms.rpnet.tune import mixed_noise, pair_tables, simplex_grid, weight_grid_search
from jstarid.metrics import CORRECT, WRONG
from jstarid.papers import rpnet as paper

FAMILY_NAMES = ("position", "magnitude", "missing", "false")


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/tune_rpnet_<network>", seed=5,
                  quick="400 scenes, step 0.1")
    p.add_argument("--network", choices=("quick", "table3"), default="quick", help="trained network preset")
    p.add_argument("--scenes", type=int, default=2000, help="scenes in the test set (a multiple of 4)")
    p.add_argument("--step", type=float, default=0.05, help="weight grid spacing")
    args = p.parse_args(argv)
    args.out = Path(str(args.out).replace("<network>", args.network))
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    n = 400 if args.quick else args.scenes
    step = 0.1 if args.quick else args.step
    cfg = ex.with_overrides(rpnet.Config.quick() if args.network == "quick" else rpnet.Config(), args.set)
    catalog = rpnet.load_guide_catalog(cfg)
    camera = js.camera_preset(paper.CAMERA)
    db = rpnet.build_database(catalog, camera, cfg)
    noise, fam = mixed_noise(n)
    k_rows, k_sim = jax.random.split(jax.random.key(args.seed))
    rows = np.asarray(db.guide_rows)[np.asarray(jax.random.randint(k_rows, (n,), 0, db.n_classes))]
    scenes = js.simulate(k_sim, catalog, camera, noise, capacity=128, boresight_ids=rows)

    with ex.Stopwatch() as t_tables:
        tables = pair_tables(db, scenes, cfg)
    po = simplex_grid(step)
    pr = simplex_grid(step)
    with ex.Stopwatch() as t_grid:
        grid = weight_grid_search(tables["probs"], tables["pair_ok"], tables["pair_correct"], po, pr)
    table5 = weight_grid_search(tables["probs"], tables["pair_ok"], tables["pair_correct"],
                                np.asarray([paper.TABLE5_POSITION_WEIGHTS]),
                                np.asarray([paper.TABLE5_PROBABILITY_WEIGHTS]))["best"]
    corr = grid["correct"]
    flat = np.argsort(-corr, axis=None, kind="stable")[:10]
    n_tied = int(np.sum(corr == corr.max()))
    top = [{"position_weights": np.round(po[a].astype(float), 3).tolist(),
            "probability_weights": np.round(pr[b].astype(float), 3).tolist(),
            "correct": float(corr[a, b]), "wrong": float(grid["wrong"][a, b])}
           for a, b in (np.unravel_index(f, corr.shape) for f in flat)]
    # end to end with the best weights and with Table 5's, through the sweep engine on the same
    # scenes (grouped by noise family: the engine's levels are contiguous)
    weights = {"table5": (paper.TABLE5_POSITION_WEIGHTS, paper.TABLE5_PROBABILITY_WEIGHTS),
               "best": (tuple(grid["best"]["position_weights"]),
                        tuple(grid["best"]["probability_weights"]))}
    entries = [js.Entry(name, "rpnet", dataclasses.replace(cfg, position_weights=w_po,
                                                           probability_weights=w_pr))
               for name, (w_po, w_pr) in weights.items()]
    order = np.argsort(fam, kind="stable")
    swept = js.compare(scenes[order], entries, catalog, camera, level_of=fam[order],
                       levels=[{"family": f} for f in FAMILY_NAMES], criterion="rpnet", progress=False)
    codes = swept.scenes["outcome"]
    e2e = {name: {"identification_rate": float(np.mean(codes[:, k] == CORRECT)),
                  "misid_rate": float(np.mean(codes[:, k] == WRONG)),
                  "per_family": {r["family"]: r["identification_rate"] for r in swept.rows()
                                 if r["label"] == name}}
           for k, name in enumerate(weights)}
    results = {"grid_points": int(corr.size), "n_po": len(po), "n_pr": len(pr), "scenes": n,
               "tables_seconds": t_tables.seconds, "grid_seconds": t_grid.seconds, "best": grid["best"],
               "table5": table5, "top10": top, "end_to_end": e2e, "n_tied_at_best": n_tied,
               "pair_tol_px": cfg.pair_tol_px,
               "top1_guide_accuracy": np.mean(tables["guide_correct"], axis=0).tolist(),
               "any_pair_correct_rate": float(np.mean(np.any(tables["pair_ok"] & tables["pair_correct"], 1))),
               "po_grid": po.tolist(), "pr_grid": pr.tolist(), "correct_grid": corr.tolist()}
    text = table(results, args.network, step, cfg.pair_tol_px)
    ex.write(args.out, config={"scenes": n, "step": step, "seed": args.seed, "network": args.network,
                               "rpnet_config": cfg, "checkpoint": db.path,
                               "test_set": "quarters: position 0.2–1.6 px, magnitude 0.323–0.969, "
                                           "1–5 missing, false ratio 5–50 % (false V 0–6)"},
             results=results, table=text)
    print(text)
    return results


def table(results, network, step, pair_tol_px) -> str:
    lines = [f"# RpNet weight search, `{network}` network ({results['scenes']} scenes, grid step {step}, "
             f"{results['n_po']} × {results['n_pr']} = {results['grid_points']} settings in one vmap, "
             f"{results['grid_seconds']:.2f} s)", "",
             "Rate of scenes whose confident pair (eq. 11) names both detections correctly; pair check: "
             + ("eq. 10 only (the paper's)" if pair_tol_px is None else
                f"eq. 10 + observed angle within {pair_tol_px} px (extension)") + ".", "",
             "| weights | po | pr | pair correct % | wrong pair % | no admissible pair % |",
             "|---|---|---|---|---|---|"]
    for name, r in (("paper Table 5", results["table5"]), ("best on the grid", results["best"])):
        w_po = np.round(np.asarray(r["position_weights"], float), 3).tolist()
        w_pr = np.round(np.asarray(r["probability_weights"], float), 3).tolist()
        lines.append(f"| {name} | {w_po} | {w_pr} | {100 * r['correct']:.2f} | "
                     f"{100 * r['wrong']:.2f} | {100 * r['none']:.2f} |")
    lines += ["", f"{results['n_tied_at_best']} of {results['grid_points']} settings tie at the best rate "
              "(the first in grid order is shown). Top 10 settings:", "", "| po | pr | pair correct % |",
              "|---|---|---|"]
    lines += [f"| {t['position_weights']} | {t['probability_weights']} | {100 * t['correct']:.2f} |"
              for t in results["top10"]]
    bound = 100 * results["any_pair_correct_rate"]
    lines += ["", f"Upper bound (some admissible pair is correct): {bound:.2f} %; "
              f"top-1 accuracy of S1, S2, S3: "
              f"{', '.join(f'{100 * a:.1f} %' for a in results['top1_guide_accuracy'])}.", "",
              "End to end through the sweep engine (`js.compare`, rpnet criterion):", "",
              "| weights | identification % | mis-identification % | position | magnitude | missing | "
              "false |",
              "|---|---|---|---|---|---|---|"]
    for name, r in results["end_to_end"].items():
        pf = r["per_family"]
        lines.append(f"| {name} | {100 * r['identification_rate']:.2f} | {100 * r['misid_rate']:.2f} | "
                     + " | ".join(f"{100 * pf[k]:.2f}" for k in FAMILY_NAMES) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    js.use_cpu_cores()  # each chunk's scenes split over every core (one JAX device each)
    js.enable_compilation_cache()  # later runs skip XLA compilation (a command-line run only)
    main()
