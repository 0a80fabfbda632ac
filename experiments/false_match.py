"""Is the false-match probability calibrated? Claims of right and wrong attitudes, and the P given to each.

Each algorithm (its default config for the camera, and ``Config.paper()``, the published algorithm
without the finishing stage) identifies simulated scenes of one camera at a few clutter levels
(``n_false`` false detections with star-like magnitudes, ``false_mag_slope = CATALOG_MAG_SLOPE``
between V 1 and the camera's limit, 0.5 px centroid noise) and scenes of random points. Every
claimed solution gets its false-match probability (:func:`jstarid.false_match.of_solutions`: the one
the finishing stage decided by, or that of the paper's names); a claim is a **wrong
attitude** when its boresight is more than ``--wrong-px`` pixels from the truth (a coincidence lands
degrees away; a right attitude from three or four names can be a pixel or two off), and every claim
on random points is one. Per set: claims, wrong attitudes, claims with any wrong name (the strict
criterion: a right attitude with one name given to the wrong star of a close pair counts), the median
P of the right attitudes, their share with P ≤ 1e-3, and the smallest P a wrong attitude got. The
probability is calibrated when, for every t, wrong attitudes are at most a share t of the claims with
P ≤ t (``calibrated``, :func:`jstarid.false_match.calibrated`).

Usage::

    python experiments/false_match.py                                  # MLV on mlv2021
    python experiments/false_match.py --algorithm sgm --camera sgm2022 --scenes 200

Writes results/false_match/{config.json, results.json, table.md}.
"""

from __future__ import annotations

import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.false_match import WRONG_ATTITUDE_PX, calibrated, of_solutions


def _row(name, config_name, scenes, truth_known, result, p, wrong_arcsec):
    ok = np.asarray(result.ok)
    ids, truth, valid = np.asarray(result.ids), np.asarray(scenes.truth), np.asarray(scenes.valid)
    misnamed = ok & np.any((ids >= 0) & (ids != truth) & valid, axis=1)
    if truth_known:
        bore, _ = js.attitude_errors_arcsec(result.attitude, scenes.attitude)
        wrong = ok & ~(np.asarray(bore) < wrong_arcsec)
    else:
        wrong = ok
    right = ok & ~wrong
    return {"set": name, "config": config_name, "scenes": int(ok.size), "claimed": int(ok.sum()),
            "wrong_attitudes": int(wrong.sum()), "wrong_names": int(misnamed.sum()),
            "right_median_p": float(np.median(p[right])) if right.any() else None,
            "right_below_1e-3": float(np.mean(p[right] <= 1e-3)) if right.any() else None,
            "wrong_min_p": float(np.min(p[wrong])) if wrong.any() else None,
            "calibrated": calibrated(p, ok, wrong)}


def parse_args(argv=None):
    parser = ex.parser(__doc__.splitlines()[0], out="results/false_match")
    parser.add_argument("--algorithm", default="mlv")
    parser.add_argument("--camera", default="mlv2021", help="a camera preset or camera file")
    parser.add_argument("--scenes", type=int, default=300, help="scenes per set")
    parser.add_argument("--false", type=int, nargs="+", default=[0, 20, 40], help="false detections")
    parser.add_argument("--points", type=int, nargs="+", default=[8, 15, 30], help="random points")
    parser.add_argument("--capacity", type=int, default=64,
                        help="detections a scene holds (the brightest; 128 for crowded sets)")
    parser.add_argument("--wrong-px", type=float, default=WRONG_ATTITUDE_PX,
                        help="boresight error of a wrong attitude (px)")
    return parser.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    cam = js.load_camera(args.camera)
    cat = js.load_catalog(cam.mag_limit)
    algo = js.algorithms.get(args.algorithm)
    configs = {"default": ex.with_overrides(js.engine.default_config(args.algorithm, camera=cam), args.set),
               "paper": algo.Config.paper()}
    rows = []
    with ex.Stopwatch() as clock:
        for config_name, config in configs.items():
            problem = js.algorithms.base.camera_problem(algo, cam, config, cat)
            if problem:  # the published SGM's 6° circle on a narrow camera, say
                print(f"{config_name}: skipped: {problem}")
                continue
            db = algo.build_database(cat, cam, config)
            sets = ex.clutter_and_random_sets(cat, cam, seed=args.seed, scenes=args.scenes,
                                              false_counts=args.false, points=args.points,
                                              capacity=args.capacity)
            for name, scenes, truth_known in sets:
                result = algo.identify(db, scenes, config)
                p = of_solutions(scenes, result, cat, cam)
                rows.append(_row(name, config_name, scenes, truth_known, result, p,
                                 args.wrong_px * cam.pixel_scale_arcsec))
                print(rows[-1])
    table = ex.markdown_table(rows, [
        ("config", "config", "{}"), ("set", "set", "{}"), ("claimed", "claimed", "{}"),
        ("wrong_attitudes", "wrong attitudes", "{}"), ("wrong_names", "any wrong name", "{}"),
        ("right_median_p", "right: median P", "{:.1e}"),
        ("right_below_1e-3", "right: P ≤ 1e-3", "{:.0%}"), ("wrong_min_p", "wrong: smallest P", "{:.2g}"),
        ("calibrated", "calibrated", "{}")],
        title=f"False-match probability, {args.algorithm} on {args.camera} ({args.scenes} scenes per set)",
        note=f"{clock.seconds:.0f} s including compilation.")
    ex.write(args.out, config={"args": vars(args), "configs": configs}, results={"rows": rows}, table=table)
    print(table)


if __name__ == "__main__":
    main()
