"""Reproduce the SGM paper's three simulation experiments (You et al. 2022, Table 2, Figs. 6–8).

The scenes and levels are :mod:`jstarid.papers.sgm`'s: each database star is the boresight ("main
star") of a scene in mode (b) on the sgm2022 camera; position noise σ = 0 … 3 px, the same plus 1
lost star, the same plus 1 fake star (uniform over the image, conventions §7 pitfall 3 — we report
how many fakes land inside the neighbor circle). Per level: accuracy (eq. 9), identification,
failure and mis-identification rates; per experiment: MA, stdA, RA (max − min) and ALN (accuracy at
3 px) next to the paper's Table 2, and the *naming ceiling* (``jstarid.ceiling``): the share of
scenes in which an oracle that knows the attitude and the stars present would name every star of
the neighbor circle correctly from positions alone — no position-only identifier does better, so
with at most 2 % failures no accuracy can exceed ceiling / 0.98.

A preset over the sweep engine: each level is one :func:`jstarid.compare` call on the paper's
scenes (its main stars taken in order, not drawn at random as ``jstarid reproduce sgm`` does), saved
as an engine result under ``<out>/levels/<experiment>_<σ>/`` (``table.md``, ``scenes.npz`` with
every scene's outcome, …) beside what the engine does not measure (``extras.json``: the naming
ceiling and false stars inside the circle). A rerun with the same settings and the same jstarid
code picks a stored level up instead of recomputing it, so a full-size run (hours on a CPU) can be
stopped and resumed.

    python experiments/reproduce_sgm.py --quick          # a few stars per level, minutes on a CPU
    python experiments/reproduce_sgm.py                  # every database star (≈5,070 per level)
    python experiments/reproduce_sgm.py --n-stars 200 --set verify.retries=0
    python experiments/reproduce_sgm.py --quick --paper  # the paper's algorithm alone

Writes results/reproduce_sgm/{config.json, results.json, table.md, accuracy.png}.
"""

from __future__ import annotations

import ast
import hashlib
import json
from pathlib import Path

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms import sgm
from jstarid.ceiling import accuracy_bound, naming_ceiling
from jstarid.papers import sgm as paper

MAX_FAILURE = 0.02  # the failure budget, used for the accuracy ceiling
OTHER_ALGORITHMS = ("mlv", "rpnet")  # packages under jstarid/algorithms/ that SGM never imports


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/reproduce_sgm", seed=0,
                  quick="20 main stars per level, σ ∈ {0, 1.5, 3}")
    p.add_argument("--paper", action="store_true",
                   help="start from Config.paper(): the paper's algorithm alone")
    p.add_argument("--n-stars", type=int, default=None, help="main stars per level (default all)")
    p.add_argument("--sigmas", type=float, nargs="+", default=None, help="position σ (px), default 0 … 3")
    p.add_argument("--experiments", nargs="+", default=list(paper.EXPERIMENTS), choices=paper.EXPERIMENTS)
    p.add_argument("--batch", type=int, default=paper.BATCH, help="scenes per identify call")
    return p.parse_args(argv)


def _fake_inside(scenes, cam, radius_deg):
    """(B,) bool: a false star lies inside the main star's neighbor circle."""
    inside = np.asarray(js.metrics.in_neighbor_circle(scenes, cam, radius_deg))
    return np.any(inside & (np.asarray(scenes.truth) < 0), axis=1)


def _code_fingerprint(package: Path | None = None) -> str:
    """Hash of what the jstarid sources compute: a stored level made by other code is recomputed,
    not reused.

    Each module is hashed as its syntax tree without docstrings (comments never reach the tree), so
    an edit to the documentation alone keeps an hour of stored levels valid, while any change to
    the code itself, a constant included, invalidates them. The other algorithms' packages
    (:data:`OTHER_ALGORITHMS`) and their papers' definitions (``jstarid/papers/<name>.py``) are left
    out: the SGM pipeline does not run them.
    """
    digest = hashlib.sha256()
    root = Path(js.__file__).parent if package is None else package
    skip = [root / "algorithms" / name for name in OTHER_ALGORITHMS]
    skip += [root / "papers" / f"{name}.py" for name in OTHER_ALGORITHMS]
    for path in sorted(root.rglob("*.py")):
        if any(path.is_relative_to(d) for d in skip):
            continue
        tree = ast.parse(path.read_bytes())
        for node in ast.walk(tree):
            body = getattr(node, "body", None)
            if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                    and body and isinstance(body[0], ast.Expr)
                    and isinstance(body[0].value, ast.Constant)
                    and isinstance(body[0].value.value, str)):
                node.body = body[1:] or [ast.Pass()]
        digest.update(str(path.relative_to(root)).encode())
        digest.update(ast.dump(tree).encode())
    return digest.hexdigest()[:16]


def _level_scenes(args, cat, cam, rows, exp, sigma):
    """The level's scenes (the paper's main stars in order, :func:`jstarid.papers.sgm.level_scenes`),
    joined on the host into one (R, N) batch."""
    parts = [s for _, s in paper.level_scenes(cat, cam, rows, exp, sigma, seed=args.seed,
                                              batch=args.batch)]
    return jax.tree.map(lambda *a: np.concatenate([np.asarray(x) for x in a]), *parts)


def _run_level(args, scfg, cat, cam, rows, exp, sigma, out: Path) -> None:
    """One (experiment, σ) level through the engine (:func:`jstarid.compare`), saved under ``out``
    with what the engine does not measure: the naming ceiling and false stars inside the circle."""
    scenes = _level_scenes(args, cat, cam, rows, exp, sigma)
    level = {"position_sigma_px": float(sigma), "n_missing": int(exp == "lost"),
             "n_false": int(exp == "fake")}
    result = js.compare(scenes, [js.Entry("sgm", "sgm", scfg)], cat, cam, levels=[level],
                        criterion="sgm", chunk_size=args.batch, progress=False,
                        settings={"camera": cam, "experiment": exp, "seed": args.seed,
                                  "boresight": "stars", "criterion": "sgm"})
    ceiling, confident, fake_in = [], [], []
    for a in range(0, scenes.batch_size, args.batch):
        part = scenes[a:a + args.batch]
        ceiling.append(naming_ceiling(part, cat, cam, radius_deg=scfg.radius_deg))
        confident.append(naming_ceiling(part, cat, cam, radius_deg=scfg.radius_deg,
                                        margin_nats=scfg.verify.ambiguity_k ** 2, sigma_px=sigma))
        fake_in.append(_fake_inside(part, cam, scfg.radius_deg))
    result.save(out, title=f"SGM {exp}, σ = {sigma:g} px")
    extras = {"ceiling_rate": float(np.mean(np.concatenate(ceiling))),
              "ceiling_at_margin_rate": float(np.mean(np.concatenate(confident))),
              "fake_inside_circle_rate": float(np.mean(np.concatenate(fake_in)))}
    (out / "extras.json").write_text(json.dumps(extras))


def _level_row(exp, sigma, out: Path) -> dict:
    """The per-level row of the tables, from a stored level (engine row + extras)."""
    row = js.load_sweep(out).rows()[0]
    n = row["scenes"]
    return {"experiment": exp, "sigma_px": float(sigma), "n_scenes": n,
            "accuracy": float("nan") if row["accuracy"] is None else row["accuracy"],
            "identification_rate": row["identification_rate"], "failure_rate": row["failure_rate"],
            "misid_rate": row["misid_rate"], "incomplete_rate": row["n_incomplete"] / n,
            "boresight_err_arcsec_median": row["boresight_err_arcsec_median"],
            **json.loads((out / "extras.json").read_text()), "seconds": row["seconds"]}


def _summary(levels) -> dict:
    """Table 2's MA, stdA, RA, ALN (%) of one experiment's levels, and the same for the ceiling."""
    acc = np.array([lv["accuracy"] for lv in levels]) * 100
    bound = accuracy_bound([lv["ceiling_rate"] for lv in levels], MAX_FAILURE) * 100
    return {"MA": float(np.mean(acc)), "stdA": float(np.std(acc)), "RA": float(np.max(acc) - np.min(acc)),
            "ALN": float(acc[-1]), "ALN_sigma_px": levels[-1]["sigma_px"],
            "MA_ceiling": float(np.mean(bound)), "ALN_ceiling": float(bound[-1])}


def main(argv=None) -> dict:
    args = parse_args(argv)
    n_stars = 20 if args.quick and args.n_stars is None else args.n_stars
    sigmas = args.sigmas or ((0.0, 1.5, 3.0) if args.quick else paper.SIGMAS)
    (args.out / "levels").mkdir(parents=True, exist_ok=True)
    cat = js.load_catalog(paper.MAG_LIMIT)
    cam = js.camera_preset(paper.CAMERA)
    scfg = ex.with_overrides(sgm.Config.paper() if args.paper else sgm.Config(), args.set)
    db = sgm.build_database(cat, cam, scfg)  # built here to report its size (the engine loads it)
    rows = paper.main_star_rows(len(cat), n_stars, args.seed)
    code = _code_fingerprint()
    results = {"levels": [], "database": {"stars": len(db), "capacity": db.capacity,
                                          "bytes": db.nbytes, "seconds": db.build_seconds}}
    for exp in args.experiments:
        for sigma in sigmas:
            # everything a level's numbers depend on; a stored level is reused only when this matches
            settings = {"code": code, "experiment": exp, "sigma_px": float(sigma), "seed": args.seed,
                        "batch": args.batch, "capacity": paper.CAPACITY, "camera": paper.CAMERA,
                        "catalog": cat.fingerprint, "sgm_config": ex.to_json(scfg), "rows": rows.tolist()}
            path = args.out / "levels" / f"{exp}_{sigma:.2f}"
            stored_settings = path / "settings.json"
            stored = json.loads(stored_settings.read_text()) if stored_settings.exists() else None
            if stored == settings and (path / "extras.json").exists():
                note = "stored"
            else:
                _run_level(args, scfg, cat, cam, rows, exp, sigma, path)
                stored_settings.write_text(json.dumps(settings))
                note = "computed"
            level = _level_row(exp, sigma, path)
            note = f"{level['seconds']:.1f}s identify, {note}"
            results["levels"].append(level)
            print(f"{exp:8s} σ={sigma:.1f}px  acc={level['accuracy']:.4f} "
                  f"id={level['identification_rate']:.4f} fail={level['failure_rate']:.4f} "
                  f"misid={level['misid_rate']:.4f} ceiling={level['ceiling_rate']:.4f}  ({note})",
                  flush=True)
    results["summary"] = {exp: _summary([lv for lv in results["levels"] if lv["experiment"] == exp])
                          for exp in args.experiments}
    table = _table(results, args.seed)
    config = {"seed": args.seed, "n_stars": n_stars, "sigmas": sigmas, "experiments": args.experiments,
              "batch": args.batch, "capacity": paper.CAPACITY, "camera": paper.CAMERA,
              "mag_limit": paper.MAG_LIMIT, "paper": args.paper, "sgm_config": scfg,
              "catalog": cat.fingerprint, "rows": rows.tolist() if n_stars else "all"}
    ex.write(args.out, config=config, results=results, table=table, figures={"accuracy.png": _plot})
    print(table)
    return results


def _table(results, seed) -> str:
    lines = [f"# SGM reproduction ({results['levels'][0]['n_scenes']} scenes per level, seed {seed})", "",
             f"Ceiling: the best any position-only identifier could reach with ≤ {MAX_FAILURE:.0%} "
             "failures (`jstarid.ceiling`); per level, the ceiling of the identification rate and, "
             "at margin, the same for a namer that withholds names below the verification's "
             "ambiguity margin (`verify.ambiguity_k`², nats, with the true σ).", "",
             "| experiment | metric | ours (%) | paper (%) | ceiling (%) |", "|---|---|---|---|---|"]
    for exp, s in results["summary"].items():
        for m in ("MA", "stdA", "RA", "ALN"):
            bound = f"{s[m + '_ceiling']:.2f}" if m + "_ceiling" in s else "–"
            lines.append(f"| {exp} | {m} | {s[m]:.2f} | {paper.PAPER[exp][m]:.2f} | {bound} |")
    lines += ["", "| experiment | σ (px) | accuracy | identification | failure | misid | incomplete |"
              " ceiling | ceiling at margin | fake in circle |", "|---|---|---|---|---|---|---|---|---|---|"]
    for lv in results["levels"]:
        lines.append(f"| {lv['experiment']} | {lv['sigma_px']:.1f} | {lv['accuracy']:.4f} | "
                     f"{lv['identification_rate']:.4f} | {lv['failure_rate']:.4f} | "
                     f"{lv['misid_rate']:.4f} | {lv['incomplete_rate']:.4f} | "
                     f"{lv['ceiling_rate']:.4f} | {lv['ceiling_at_margin_rate']:.4f} | "
                     f"{lv['fake_inside_circle_rate']:.3f} |")
    return "\n".join(lines) + "\n"


def _plot(results, path):
    """Accuracy per level and, dashed, its ceiling; from the saved results."""
    series = []
    for k, exp in enumerate(results["summary"]):
        lv = [x for x in results["levels"] if x["experiment"] == exp]
        sigma = [x["sigma_px"] for x in lv]
        series += [js.plotting.Series(sigma, [None if x["accuracy"] is None else 100 * x["accuracy"]
                                              for x in lv], exp, "o-", color=f"C{k}"),
                   js.plotting.Series(sigma, 100 * accuracy_bound([x["ceiling_rate"] for x in lv],
                                                                  MAX_FAILURE),
                                      None, "--", color=f"C{k}", alpha=0.6)]
    js.plotting.save_panels([js.plotting.Panel(
        series, xlabel="position noise σ (px)", ylabel="accuracy, eq. 9 (%)",
        title="SGM on sgm2022, V ≤ 6 (mode b); dashed: ceiling")], path, size=(6.0, 4.0))


if __name__ == "__main__":
    js.enable_compilation_cache()  # later runs skip XLA compilation (a command-line run only)
    js.use_cpu_cores()  # SGM's pair kernels split over every core (one JAX device each)
    main()
