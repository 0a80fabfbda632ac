"""Reproduce the MLV paper's noise sweeps (Sensors 2021, 21, 3084, Figs. 6–8) with jstarid.

A preset over the sweep engine (:mod:`jstarid.papers.reproduction`, the same runs as ``jstarid
reproduce mlv``) with the paper's camera ``mlv2021`` (25°×25°, 1024², V ≤ 5.5, simulation list to
6.5), random attitudes (conventions §3 mode a) and the mlv criterion (≥ 3 correct, none wrong;
conventions §5). The sweeps are :mod:`jstarid.papers.mlv`'s:

- fig6: position σ 0–2.5 px (step 0.5), magnitude σ 0.3;
- fig7: magnitude σ 0–0.7 (step 0.1), position σ 1 px;
- fig8: 0–6 false stars of V 3.5–5.5, position σ 1 px, magnitude σ 0.3.

Usage::

    python experiments/reproduce_mlv.py --quick          # 200 scenes per level
    python experiments/reproduce_mlv.py --scenes 10000   # the paper's 10,000 per level
    python experiments/reproduce_mlv.py --quick --paper  # the paper's algorithm alone
    python experiments/reproduce_mlv.py --quick --set th1=2 th2=2 eps_deg=0.3 side_tol_deg=0.3

Writes results/reproduce_mlv/{table.md, fig6.png, fig7.png, fig8.png} and each sweep's engine
results under results/reproduce_mlv/mlv/<sweep>/.
"""

from __future__ import annotations

import functools

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms import mlv
from jstarid.papers import mlv as paper
from jstarid.papers import reproduction


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


def plot(name, results, path):
    """Sweep ``name``'s rates and the paper's quoted values, from the saved results."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = results["sweeps"][name]
    field = paper.SWEEPS[name].field
    x = [r[field] for r in rows]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(x, [100 * r["identification_rate"] for r in rows], "o-", label="jstarid MLV: identification")
    ax.plot(x, [100 * r["misid_rate"] for r in rows], "s--", label="jstarid MLV: mis-identification")
    quoted = paper.PAPER[name]["values"]
    ax.plot(list(quoted), list(quoted.values()), "k*", ms=10, label="paper (quoted values)")
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
    chosen = args.sweeps.split(",")
    results, text = {"sweeps": {}}, ["# MLV reproduction (mlv criterion: ≥ 3 correct, none wrong)", ""]
    for experiment in reproduction.experiments("mlv"):
        if experiment.name not in chosen:
            continue
        sweep = reproduction.run(experiment, args.out, scenes=n, seed=args.seed, config=cfg,
                                 capacity=args.capacity)
        rows = sweep.rows()
        results["sweeps"][experiment.name] = rows
        text.append(reproduction.comparison(experiment, rows))
        print(experiment.name, [(r[experiment.axis], round(100 * r["identification_rate"], 2),
                                 round(100 * r["misid_rate"], 2)) for r in rows], flush=True)
    config = {"scenes_per_level": n, "seed": args.seed, "sweeps": args.sweeps, "capacity": args.capacity,
              "paper": args.paper, "mlv_config": cfg}
    ex.write(args.out, config=config, results=results, table="\n".join(text),
             figures={f"{name}.png": functools.partial(plot, name) for name in results["sweeps"]})
    print("\n".join(text))
    return results


if __name__ == "__main__":
    js.use_cpu_cores()  # each chunk's scenes split over every core (one JAX device each)
    js.enable_compilation_cache()  # later runs skip XLA compilation (a command-line run only)
    main()
