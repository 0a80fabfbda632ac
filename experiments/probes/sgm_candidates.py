"""Where SGM's search spends its candidates: examined database graphs per scene, by outcome.

SGM's throughput follows the number of (scene, database graph) pairs its search examines (each is
screened, and the few the screen keeps are matched spectrally). Algorithm 1 stops a scene at the
first Δw level with a match; a scene with no match examines its whole window ``|w_J − w_I| ≤
Δw_max``. On fresh scenes at each ``--sigmas`` level this prints, for the first pass of
``identify`` (``diagnostics=True``), the scenes that found a match and those that found none: how
many, their share of the examined candidates, and the median and 90th percentile per scene::

    python experiments/probes/sgm_candidates.py --sigmas 1 3 --batch 1000

Writes results/sgm_candidates/{config.json, results.json, table.md}.
"""

from __future__ import annotations

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/sgm_candidates", seed=0)
    p.add_argument("--camera", default="sgm2022")
    p.add_argument("--sigmas", type=float, nargs="+", default=[1.0, 3.0], help="position noise σ (px)")
    p.add_argument("--magnitude-sigma", type=float, default=0.1, help="magnitude noise σ (mag)")
    p.add_argument("--batch", type=int, default=1000, help="scenes per level")
    return p.parse_args(argv)


def breakdown(diag) -> list[dict]:
    """Rows of examined candidates (``Diagnostics.n_candidates``) per outcome of the first pass."""
    n = np.asarray(diag.n_candidates, np.int64)
    total = max(int(n.sum()), 1)
    groups = (("match found", diag.match_ok), ("no match", diag.usable & ~diag.match_ok),
              ("not searched", ~diag.usable))
    rows = []
    for name, mask in groups:
        mask = np.asarray(mask, bool)
        picked = n[mask]
        rows.append({"outcome": name, "scenes": int(mask.sum()), "examined": int(picked.sum()),
                     "share": float(picked.sum() / total),
                     "median": float(np.median(picked)) if picked.size else 0.0,
                     "p90": float(np.percentile(picked, 90)) if picked.size else 0.0})
    return rows


def main(argv=None):
    args = parse_args(argv)
    js.use_cpu_cores()
    camera = js.load_camera(args.camera)
    catalog = js.load_catalog(camera.mag_limit)
    algo = js.algorithms.get("sgm")
    config = ex.with_overrides(js.engine.default_config("sgm", camera=camera), args.set)
    db = algo.build_database(catalog, camera, config)
    results, lines = [], ["| σ (px) | outcome | scenes | candidates examined | share | median | 90th pct |",
                          "|---|---|---|---|---|---|---|"]
    for level, sigma in enumerate(args.sigmas):
        noise = js.NoiseConfig(position_sigma_px=sigma, magnitude_sigma=args.magnitude_sigma)
        scenes = js.simulate(jax.random.fold_in(jax.random.key(args.seed), level), catalog, camera, noise,
                             batch_size=args.batch, capacity=64)
        _, diag = algo.identify(db, scenes, config, diagnostics=True)
        for row in breakdown(diag):
            results.append({"sigma_px": sigma, **row})
            lines.append(f"| {sigma:g} | {row['outcome']} | {row['scenes']} | {row['examined']:,} | "
                         f"{row['share']:.1%} | {row['median']:,.0f} | {row['p90']:,.0f} |")
        print("\n".join(lines[-3:]), flush=True)
    ex.write(args.out, config={"args": vars(args), "config": config}, results={"rows": results},
             table="\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
