"""MLV parameter tuning (Sensors 2021, 21, 3084, §3.1 and Fig. 5) with vectorized sweeps.

Camera ``mlv2021`` (25°×25°, 1024², V ≤ 5.5, simulation list to 6.5), random attitudes, the mlv
success criterion (≥ 3 correct and none wrong; conventions §5), identification and
mis-identification rates per level. Three parts:

- ``fig5``: identification rate vs position noise σ ∈ {0, 0.5, …, 2.5} px with magnitude σ 0.3 (the
  paper's Fig. 5 conditions, :mod:`jstarid.papers.mlv`) for Δv1/Δv2 ∈ {3e-5/3e-4, 5e-5/5e-4,
  6e-5/6e-4}, for our algorithm (``mlv``: all extensions on) and the paper's voting alone
  (``paper``: ``Config.paper()``, no vertex match, attitude or field check). All noise levels are
  ONE batched ``js.simulate`` call over ``js.noise_grid``; the same scenes serve every Δv and
  variant (a paired comparison). Δv changes the discretization, so the lookup tables are built once
  per Δv pair (the triangle table is cached on disk and shared by all Δv) and reused for every
  noise level.
- ``grid``: Th1 = Th2 ∈ ``--th`` × ε ∈ ``--eps`` (deg; the vertex-match side tolerance is set to ε
  too) at the ``--grid-levels`` position-noise levels, default Δv, extensions on. Th and ε are
  traced per-scene values (``identify(..., tuning=mlv.Tuning(th1, th2, eps_rad, side_tol_rad))``), so
  the whole grid is one batch axis: ONE ``identify`` call and one compilation (its window shape is
  set by the largest Th) serve every (Th, ε, noise) cell.
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

import jax
import jax.numpy as jnp
import numpy as np

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


def _rates(scenes, result, diag, lo, hi):
    rep = js.evaluate(scenes[lo:hi], result[lo:hi], "mlv")
    return {"identification_rate": rep["identification_rate"], "misid_rate": rep["misid_rate"],
            "failure_rate": rep["failure_rate"], "mean_identified": rep["mean_identified"],
            "candidate_overflow_rate": float(np.mean(np.asarray(diag.candidate_overflow)[lo:hi])),
            "n_scenes": rep["n_scenes"]}


def _identify_timed(db, scenes, cfg, tuning=None):
    with ex.Stopwatch() as clock:
        result, diag = mlv.identify(db, scenes, cfg, diagnostics=True, tuning=tuning)
        result.ids.block_until_ready()
    return result, diag, clock.seconds


def _tile(scenes, times: int):
    """The batch repeated ``times`` times along the batch axis (a new batch axis for tuning)."""
    return jax.tree_util.tree_map(lambda a: jnp.concatenate([a] * times), scenes)


def run_fig5(args, catalog, camera, scenes, levels, n, databases):
    out = {}
    for variant in args.variants.split(","):
        if variant not in ("mlv", "paper"):
            raise ValueError(f"unknown variant {variant!r}")
        base = ex.with_overrides(mlv.Config.paper() if variant == "paper" else mlv.Config(), args.set)
        out[variant] = {}
        for pair in args.dv.split(","):
            dv1, dv2 = (float(v) for v in pair.split("/"))
            cfg = dataclasses.replace(base, dv1=dv1, dv2=dv2)
            with ex.Stopwatch() as clock:
                db = mlv.build_database(catalog, camera, cfg, progress=False)  # once per Δv
            databases[pair] = {**db.info_dict(), "seconds": clock.seconds}
            result, diag, seconds = _identify_timed(db, scenes, cfg)
            rows = [{"position_sigma_px": lv, **_rates(scenes, result, diag, i * n, (i + 1) * n)}
                    for i, lv in enumerate(levels)]
            out[variant][pair] = {"rows": rows, "identify_seconds": seconds,
                                  "scenes_per_second": scenes.batch_size / seconds,
                                  "candidate_capacity_used": diag.capacity}
            print(f"fig5 {variant} Δv {pair}: " + ", ".join(
                f"{r['position_sigma_px']}px {100 * r['identification_rate']:.2f}%"
                f"/{100 * r['misid_rate']:.2f}%" for r in rows) + f" ({seconds:.1f} s)", flush=True)
    return out


def run_grid(args, catalog, camera, scenes, levels, n):
    """One identify call over the Cartesian grid (Th × ε) × noise levels × scenes."""
    cfg = ex.with_overrides(mlv.Config(), args.set)
    db = mlv.build_database(catalog, camera, cfg, progress=False)
    grid = list(itertools.product([int(v) for v in _floats(args.th)], _floats(args.eps)))
    s = scenes.batch_size
    th = np.repeat([g[0] for g in grid], s)  # (G·S,) per-scene values, grid cell outermost
    eps = np.repeat([g[1] for g in grid], s)
    tiled = _tile(scenes, len(grid))
    eps_rad = np.deg2rad(eps.astype(np.float32))
    tuning = mlv.Tuning(th1=th, th2=th, eps_rad=eps_rad, side_tol_rad=eps_rad)
    result, diag, seconds = _identify_timed(db, tiled, cfg, tuning)
    rows = []
    for g, (t, e) in enumerate(grid):
        for i, lv in enumerate(levels):
            lo = g * s + i * n
            rows.append({"th": t, "eps_deg": e, "position_sigma_px": lv,
                         **_rates(tiled, result, diag, lo, lo + n)})
    print(f"grid: {len(grid)} (Th, ε) cells × {len(levels)} levels × {n} scenes in one call, "
          f"{seconds:.1f} s", flush=True)
    return {"rows": rows, "identify_seconds": seconds,
            "scenes_per_second": tiled.batch_size / seconds, "n_calls": 1}


def run_nstars(args, catalog, camera, scenes, levels, n, databases):
    rows, timing = [], {}
    for n_stars in (int(v) for v in _floats(args.n_stars)):
        cfg = dataclasses.replace(ex.with_overrides(mlv.Config(), args.set), n_stars=n_stars)
        with ex.Stopwatch() as clock:
            db = mlv.build_database(catalog, camera, cfg, progress=False)
        databases[f"N={n_stars}"] = {**db.info_dict(), "seconds": clock.seconds}
        result, diag, seconds = _identify_timed(db, scenes, cfg)
        timing[str(n_stars)] = {"identify_seconds": seconds,
                           "scenes_per_second": scenes.batch_size / seconds}
        for i, lv in enumerate(levels):
            rows.append({"n_stars": n_stars, "position_sigma_px": lv,
                         "db_triangles": db.n_triangles,
                         **_rates(scenes, result, diag, i * n, (i + 1) * n)})
        print(f"N = {n_stars}: " + ", ".join(
            f"{r['position_sigma_px']}px {100 * r['identification_rate']:.2f}%"
            f"/{100 * r['misid_rate']:.2f}%" for r in rows if r["n_stars"] == n_stars)
            + f" ({seconds:.1f} s)", flush=True)
    return {"rows": rows, "timing": timing}


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
                  f"One identify call over the whole grid ({g['identify_seconds']:.1f} s, "
                  f"{g['scenes_per_second']:.0f} scenes/s, compile included).", "",
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
    lines += ["scenes/s: identify only, compile included.", ""]
    return "\n".join(lines)


def plot(results, path):
    """Fig. 5 from the saved results."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    styles = {"mlv": "-", "paper": "--"}
    for variant, by_dv in results["fig5"].items():
        for i, (pair, res) in enumerate(by_dv.items()):  # one colour per Δv, one style per variant
            x = [r["position_sigma_px"] for r in res["rows"]]
            label = f"{'ours' if variant == 'mlv' else 'paper voting'} Δv {pair}"
            style = dict(color=f"C{i}", marker="os^dv<>"[i % 7], label=label,
                         linestyle=styles.get(variant, ":"))
            ax1.plot(x, [100 * r["identification_rate"] for r in res["rows"]], **style)
            ax2.plot(x, [100 * r["misid_rate"] for r in res["rows"]], **style)
    ax1.set_ylabel("identification rate (%)")
    ax2.set_ylabel("mis-identification rate (%)")
    for ax in (ax1, ax2):
        ax.set_xlabel("position noise σ (px), magnitude σ 0.3")
        ax.grid(alpha=0.3)
    ax1.legend(fontsize=7)
    ax1.set_title("MLV Fig. 5: identification vs Δv1/Δv2")
    ax2.set_title("mis-identification")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> dict:
    args = parse_args(argv)
    n = 300 if args.quick else args.scenes
    parts = args.parts.split(",")
    catalog = js.load_catalog(paper.MAG_LIMIT)
    camera = js.camera_preset(paper.CAMERA)
    key_fig5, key_grid = jax.random.split(jax.random.key(args.seed))
    levels = _floats(args.levels)
    grid_levels = _floats(args.grid_levels)
    databases, results, timing = {}, {}, {}

    def simulate(key, sigmas):  # all noise levels: one batched simulate call
        with ex.Stopwatch() as clock:
            scenes = js.simulate(key, catalog, camera,
                                 js.noise_grid(n, position_sigma_px=sigmas,
                                               magnitude_sigma=args.magnitude_sigma),
                                 batch_size=n * len(sigmas), capacity=args.capacity)
        return scenes, clock.seconds

    if "fig5" in parts:
        scenes, timing["simulate_fig5_seconds"] = simulate(key_fig5, levels)
        results["fig5"] = run_fig5(args, catalog, camera, scenes, levels, n, databases)
    if "grid" in parts or "nstars" in parts:
        scenes, timing["simulate_grid_seconds"] = simulate(key_grid, grid_levels)
        if "grid" in parts:
            results["grid"] = run_grid(args, catalog, camera, scenes, grid_levels, n)
        if "nstars" in parts:
            results["nstars"] = run_nstars(args, catalog, camera, scenes, grid_levels, n, databases)
    config = {"args": vars(args), "scenes_per_level": n, "seed": args.seed,
              "mlv_config": ex.with_overrides(mlv.Config(), args.set), "catalog": catalog.fingerprint,
              "catalog_settings": catalog.settings, "camera": camera, "databases": databases,
              "timing": timing}
    text = table(results, n, args.magnitude_sigma, args.seed)
    ex.write(args.out, config=config, results=results, table=text,
             figures={"fig5.png": plot} if "fig5" in results else None)
    print(text)
    return results


if __name__ == "__main__":
    js.use_cpu_cores()  # each chunk's scenes split over every core (one JAX device each)
    js.enable_compilation_cache()  # later runs skip XLA compilation (a command-line run only)
    main()
