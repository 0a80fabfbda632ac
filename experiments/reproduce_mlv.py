"""Reproduce the MLV paper's noise sweeps (Sensors 2021, 21, 3084, Figs. 6–8) with jstarid.

Camera ``mlv2021`` (25°×25°, 1024², V ≤ 5.5, simulation list to 6.5), random attitudes (conventions §3
mode a), the mlv success criterion (≥ 3 correct, none wrong; conventions §5). The sweeps are
:mod:`jstarid.papers.mlv`'s; each is one batched ``js.simulate`` call over ``js.noise_grid`` levels
and one ``identify`` call:

- fig6: position σ 0–2.5 px (step 0.5), magnitude σ 0.3;
- fig7: magnitude σ 0–0.7 (step 0.1), position σ 1 px;
- fig8: 0–6 false stars of V 3.5–5.5, position σ 1 px, magnitude σ 0.3.

Usage::

    python experiments/reproduce_mlv.py --quick          # 200 scenes per level
    python experiments/reproduce_mlv.py --scenes 10000   # the paper's 10,000 per level
    python experiments/reproduce_mlv.py --quick --paper  # the paper's algorithm alone
    python experiments/reproduce_mlv.py --quick --set th1=2 th2=2 eps_deg=0.3 side_tol_deg=0.3

Writes results/reproduce_mlv/{config.json, results.json, table.md, fig6.png, fig7.png, fig8.png}.
"""

from __future__ import annotations

import functools

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms import mlv
from jstarid.papers import mlv as paper


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/reproduce_mlv", seed=2021,
                  quick="200 scenes per level")
    p.add_argument("--paper", action="store_true",
                   help="start from Config.paper(): the paper's voting and verification alone (no vertex "
                        "match, attitude or field check)")
    p.add_argument("--scenes", type=int, default=10_000, help="scenes per noise level")
    p.add_argument("--sweeps", default="fig6,fig7,fig8")
    p.add_argument("--capacity", type=int, default=64, help="scene capacity")
    return p.parse_args(argv)


def run_sweep(name, key, catalog, camera, db, cfg, n, capacity):
    sweep = paper.SWEEPS[name]
    noise = js.noise_grid(n, **{sweep.field: sweep.levels}, **sweep.fixed)
    with ex.Stopwatch() as t_sim:
        scenes = js.simulate(key, catalog, camera, noise, batch_size=n * len(sweep.levels), capacity=capacity)
    with ex.Stopwatch() as t_id:
        result, diag = mlv.identify(db, scenes, cfg, diagnostics=True)
        result.ids.block_until_ready()
    rows = []
    for i, level in enumerate(sweep.levels):
        part = slice(i * n, (i + 1) * n)
        rep = js.evaluate(scenes[part], result[part], "mlv")
        rows.append({
            "level": level,
            "identification_rate": rep["identification_rate"],
            "misid_rate": rep["misid_rate"],
            "failure_rate": rep["failure_rate"],
            "incomplete_rate": rep["incomplete_rate"],
            "mean_identified": rep["mean_identified"],
            "candidate_overflow_rate": float(np.mean(np.asarray(diag.candidate_overflow)[part])),
            "n_scenes": rep["n_scenes"],
            "paper_identification_rate": paper.PAPER[name]["values"].get(level),
        })
    return {"field": sweep.field, "fixed": sweep.fixed, "rows": rows, "simulate_seconds": t_sim.seconds,
            "identify_seconds": t_id.seconds, "scenes_per_second": n * len(sweep.levels) / t_id.seconds,
            "candidate_capacity_used": diag.capacity, "paper_note": paper.PAPER[name]["note"]}


def table(results) -> str:
    lines = ["# MLV reproduction (mlv criterion: ≥ 3 correct, none wrong)", ""]
    for name, res in results["sweeps"].items():
        lines += [f"## {name}: {paper.SWEEPS[name].label}; fixed {res['fixed']}", "",
                  f"Paper: {res['paper_note']}.", "",
                  "| level | identification % | mis-identification % | failure % | paper % |",
                  "|---|---|---|---|---|"]
        for r in res["rows"]:
            p = r["paper_identification_rate"]
            lines.append(f"| {r['level']} | {100 * r['identification_rate']:.2f} | "
                         f"{100 * r['misid_rate']:.2f} | {100 * r['failure_rate']:.2f} | "
                         f"{'' if p is None else f'{p:.2f}'} |")
        lines += ["", f"{res['rows'][0]['n_scenes']} scenes per level; identify "
                  f"{res['scenes_per_second']:.0f} scenes/s (compile included).", ""]
    return "\n".join(lines)


def plot(name, results, path):
    """Sweep ``name``'s rates and the paper's quoted values, from the saved results."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = results["sweeps"][name]["rows"]
    x = [r["level"] for r in rows]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(x, [100 * r["identification_rate"] for r in rows], "o-", label="jstarid MLV: identification")
    ax.plot(x, [100 * r["misid_rate"] for r in rows], "s--", label="jstarid MLV: mis-identification")
    quoted = [(r["level"], r["paper_identification_rate"]) for r in rows
              if r["paper_identification_rate"] is not None]
    ax.plot([q[0] for q in quoted], [q[1] for q in quoted], "k*", ms=10, label="paper (quoted values)")
    ax.set_xlabel(paper.SWEEPS[name].label)
    ax.set_ylabel("rate (%)")
    ax.set_ylim(-2, 102)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"MLV {name}")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> dict:
    args = parse_args(argv)
    n = 200 if args.quick else args.scenes
    cfg = ex.with_overrides(mlv.Config.paper() if args.paper else mlv.Config(), args.set)
    catalog = js.load_catalog(paper.MAG_LIMIT)
    camera = js.camera_preset(paper.CAMERA)
    with ex.Stopwatch() as t_db:
        db = mlv.build_database(catalog, camera, cfg)
    keys = jax.random.split(jax.random.key(args.seed), len(paper.SWEEPS))
    results = {"sweeps": {}}
    for name, key in zip(paper.SWEEPS, keys, strict=True):
        if name not in args.sweeps.split(","):
            continue
        res = run_sweep(name, key, catalog, camera, db, cfg, n, args.capacity)
        results["sweeps"][name] = res
        print(name, [(r["level"], round(100 * r["identification_rate"], 2),
                      round(100 * r["misid_rate"], 2)) for r in res["rows"]], flush=True)
    config = {"scenes_per_level": n, "seed": args.seed, "sweeps": args.sweeps, "capacity": args.capacity,
              "paper": args.paper, "mlv_config": cfg, "catalog": catalog.fingerprint,
              "catalog_settings": catalog.settings, "camera": camera, "database": db.info_dict(),
              "database_seconds": t_db.seconds}
    text = table(results)
    ex.write(args.out, config=config, results=results, table=text,
             figures={f"{name}.png": functools.partial(plot, name) for name in results["sweeps"]})
    print(text)
    return results


if __name__ == "__main__":
    js.use_cpu_cores()  # each chunk's scenes split over every core (one JAX device each)
    js.enable_compilation_cache()  # later runs skip XLA compilation (a command-line run only)
    main()
