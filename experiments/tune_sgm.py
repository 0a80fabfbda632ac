"""SGM parameter experiments (You et al. 2022, Figs. 11–13), vectorized over the parameter grid.

Fig. 11: how far the image graph's MST weight w_I moves from the database w_J of the true main star
under position noise (σ = 0 … 3 px) — the Δw the rough search must reach. Figs. 12–13: accuracy
(eq. 9) and failure rate against the matching-error threshold ε_δ at σ = 3 px, for several values
of the affinity adjustor c. The grid is a ``js.grid`` of the sweep engine run by ``js.compare``, which
SGM's ``identify_grid`` serves with one computation: the spectral matching runs once per (candidate,
c) with c as a ``vmap`` axis, and Algorithm 1's stop rule is replayed for every ε_δ on the stored
errors (``jstarid.algorithms.sgm.tuning``). The paper's algorithm alone (``Config.paper()``, no
verification; ``--set`` changes it; with verification on, each grid point is its own search).

    python experiments/tune_sgm.py --quick        # 30 main stars, minutes on a CPU
    python experiments/tune_sgm.py --scenes 300   # default 200 main stars

Writes results/tune_sgm/{config.json, results.json, table.md, fig11_dw.png, fig12_13_eps.png}.
"""

from __future__ import annotations

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms import sgm
from jstarid.algorithms.sgm.graph import searchable_graphs
from jstarid.papers import sgm as paper


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/tune_sgm", seed=11, quick="30 main stars")
    p.add_argument("--scenes", type=int, default=None, help="main stars (default 200)")
    p.add_argument("--sigma", type=float, default=3.0, help="noise of the ε_δ sweep (px)")
    p.add_argument("--cs", type=float, nargs="+", default=[0.5, 1.0, 1.74, 3.0, 5.0], help="values of c")
    p.add_argument("--eps", type=float, nargs="+", default=[0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
                   help="values of ε_δ (deg)")
    return p.parse_args(argv)


def delta_w(cat, cam, db, cfg, rows, sigmas, key):
    """Fig. 11: w_I − w_J(true main star) per σ, one batched simulation over every level (deg)."""
    noise = js.noise_grid(rows.size, position_sigma_px=list(sigmas))
    scenes = js.simulate(key, cat, cam, noise, capacity=paper.CAPACITY,
                         boresight_ids=np.tile(rows, len(sigmas)))
    g, usable = searchable_graphs(db, scenes, cfg)
    w_true = np.empty(len(cat), np.float32)
    w_true[db.main] = db.w
    dw = (g.w - w_true[np.tile(rows, len(sigmas))]).reshape(len(sigmas), rows.size)
    return dw, usable.reshape(len(sigmas), rows.size)


def main(argv=None) -> dict:
    args = parse_args(argv)
    n = args.scenes or (30 if args.quick else 200)
    cat = js.load_catalog(paper.MAG_LIMIT)
    cam = js.camera_preset(paper.CAMERA)
    base = ex.with_overrides(sgm.Config.paper(), args.set)
    db = sgm.build_database(cat, cam, base)
    rows = np.sort(np.random.default_rng(args.seed).choice(len(cat), n, replace=False))
    k1, k2 = jax.random.split(jax.random.key(args.seed))

    dw, dw_ok = delta_w(cat, cam, db, base, rows, paper.SIGMAS, k1)
    fig11 = []
    for s, d, ok in zip(paper.SIGMAS, dw, dw_ok, strict=True):
        a = np.abs(d[ok])
        fig11.append({"sigma_px": float(s), "mean_abs_dw": float(a.mean()),
                      "median_abs_dw": float(np.median(a)), "p90_abs_dw": float(np.percentile(a, 90)),
                      "within_dw0": float(np.mean(a <= base.dw0_deg)),
                      "within_1deg": float(np.mean(a <= 1.0))})

    scenes = js.simulate(k2, cat, cam, js.NoiseConfig(position_sigma_px=args.sigma),
                         capacity=paper.CAPACITY, boresight_ids=rows)
    # the c × ε_δ grid through the engine: one SGM entry group, which sgm.identify_grid runs as a
    # single search (c a vmap axis of the matching, ε_δ replayed on the stored errors)
    entries = js.grid("sgm", base, c=[float(c) for c in args.cs],
                      max_error_deg=[float(e) for e in args.eps])
    swept = js.compare(scenes, entries, cat, cam, criterion="sgm", progress=False)
    grid = [{"c": r["c"], "eps_deg": r["max_error_deg"], "accuracy": r["accuracy"],
             "failure_rate": r["failure_rate"], "misid_rate": r["misid_rate"],
             "identification_rate": r["identification_rate"]} for r in swept.rows()]
    results = {"sigma_px": args.sigma, "fig11": fig11, "grid": grid,
               "grid_seconds": float(swept.seconds.sum())}
    text = table(results, n, args.seed)
    ex.write(args.out, config={"scenes": n, "seed": args.seed, "sigma_px": args.sigma, "cs": args.cs,
                               "eps": args.eps, "dw_sigmas": paper.SIGMAS, "capacity": paper.CAPACITY,
                               "sgm_config": base, "catalog": cat.fingerprint},
             results=results, table=text, figures={"fig11_dw.png": plot_dw, "fig12_13_eps.png": plot_eps})
    print(text)
    return results


def _cs(results) -> list[float]:
    return list(dict.fromkeys(r["c"] for r in results["grid"]))


def table(results, n, seed) -> str:
    eps = list(dict.fromkeys(r["eps_deg"] for r in results["grid"]))
    lines = [f"# SGM parameter sweeps ({n} main stars, seed {seed})", "",
             "## Fig. 11: |w_I − w_J| of the true main star under position noise (deg)", "",
             "| σ (px) | mean | median | 90th pct | ≤ Δw₀ = 0.1° | ≤ 1° |", "|---|---|---|---|---|---|"]
    for r in results["fig11"]:
        lines.append(f"| {r['sigma_px']:.1f} | {r['mean_abs_dw']:.3f} | {r['median_abs_dw']:.3f} | "
                     f"{r['p90_abs_dw']:.3f} | {100 * r['within_dw0']:.1f} % | "
                     f"{100 * r['within_1deg']:.1f} % |")
    lines += ["", f"## Figs. 12–13: accuracy / failure / misid (%) vs ε_δ at σ = {results['sigma_px']} px",
              "",
              "| c \\ ε_δ (deg) | " + " | ".join(f"{e:g}" for e in eps) + " |",
              "|---|" + "---|" * len(eps)]
    for c in _cs(results):
        cells = [r for r in results["grid"] if r["c"] == c]
        lines.append(f"| {c:g} | " + " | ".join(
            f"{_pct(r['accuracy'])} / {_pct(r['failure_rate'])} / {_pct(r['misid_rate'])}"
            for r in cells) + " |")
    lines += ["", f"Grid of {len(_cs(results))} c × {len(eps)} ε_δ evaluated as one search in "
              f"{results['grid_seconds']:.0f} s (compilation included)."]
    return "\n".join(lines) + "\n"


def _pct(x) -> str:
    """A rate as a percentage; accuracy (eq. 9) is undefined when every scene failed → "—"."""
    return "—" if x is None or not np.isfinite(x) else f"{100 * x:.1f}"


def plot_dw(results, path):
    """Fig. 11 from the saved results."""
    f11 = results["fig11"]
    s = [r["sigma_px"] for r in f11]
    series = [js.plotting.Series(s, [r[f"{key}_abs_dw"] for r in f11], label, style)
              for key, label, style in (("mean", "mean", "o-"), ("median", "median", "s-"),
                                        ("p90", "90th percentile", "^-"))]
    js.plotting.save_panels([js.plotting.Panel(
        series, xlabel="position noise σ (px)", ylabel="|w_I − w_J| (deg)",
        title="Fig. 11: MST weight shift under noise")], path, size=(5.5, 4.0))


def plot_eps(results, path):
    """Figs. 12–13 from the saved results."""
    accuracy, failure = [], []
    for c in _cs(results):
        cells = [r for r in results["grid"] if r["c"] == c]
        e = [r["eps_deg"] for r in cells]
        accuracy.append(js.plotting.Series(e, [None if r["accuracy"] is None else 100 * r["accuracy"]
                                               for r in cells], f"c = {c:g}"))
        failure.append(js.plotting.Series(e, [100 * r["failure_rate"] for r in cells], f"c = {c:g}"))
    js.plotting.save_panels([js.plotting.Panel(accuracy, xlabel="ε_δ (deg)", ylabel="accuracy, eq. 9 (%)"),
                             js.plotting.Panel(failure, xlabel="ε_δ (deg)", ylabel="failure rate (%)")],
                            path, title=f"Figs. 12–13: σ = {results['sigma_px']} px", size=(5.0, 4.0))


if __name__ == "__main__":
    js.enable_compilation_cache()  # later runs skip XLA compilation (a command-line run only)
    js.use_cpu_cores()  # SGM's pair kernels split over every core (one JAX device each)
    main()
