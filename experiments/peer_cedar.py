"""The peer solver: cedar-solve (the maintained fork of ESA's tetra3) on exactly the engine's scenes.

A preset over :mod:`jstarid.peers.cedar` (cedar in its own environment, built on first use; jstarid's
catalog as its ``hip_main.dat``; its database for the camera): draws the sweep's scenes with
:func:`jstarid.engine.simulate_levels` (the same scenes as ``jstarid demo`` for the same camera,
levels, scene count and seed), solves each once per ``match_max_error`` (its default 0.002, and
0.005: a fair tuned value at 2–3 px), times every solve, and scores the matches with
:func:`jstarid.evaluate` like every other algorithm. ``jstarid demo --peer cedar`` puts it in the
engine's table instead (a row per setting, the engine's timing).

If the environment cannot be built the script says so and exits with status 0. Usage::

    python experiments/peer_cedar.py                      # sgm2022, 0–3 px, 200 scenes per level
    python experiments/peer_cedar.py --scenes 20 --levels 0,2 --max-error 0.005
"""

from __future__ import annotations

import sys
import time

import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.peers import cedar


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/peer_cedar")
    p.add_argument("--camera", default="sgm2022", help="camera preset or file (default sgm2022)")
    p.add_argument("--levels", default="0,1,2,3", help="position noise σ levels, px (default 0,1,2,3)")
    p.add_argument("--scenes", type=int, default=200, help="scenes per level (default 200)")
    p.add_argument("--max-error", default="0.002,0.005",
                   help="cedar's match_max_error values (default 0.002 = its default, and 0.005)")
    args = p.parse_args(argv)
    if args.set:
        p.error("--set changes jstarid algorithms' configs; the peer takes --max-error")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    if cedar.environment() is None:
        print("no peer rows: cedar-solve's environment is not available")
        return 0
    levels = [float(v) for v in args.levels.split(",")]
    errors = [float(v) for v in args.max_error.split(",")]
    drawn = js.engine.simulate_levels(args.camera, axes={"position_sigma_px": levels}, scenes=args.scenes,
                                      seed=args.seed)
    database = cedar.build_database(drawn.catalog, drawn.camera)
    print(f"cedar-solve on {drawn.scenes.batch_size} scenes × {len(errors)} settings …", flush=True)
    t0 = time.perf_counter()
    answers = cedar.solve(database, drawn.scenes, errors)
    print(f"done in {time.perf_counter() - t0:.0f} s", flush=True)
    rows = ["| match_max_error | position σ (px) | scenes | identified | misid | failed | ms per solve "
            "(median) |", "|---|---|---|---|---|---|---|"]
    for err in errors:
        solved = answers[str(err)]
        ids, ok = cedar.matches_to_ids(drawn.scenes, drawn.catalog, solved)
        result = js.Identification(ids=ids, ok=ok, attitude=None)
        seconds = np.asarray(solved["seconds"])
        for k, level in enumerate(levels):
            sel = np.flatnonzero(drawn.level_of == k)
            rep = js.evaluate(drawn.scenes[sel[0]:sel[-1] + 1], result[sel[0]:sel[-1] + 1], "strict")
            rows.append(f"| {err} | {level:g} | {sel.size} | {100 * rep['identification_rate']:.2f}% | "
                        f"{100 * rep['misid_rate']:.2f}% | {100 * rep['failure_rate']:.2f}% | "
                        f"{1e3 * np.median(seconds[sel]):.1f} |")
    table = "\n".join(rows)
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    title = f"# cedar-solve on the engine's scenes ({drawn.camera.name}, seed {args.seed})"
    (args.out / "table.md").write_text(f"{title}\n\n{table}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
