"""Names a neighbouring star explains as well: what the finishing stage's step 2b takes back.

Each seed algorithm runs twice on the same scenes, with ``Finishing.rival_odds`` at its default and
at 0 (the step off, :mod:`jstarid.rival_stars`; ``--off`` another override, e.g.
``finishing.false_per_frame=0`` for the rival that is no star alone): the demo's scenes
(``sgm2022``, 0–3 px, 200 a level, seed 0, capacity 96: ``jstarid demo``'s), and each algorithm's
own camera (or ``--camera``) at 1 px (``--sigma``), 0.2 mag and one false star. Per run: claimed
scenes, names, wrong names and the scenes holding one, for both settings — the names the step takes
back, and whether any was right; below the table, each name taken back and each wrong name the
step leaves (its distance and brightness against the star it is named after and its true star).

Usage::

    python experiments/probes/rival_names.py
    python experiments/probes/rival_names.py --off finishing.false_per_frame=0 --no-demo \
        --camera experiments/cameras/wide40_512.toml --sigma 2 --scenes 400

Writes results/rival_names/{config.json, results.json, table.md}.
"""

from __future__ import annotations

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex

DEMO_CAPACITY = 96  # jstarid demo's --capacity
OWN_CAMERAS = {"mlv": "mlv2021", "rpnet": "rpnet2019", "sgm": "sgm2022"}


def parse_args(argv=None):
    parser = ex.parser(__doc__.splitlines()[0], out="results/rival_names")
    parser.add_argument("--algorithms", default="mlv,rpnet,sgm", help="comma-separated seed algorithms")
    parser.add_argument("--scenes", type=int, default=200, help="scenes per set")
    parser.add_argument("--off", default="finishing.rival_odds=0",
                        help="the override of the run without the step (e.g. finishing.false_per_frame=0: "
                             "the rival that is no star alone)")
    parser.add_argument("--camera", default=None,
                        help="the second set's camera (default: each algorithm's own; a name or a file)")
    parser.add_argument("--sigma", type=float, default=1.0, help="the second set's position noise (px)")
    parser.add_argument("--no-demo", action="store_true", help="skip the demo's levels")
    return parser.parse_args(argv)


def _counts(scenes, result) -> dict:
    """Claimed scenes, names, wrong names and scenes holding one (:func:`jstarid.metrics.scene_outcomes`)."""
    out = {k: np.asarray(v) for k, v in js.metrics.scene_outcomes(scenes, result).items()}
    return {"claimed": int(np.asarray(result.ok).sum()), "names": int(out["n_identified"].sum()),
            "wrong": int(out["n_wrong"].sum()),
            "wrong_scenes": int((out["outcome"] == js.metrics.WRONG).sum())}


def _sets(algorithm: str, args):
    """(name, catalog, camera, scenes) of the demo's levels and the algorithm's own camera."""
    if not args.no_demo:
        levels = js.engine.simulate_levels("sgm2022", axes={"position_sigma_px": [0.0, 1.0, 2.0, 3.0]},
                                           scenes=args.scenes, seed=args.seed, capacity=DEMO_CAPACITY)
        for level, sigma in enumerate((0, 1, 2, 3)):
            yield (f"sgm2022, {sigma} px (demo)", levels.catalog, levels.camera,
                   levels.scenes[np.flatnonzero(levels.level_of == level)])
    camera = js.load_camera(args.camera or OWN_CAMERAS[algorithm])
    catalog = js.load_catalog(camera.mag_limit)
    noise = js.NoiseConfig(position_sigma_px=args.sigma, magnitude_sigma=0.2, n_false=1)
    yield (f"{camera.name}, {args.sigma:g} px, 0.2 mag, 1 false", catalog, camera,
           js.simulate(jax.random.key(args.seed + 7), catalog, camera, noise, batch_size=args.scenes))


def _names(scenes, result, where, catalog, camera) -> list[dict]:
    """The names of ``result`` at ``where`` ((B, N) bool): scene, whether right, and the detection's
    distance (px, under the scene's true attitude) and magnitude against the star it is named after
    and the star it truly is (``true_v`` None for a false detection), and whether the named star has
    a detection of its own in the scene."""
    ids, truth = np.asarray(result.ids), np.asarray(scenes.truth)
    out = []
    for b, i in zip(*np.nonzero(where), strict=True):
        att = np.asarray(scenes.attitude[b], np.float64)

        def px_to(row, b=b, i=i, att=att):
            xy, _ = camera.project(np.asarray(catalog.unit_vectors[row], np.float64) @ att.T)
            return round(float(np.hypot(*(np.asarray(xy) - np.asarray(scenes.xy[b, i])))), 2)

        named, true = int(ids[b, i]), int(truth[b, i])
        detected = bool(np.any((truth[b] == named) & np.asarray(scenes.valid[b])))
        out.append({"scene": int(b), "right": named == true, "named_v": round(float(catalog.mag[named]), 2),
                    "named_star_detected": detected,
                    "px_to_named": px_to(named), "detection_mag": round(float(scenes.mag[b, i]), 2),
                    "true_v": None if true < 0 else round(float(catalog.mag[true]), 2),
                    "px_to_true": None if true < 0 else px_to(true)})
    return out


def main(argv=None):
    args = parse_args(argv)
    js.use_cpu_cores()
    rows = []
    with ex.Stopwatch() as clock:
        for algorithm in args.algorithms.split(","):
            algo = js.algorithms.get(algorithm)
            for name, catalog, camera, scenes in _sets(algorithm, args):
                config = ex.with_overrides(js.engine.default_config(algorithm, camera=camera), args.set)
                off = ex.with_overrides(config, [args.off])
                database = algo.build_database(catalog, camera, config)
                with_step, without = (algo.identify(database, scenes, c) for c in (config, off))
                on_, off_ = _counts(scenes, with_step), _counts(scenes, without)
                row = {"algorithm": algorithm, "set": name, "odds": config.finishing.rival_odds,
                       "names_taken_back": _names(scenes, without, (np.asarray(without.ids) >= 0)
                                                  & (np.asarray(with_step.ids) < 0)
                                                  & np.asarray(with_step.ok)[:, None], catalog, camera),
                       "wrong_names_left": _names(scenes, with_step, (np.asarray(with_step.ids) >= 0)
                                                  & (np.asarray(with_step.ids) != np.asarray(scenes.truth))
                                                  & np.asarray(scenes.valid), catalog, camera),
                       **{f"off_{k}": v for k, v in off_.items()}, **{f"on_{k}": v for k, v in on_.items()},
                       "taken_back": off_["names"] - on_["names"],
                       "right_taken_back": (off_["names"] - off_["wrong"]) - (on_["names"] - on_["wrong"])}
                rows.append(row)
                print(row, flush=True)
    for row in rows:  # "off / on" cells
        for key in ("claimed", "wrong", "wrong_scenes"):
            row[key] = f"{row[f'off_{key}']} / {row[f'on_{key}']}"
    columns = [("algorithm", "algorithm", "{}"), ("set", "scenes", "{}"),
               ("claimed", "claimed, off / on", "{}"),
               ("off_names", "names, off", "{}"), ("taken_back", "taken back", "{}"),
               ("right_taken_back", "of them right", "{}"), ("wrong", "wrong names, off / on", "{}"),
               ("wrong_scenes", "scenes with one, off / on", "{}")]
    note = (f"{args.scenes} scenes per set, seed {args.seed}; on: the defaults, off: `{args.off}`; "
            f"{clock.seconds:.0f} s including compilation and database builds.")
    table = ex.markdown_table(rows, columns, title="Names a neighbouring star explains as well", note=note)
    for row in rows:  # each name taken back and each wrong name left, below the table
        for kind in ("names_taken_back", "wrong_names_left"):
            for item in row[kind]:
                table += f"\n{row['algorithm']}, {row['set']}, {kind.replace('_', ' ')}: {item}"
    ex.write(args.out, config={"args": vars(args)}, results={"rows": rows}, table=table)
    print(table)


if __name__ == "__main__":
    main()
