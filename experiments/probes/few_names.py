"""Claims of few names and what their frame says: the measurement behind ``Finishing.max_false_match``.

For one algorithm and camera (the sets of ``experiments/false_match.py``,
:func:`jstarid.experiment.clutter_and_random_sets`: a few clutter levels and
scenes of random points), the algorithm's claims of at most ``--names`` names are each given the
false-match probability of their whole frame, named from the claim's attitude
(:func:`jstarid.completion.name_from_attitude` within the camera check's largest radius), as the
finishing stage's false-match test computes it for a claim its own names leave doubtful. Run with
``--set finishing.max_false_match=1`` to see the claims the test judges (with it on, the doubtful
ones are already gone). Per set: claims, claims of few names, how many of those are wrong attitudes
(boresight over ``--wrong-px`` off; every claim on random points), the range of log10 P of the right
and the wrong ones, and how many right ones each threshold would fail.

Usage::

    python experiments/probes/few_names.py --camera experiments/cameras/challenge10.toml \\
        --set finishing.max_false_match=1

Writes results/few_names/{config.json, results.json, table.md}.
"""

from __future__ import annotations

import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.camera_fit import MAX_TOL_PX
from jstarid.completion import name_from_attitude
from jstarid.false_match import false_match_probability
from jstarid.runtime import padded_indices

THRESHOLDS = (1e-3, 1e-2)


def parse_args(argv=None):
    parser = ex.parser(__doc__.splitlines()[0], out="results/few_names")
    parser.add_argument("--algorithm", default="mlv")
    parser.add_argument("--camera", default="experiments/cameras/challenge10.toml",
                        help="a camera preset or camera file")
    parser.add_argument("--scenes", type=int, default=300, help="scenes per set")
    parser.add_argument("--false", type=int, nargs="+", default=[0, 20, 40, 80], help="false detections")
    parser.add_argument("--points", type=int, nargs="+", default=[8, 15, 30], help="random points")
    parser.add_argument("--names", type=int, default=4, help="a claim of at most this many names is few")
    parser.add_argument("--wrong-px", type=float, default=10.0, help="boresight error of a wrong attitude")
    return parser.parse_args(argv)


def _frame_p(catalog, camera, scenes, result, rows):
    """(R,) log10 P of each claim's frame (−inf where P underflows; 0 where the frame fails)."""
    padded = padded_indices(rows)
    framed = name_from_attitude(catalog, camera, scenes[padded], result[padded], tol_px=MAX_TOL_PX)
    p = false_match_probability(scenes[padded], framed, catalog.unit_vectors, camera)[:rows.size]
    p = np.where(np.asarray(framed.ok)[:rows.size], p, 1.0)
    with np.errstate(divide="ignore"):
        return np.log10(p)


def _span(values):
    return f"{values.min():.1f} … {values.max():.1f}" if values.size else "–"


def main(argv=None):
    args = parse_args(argv)
    camera = js.load_camera(args.camera)
    catalog = js.load_catalog(camera.mag_limit)
    algo = js.algorithms.get(args.algorithm)
    config = ex.with_overrides(js.engine.default_config(args.algorithm, camera=camera), args.set)
    database = algo.build_database(catalog, camera, config)
    rows = []
    sets = ex.clutter_and_random_sets(catalog, camera, seed=args.seed, scenes=args.scenes,
                                      false_counts=args.false, points=args.points)
    with ex.Stopwatch() as clock:
        for name, scenes, truth_known in sets:
            result = algo.identify(database, scenes, config)
            ok = np.asarray(result.ok)
            if truth_known:
                bore, _ = js.attitude_errors_arcsec(result.attitude, scenes.attitude)
                wrong = ok & ~(np.asarray(bore) < args.wrong_px * camera.pixel_scale_arcsec)
            else:
                wrong = ok
            few = np.flatnonzero(ok & (np.sum(np.asarray(result.ids) >= 0, axis=1) <= args.names))
            log_p = _frame_p(catalog, camera, scenes, result, few) if few.size else np.zeros(0)
            right_p, wrong_p = log_p[~wrong[few]], log_p[wrong[few]]
            row = {"set": name, "claimed": int(ok.sum()), "few": int(few.size),
                   "few_wrong": int(wrong[few].sum()), "right_log10_p": _span(right_p),
                   "wrong_log10_p": _span(wrong_p)}
            for t in THRESHOLDS:
                row[f"right_failed_at_{t:g}"] = int(np.sum(right_p > np.log10(t)))
            rows.append(row)
            print(row)
    columns = [("set", "set", "{}"), ("claimed", "claimed", "{}"), ("few", f"≤ {args.names} names", "{}"),
               ("few_wrong", "of them wrong", "{}"), ("right_log10_p", "right: log10 P of the frame", "{}"),
               ("wrong_log10_p", "wrong: log10 P", "{}")]
    columns += [(f"right_failed_at_{t:g}", f"right failed at {t:g}", "{}") for t in THRESHOLDS]
    note = f"{args.scenes} scenes per set; {clock.seconds:.0f} s including compilation."
    table = ex.markdown_table(rows, columns, title=f"Claims of few names, {args.algorithm} on {args.camera}",
                              note=note)
    ex.write(args.out, config={"args": vars(args), "config": config}, results={"rows": rows}, table=table)
    print(table)


if __name__ == "__main__":
    main()
