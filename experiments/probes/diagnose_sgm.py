"""Why SGM scenes are not correct: the outcomes of one level of ``reproduce_sgm.py``, broken down.

The scenes are the reproduction's own (:mod:`jstarid.papers.sgm`: same main stars, keys and
batches), so a figure quoted from a full-size or sampled run can be looked at scene by scene. Per
level it reports the outcome counts, the correct scenes that needed the search to go on after a
rejected match (``Config.verify.retries``), each failure's cause, and every mis-identified detection
with its distances (px, through the true attitude) to the star it was named after and to its own
star::

    python experiments/probes/diagnose_sgm.py --experiment lost --sigma 0 --n-stars 800
    python experiments/probes/diagnose_sgm.py --experiment lost --sigma 2.5 --batches 3  # rows 768–1023
    python experiments/probes/diagnose_sgm.py --experiment lost --sigma 0 --n-stars 800 --set verify.retries=0

Failure causes (from ``identify(..., diagnostics=True)``): ``unusable`` (too few stars, or overflow),
``no δ ≤ ε_δ`` (Algorithm 1 found no match), ``main star contested`` (the match passed every test but
a close rival star contests the main star's name), ``matches rejected`` (the verification rejected
every match the search offered, the retries included).

Writes results/diagnose_sgm/{config.json, results.json, table.md}.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms import sgm
from jstarid.papers import sgm as paper

OUTCOME_NAMES = {js.metrics.CORRECT: "correct", js.metrics.INCOMPLETE: "incomplete",
                 js.metrics.FAIL: "fail", js.metrics.WRONG: "wrong"}


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/diagnose_sgm", seed=0)
    p.add_argument("--experiment", choices=paper.EXPERIMENTS, default="position")
    p.add_argument("--sigma", type=float, default=2.0, help="position noise σ (px)")
    p.add_argument("--n-stars", type=int, default=None, help="main stars (default: all, full size)")
    p.add_argument("--batches", type=int, nargs="*", default=None,
                   help="only these batch indices of the level (batch i = rows i·B … (i+1)·B − 1)")
    p.add_argument("--batch", type=int, default=paper.BATCH, help="scenes per identify call (B)")
    return p.parse_args(argv)


def failure_cause(info, s: int) -> str:
    """The cause of scene ``s``'s failure, from :func:`~jstarid.algorithms.sgm.identify` details."""
    if not info.usable[s]:
        return "unusable"
    if info.main_contested[s]:
        return "main star contested"
    if not info.match_ok[s] and info.n_rejected[s] == 0:
        return "no δ ≤ ε_δ"
    return "matches rejected"


def wrong_names(scenes, result, cam, catalog, s: int) -> list[dict]:
    """Each wrongly named detection of scene ``s``: the stars involved and their distances (px)."""
    truth, ids = np.asarray(scenes.truth[s]), np.asarray(result.ids[s])
    att = np.asarray(scenes.attitude[s], np.float64)
    out = []
    for d in np.nonzero((ids >= 0) & (ids != truth))[0]:
        stars = [int(ids[d]), int(truth[d])] if truth[d] >= 0 else [int(ids[d])]
        xy, _ = cam.project(catalog.unit_vectors[stars] @ att.T)
        dist = np.linalg.norm(np.asarray(xy) - np.asarray(scenes.xy[s, d]), axis=1)
        out.append({"detection": int(d), "named": stars[0], "truth": int(truth[d]),
                    "px_to_named": round(float(dist[0]), 2),
                    "px_to_own": round(float(dist[1]), 2) if len(stars) > 1 else None,
                    "named_star_detected": bool(np.any(truth == stars[0]))})
    return out


def diagnose(args, scfg) -> dict:
    """Outcome counts, failure causes and mis-identifications of one level (see module doc)."""
    cat = js.load_catalog(paper.MAG_LIMIT)
    cam = js.camera_preset(paper.CAMERA)
    db = sgm.build_database(cat, cam, scfg)
    rows = paper.main_star_rows(len(cat), args.n_stars, args.seed)
    batches = None if args.batches is None else set(args.batches)
    outcomes, causes, retried, wrong = Counter(), Counter(), 0, []
    for start, scenes in paper.level_scenes(cat, cam, rows, args.experiment, args.sigma, seed=args.seed,
                                            batch=args.batch, batches=batches):
        res, info = sgm.identify(db, scenes, scfg, diagnostics=True)
        code = np.asarray(js.scene_outcomes(scenes, res, "sgm", camera=cam,
                                            radius_deg=scfg.radius_deg)["outcome"])
        outcomes.update(OUTCOME_NAMES[int(c)] for c in code)
        retried += int(np.sum((code == js.metrics.CORRECT) & (info.n_rejected > 0)))
        causes.update(failure_cause(info, s) for s in np.nonzero(code == js.metrics.FAIL)[0])
        for s in np.nonzero(code == js.metrics.WRONG)[0]:
            wrong.append({"main_star_row": int(rows[start + s]), "n_rejected": int(info.n_rejected[s]),
                          "level": int(info.level[s]), "delta_deg": float(info.error[s]),
                          "names": wrong_names(scenes, res, cam, cat, s)})
    return {"experiment": args.experiment, "sigma_px": args.sigma, "outcomes": dict(outcomes),
            "correct_after_rejections": retried, "failure_causes": dict(causes),
            "mis_identified": wrong}


def main(argv=None) -> dict:
    args = parse_args(argv)
    scfg = ex.with_overrides(sgm.Config(), args.set)
    out = diagnose(args, scfg)
    counts = ([{"what": f"outcome: {k}", "scenes": v} for k, v in out["outcomes"].items()]
              + [{"what": "correct after rejected matches", "scenes": out["correct_after_rejections"]}]
              + [{"what": f"failure: {k}", "scenes": v} for k, v in out["failure_causes"].items()])
    table = ex.markdown_table(counts, [("what", "", "{}"), ("scenes", "scenes", "{}")],
                              title=f"SGM {args.experiment}, σ = {args.sigma} px")
    ex.write(args.out, config={"experiment": args.experiment, "sigma_px": args.sigma, "n_stars": args.n_stars,
                               "batches": args.batches, "batch": args.batch, "seed": args.seed,
                               "sgm_config": scfg}, results=out, table=table)
    print(f"{args.experiment} σ = {args.sigma} px: {out['outcomes']}; correct after rejected matches: "
          f"{out['correct_after_rejections']}; failures: {out['failure_causes']}")
    for w in out["mis_identified"]:
        print("mis-identified:", w)
    return out


if __name__ == "__main__":
    js.enable_compilation_cache()
    js.use_cpu_cores()
    main()
