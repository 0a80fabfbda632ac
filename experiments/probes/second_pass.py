"""The hypothesis search alone on cluttered frames, at several second-pass capacities.

Every frame starts unsolved and goes through :func:`jstarid.hypotheses.solve_unsolved` (48 brightest
detections, then the crowded pass over 96), once per factor in ``--factors`` (the second pass
verifies that many times the first's 4,096 hypotheses, ``hypotheses.SECOND_PASS_CAPACITY``). Per
factor: frames solved, solved among the frames with ``--stars`` true stars, frames with any wrong
name, frames flagged as overflowing, seconds (compilation included). Why the factor is 16:
docs/design/hypotheses.md.

Usage::

    python experiments/probes/second_pass.py --camera experiments/cameras/challenge6.toml --false 60
"""

from __future__ import annotations

import time

import jax.numpy as jnp
import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid import hypotheses


def parse_args(argv=None):
    parser = ex.parser(__doc__.splitlines()[0], out="results/second_pass")
    parser.add_argument("--camera", default="experiments/cameras/challenge6.toml")
    parser.add_argument("--false", type=int, default=60, help="false detections of star-like brightness")
    parser.add_argument("--scenes", type=int, default=64)
    parser.add_argument("--factors", type=int, nargs="+", default=[4, 16])
    parser.add_argument("--stars", type=int, nargs=2, default=[10, 14],
                        help="true stars of the frames counted apart")
    return parser.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    cam = js.load_camera(args.camera)
    cat = js.load_catalog(cam.mag_limit)
    # the false-match experiments' clutter set (experiment.clutter_and_random_sets), 128 detections
    (_, scenes, _), = ex.clutter_and_random_sets(cat, cam, seed=args.seed, scenes=args.scenes,
                                                 false_counts=[args.false], points=[], capacity=128)
    truth, valid = np.asarray(scenes.truth), np.asarray(scenes.valid)
    stars = ((truth >= 0) & valid).sum(axis=1)
    counted = (stars >= args.stars[0]) & (stars <= args.stars[1])
    b, n = truth.shape
    unsolved = js.Identification(ids=jnp.full((b, n), -1, jnp.int32), ok=jnp.zeros(b, bool),
                                 attitude=jnp.full((b, 3, 3), jnp.nan))
    rows = []
    for factor in args.factors:
        hypotheses.SECOND_PASS_CAPACITY = factor
        start = time.perf_counter()
        out = hypotheses.solve_unsolved(unsolved, scenes, star_vectors=cat.unit_vectors, camera=cam, n_use=48,
                                        eps_px=3.0, min_confirm=1, max_false_match=1e-5, n_crowded=96,
                                        star_mags=cat.mag)
        ok, ids = np.asarray(out.result.ok), np.asarray(out.result.ids)
        rows.append({"factor": factor, "solved": int(ok.sum()),
                     "solved_counted": f"{int(ok[counted].sum())} / {int(counted.sum())}",
                     "wrong": int((ok & np.any((ids >= 0) & (ids != truth) & valid, axis=1)).sum()),
                     "overflow": int(out.overflow.sum()), "seconds": time.perf_counter() - start})
        print(rows[-1], flush=True)
    table = ex.markdown_table(rows, [
        ("factor", "second-pass capacity ×", "{}"), ("solved", f"solved of {b}", "{}"),
        ("solved_counted", f"solved, {args.stars[0]}–{args.stars[1]} stars", "{}"),
        ("wrong", "any wrong name", "{}"), ("overflow", "overflow flagged", "{}"),
        ("seconds", "s (compile included)", "{:.0f}")],
        title=f"The search alone on {args.camera}, {args.false} false detections")
    ex.write(args.out, config={"args": vars(args)}, results={"rows": rows}, table=table)


if __name__ == "__main__":
    main()
