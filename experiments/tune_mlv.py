"""MLV parameter tuning (Sensors 2021, 21, 3084, §3.1 and Fig. 5) with vectorized sweeps.

Camera ``mlv2021`` (25°×25°, 1024², V ≤ 5.5, simulation list to 6.5), random attitudes, the mlv
success criterion (≥ 3 correct and none wrong; conventions §5), identification and
mis-identification rates per level; a preset over the sweep engine (``js.engine.simulate_levels``
draws every level in one simulate call, ``js.compare`` runs the entries on the same scenes in
bounded chunks). Three parts:

- ``fig5``: identification rate vs position noise σ ∈ {0, 0.5, …, 2.5} px with magnitude σ 0.3 (the
  paper's Fig. 5 conditions, :mod:`jstarid.papers.mlv`) for Δv1/Δv2 ∈ {3e-5/3e-4, 5e-5/5e-4,
  6e-5/6e-4}, for our algorithm (``mlv``: all extensions on) and the paper's voting alone
  (``paper``: ``Config.paper()``, no vertex match, attitude or field check). The same scenes serve
  every Δv and variant (a paired comparison). Δv changes the discretization, so each pair has its
  own lookup tables (the triangle table is cached on disk and shared by all Δv).
- ``grid``: Th1 = Th2 ∈ ``--th`` × ε ∈ ``--eps`` (deg; the vertex-match side tolerance is set to ε
  too) at the ``--grid-levels`` position-noise levels, default Δv, extensions on. Th and ε are
  traced per-scene values, so the grid is one engine group that MLV's ``identify_grid`` runs as one
  batch axis (the scenes repeated once per cell): one compilation (its window shape is set by the
  largest Th) serves every (Th, ε, noise) cell.
- ``nstars``: N ∈ ``--n-stars`` at the grid levels, default Δv, Th, ε. N changes array shapes (C(N,3)
  triangles, 2^N verification subsets) and the database (brightest N stars per boresight), so it is
  NOT a batch axis: one database and one compilation per static N value (a loop).

Scenes per level: ``--quick`` 300, else ``--scenes`` (default 2,000). The full mode (2,000 per level)
simulates 12,000 scenes and identifies 72,000 (fig5) + 48,000 (grid) + 12,000 per N value.
``--set`` changes the settings every part starts from (both variants of fig5).

Usage::

    python experiments/tune_mlv.py --quick
    python experiments/tune_mlv.py                    # 2,000 scenes per level
    python experiments/tune_mlv.py --parts fig5 --variants mlv,paper --scenes 1000

Writes results/tune_mlv/{config.json, results.json, table.md, fig5.png}.
"""

from __future__ import annotations

import dataclasses
import itertools

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms import mlv
from jstarid.papers import mlv as paper


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/tune_mlv", seed=5, quick="300 scenes per level")
    p.add_argument("--scenes", type=int, default=2000, help="scenes per noise level")
    p.add_argument("--parts", default="fig5,grid,nstars")
    p.add_argument("--capacity", type=int, default=64, help="scene capacity")
    p.add_argument("--dv", default=",".join(paper.FIG5_DV), help="Δv1/Δv2 pairs (fig5)")
    p.add_argument("--levels", default=",".join(f"{v:g}" for v in paper.FIG5_LEVELS),
                   help="position σ (px), fig5")
    p.add_argument("--magnitude-sigma", type=float, default=paper.FIG5_MAGNITUDE_SIGMA,
                   help="mag (paper Fig. 5: 0.3)")
    p.add_argument("--variants", default="mlv,paper", help="fig5: mlv (ours), paper (voting only)")
    p.add_argument("--grid-levels", default="1,2.5", help="position σ (px) of grid and nstars")
    p.add_argument("--th", default="0,1,2", help="Th1 = Th2 values (bins), grid")
    p.add_argument("--eps", default="0.1,0.15,0.2,0.3", help="ε = side tolerance values (deg)")
    p.add_argument("--n-stars", default="8,10,12", help="N values (static loop)")
    return p.parse_args(argv)


def _floats(text):
    return [float(v) for v in text.split(",") if v.strip()]


def _compare(drawn, entries):
    """The engine on the drawn scenes; per entry, its rows and identify seconds."""
    result = js.compare(drawn.scenes, entries, drawn.catalog, drawn.camera, level_of=drawn.level_of,
                        levels=drawn.levels, criterion="mlv", progress=False)
    keys = ("position_sigma_px", "identification_rate", "misid_rate", "failure_rate",
            "mean_identified", "scenes")
    rows = {e.label: [{k: r[k] for k in keys} for r in result.rows() if r["label"] == e.label]
            for e in entries}
    seconds = {e.label: float(result.seconds[i].sum()) for i, e in enumerate(entries)}
    return rows, seconds


def run_fig5(args, drawn):
    """Every Δv pair of every variant on the same scenes (one engine run; Δv shapes the lookup
    tables, so each pair has its own database and identify call)."""
    entries = []
    for variant in args.variants.split(","):
        if variant not in ("mlv", "paper"):
            raise ValueError(f"unknown variant {variant!r}")
        base = ex.with_overrides(mlv.Config.paper() if variant == "paper" else mlv.Config(), args.set)
        for pair in args.dv.split(","):
            dv1, dv2 = (float(v) for v in pair.split("/"))
            entries.append(js.Entry(f"{variant} {pair}", "mlv", dataclasses.replace(base, dv1=dv1,
                                                                                 dv2=dv2)))
    rows, seconds = _compare(drawn, entries)
    out = {}
    for e in entries:
        variant, pair = e.label.split(" ")
        out.setdefault(variant, {})[pair] = {
            "rows": rows[e.label], "identify_seconds": seconds[e.label],
            "scenes_per_second": drawn.scenes.batch_size / seconds[e.label]}
        print(f"fig5 {variant} Δv {pair}: " + ", ".join(
            f"{r['position_sigma_px']}px {100 * r['identification_rate']:.2f}%"
            f"/{100 * r['misid_rate']:.2f}%" for r in rows[e.label]), flush=True)
    return out


def run_grid(args, drawn):
    """Th1 = Th2 × ε (= side tolerance) as one grid of the engine: MLV runs it as one batch (the
    scenes repeated once per cell, each copy with its own traced tolerances)."""
    base = ex.with_overrides(mlv.Config(), args.set)
    cells = list(itertools.product([int(v) for v in _floats(args.th)], _floats(args.eps)))
    entries = [js.Entry(f"th={t} eps={e:g}", "mlv",
                        dataclasses.replace(base, th1=t, th2=t, eps_deg=e, side_tol_deg=e), "grid")
               for t, e in cells]
    rows, seconds = _compare(drawn, entries)
    out = [{"th": t, "eps_deg": e, **r} for (t, e), entry in zip(cells, entries, strict=True)
           for r in rows[entry.label]]
    total = sum(seconds.values())
    print(f"grid: {len(cells)} (Th, ε) cells × {len(drawn.levels)} levels as one batch axis, "
          f"{total:.1f} s", flush=True)
    return {"rows": out, "identify_seconds": total,
            "scenes_per_second": len(cells) * drawn.scenes.batch_size / total, "n_calls": 1}


def run_nstars(args, drawn):
    """N changes shapes and the database: one entry (database, compilation) per N."""
    values = [int(v) for v in _floats(args.n_stars)]
    configs = [dataclasses.replace(ex.with_overrides(mlv.Config(), args.set), n_stars=k) for k in values]
    rows, seconds = _compare(drawn, [js.Entry(f"N={k}", "mlv", c) for k, c in zip(values, configs,
                                                                                 strict=True)])
    out, timing = [], {}
    for k, cfg in zip(values, configs, strict=True):
        triangles = mlv.build_database(drawn.catalog, drawn.camera, cfg, progress=False).n_triangles
        out += [{"n_stars": k, "db_triangles": triangles, **r} for r in rows[f"N={k}"]]
        timing[str(k)] = {"identify_seconds": seconds[f"N={k}"],
                          "scenes_per_second": drawn.scenes.batch_size / seconds[f"N={k}"]}
        print(f"N = {k}: " + ", ".join(f"{r['position_sigma_px']}px {100 * r['identification_rate']:.2f}%"
                                       f"/{100 * r['misid_rate']:.2f}%" for r in rows[f"N={k}"]),
              flush=True)
    return {"rows": out, "timing": timing}


def table(results, n, magnitude_sigma, seed) -> str:
    lines = ["# MLV tuning (mlv criterion: ≥ 3 correct, none wrong)", "",
             f"{n} scenes per level, magnitude σ {magnitude_sigma}, seed "
             f"{seed}; cells are identification % / mis-identification %.", ""]
    if "fig5" in results:
        lines += ["## Fig. 5: identification vs position noise for Δv1/Δv2", "",
                  f"Paper: {paper.FIG5_NOTE}.", ""]
        for variant, by_dv in results["fig5"].items():
            name = ("ours (all extensions)" if variant == "mlv"
                    else "paper's voting and verification only")
            levels = [r["position_sigma_px"] for r in next(iter(by_dv.values()))["rows"]]
            lines += [f"### {name} (`{variant}`)", "",
                      "| Δv1/Δv2 | " + " | ".join(f"{lv} px" for lv in levels) + " | scenes/s |",
                      "|---|" + "---|" * (len(levels) + 1)]
            for pair, res in by_dv.items():
                cells = [f"{100 * r['identification_rate']:.2f} / {100 * r['misid_rate']:.2f}"
                         for r in res["rows"]]
                lines.append(f"| {pair} | " + " | ".join(cells)
                             + f" | {res['scenes_per_second']:.0f} |")
            lines.append("")
    if "grid" in results:
        g = results["grid"]
        levels = sorted({r["position_sigma_px"] for r in g["rows"]})
        lines += ["## Th1 = Th2 × ε (deg; side tolerance = ε), Δv 5e-5/5e-4, N = 10", "",
                  f"The whole grid as one batch axis ({g['identify_seconds']:.1f} s, "
                  f"{g['scenes_per_second']:.0f} scenes/s, compilation included).", "",
                  "| Th | ε (deg) | " + " | ".join(f"{lv} px" for lv in levels) + " |",
                  "|---|---|" + "---|" * len(levels)]
        for (th, eps), rows in itertools.groupby(g["rows"], key=lambda r: (r["th"], r["eps_deg"])):
            by = {r["position_sigma_px"]: r for r in rows}
            lines.append(f"| {th} | {eps} | " + " | ".join(
                f"{100 * by[lv]['identification_rate']:.2f} / {100 * by[lv]['misid_rate']:.2f}"
                for lv in levels) + " |")
        lines.append("")
    if "nstars" in results:
        r_all = results["nstars"]["rows"]
        levels = sorted({r["position_sigma_px"] for r in r_all})
        lines += ["## N brightest stars (static: one database and compilation per N)", "",
                  "| N | triangles | " + " | ".join(f"{lv} px" for lv in levels) + " | scenes/s |",
                  "|---|---|" + "---|" * (len(levels) + 1)]
        for n_stars, rows in itertools.groupby(r_all, key=lambda r: r["n_stars"]):
            rows = list(rows)
            by = {r["position_sigma_px"]: r for r in rows}
            sps = results["nstars"]["timing"][str(n_stars)]["scenes_per_second"]
            lines.append(f"| {n_stars} | {rows[0]['db_triangles']:,} | " + " | ".join(
                f"{100 * by[lv]['identification_rate']:.2f} / {100 * by[lv]['misid_rate']:.2f}"
                for lv in levels) + f" | {sps:.0f} |")
        lines.append("")
    lines += ["scenes/s: identify only, compilation included (the sweep engine's timing).", ""]
    return "\n".join(lines)


def plot(results, path):
    """Fig. 5 from the saved results."""
    styles = {"mlv": "-", "paper": "--"}
    rates = {"identification": [], "misid": []}
    for variant, by_dv in results["fig5"].items():
        for i, (pair, res) in enumerate(by_dv.items()):  # one colour per Δv, one style per variant
            x = [r["position_sigma_px"] for r in res["rows"]]
            label = f"{'ours' if variant == 'mlv' else 'paper voting'} Δv {pair}"
            style = "os^dv<>"[i % 7] + styles.get(variant, ":")
            for rate, series in rates.items():
                series.append(js.plotting.Series(x, [100 * r[f"{rate}_rate"] for r in res["rows"]],
                                                 label, style, color=f"C{i}"))
    xlabel = "position noise σ (px), magnitude σ 0.3"
    js.plotting.save_panels([
        js.plotting.Panel(rates["identification"], xlabel=xlabel, ylabel="identification rate (%)",
                          title="MLV Fig. 5: identification vs Δv1/Δv2"),
        js.plotting.Panel(rates["misid"], xlabel=xlabel, ylabel="mis-identification rate (%)",
                          title="mis-identification", legend=False)], path)


def main(argv=None) -> dict:
    args = parse_args(argv)
    n = 300 if args.quick else args.scenes
    parts = args.parts.split(",")
    catalog = js.load_catalog(paper.MAG_LIMIT)
    camera = js.camera_preset(paper.CAMERA)
    levels = _floats(args.levels)
    grid_levels = _floats(args.grid_levels)
    results, timing = {}, {}

    def simulate(seed, sigmas):  # all noise levels: one batched simulate call
        drawn = js.engine.simulate_levels(camera, axes={"position_sigma_px": sigmas},
                                          fixed={"magnitude_sigma": args.magnitude_sigma}, scenes=n,
                                          seed=seed, catalog=catalog, capacity=args.capacity)
        return drawn, drawn.settings["simulate_seconds"]

    if "fig5" in parts:
        drawn, timing["simulate_fig5_seconds"] = simulate(args.seed, levels)
        results["fig5"] = run_fig5(args, drawn)
    if "grid" in parts or "nstars" in parts:
        drawn, timing["simulate_grid_seconds"] = simulate(args.seed + 1, grid_levels)
        if "grid" in parts:
            results["grid"] = run_grid(args, drawn)
        if "nstars" in parts:
            results["nstars"] = run_nstars(args, drawn)
    config = {"args": vars(args), "scenes_per_level": n, "seed": args.seed,
              "mlv_config": ex.with_overrides(mlv.Config(), args.set), "catalog": catalog.fingerprint,
              "catalog_settings": catalog.settings, "camera": camera, "timing": timing}
    text = table(results, n, args.magnitude_sigma, args.seed)
    ex.write(args.out, config=config, results=results, table=text,
             figures={"fig5.png": plot} if "fig5" in results else None)
    print(text)
    return results


if __name__ == "__main__":
    js.use_cpu_cores()  # each chunk's scenes split over every core (one JAX device each)
    js.enable_compilation_cache()  # later runs skip XLA compilation (a command-line run only)
    main()
