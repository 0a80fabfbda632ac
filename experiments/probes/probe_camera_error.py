"""Wrong names from a slightly wrong camera: every algorithm on scenes taken with a focal length or
principal point that differs from the camera it was given.

The scenes are simulated with the *true* camera (the nominal one with ``f_px`` scaled, or the
principal point moved, or seen through a lens with radial distortion); every algorithm and
:func:`jstarid.name_from_attitude` work with the *nominal* camera, as a user with an uncalibrated
lens or a datasheet focal length would. Per setting and algorithm: scenes claimed, claimed scenes
with at least one wrong name, the same after ``name_from_attitude``, the median focal-length error
the camera fit reports (``fitted``, %) against the true one (``true``, %), and the median fitted
distortion ``k1``.

Usage::

    python experiments/probes/probe_camera_error.py --quick          # 100 scenes per setting
    python experiments/probes/probe_camera_error.py --scenes 1000

Writes results/probe_camera_error/{config.json, results.json, table.md}.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex

# (label, focal scale, principal point shift in x (px), radial distortion k1 of the lens)
SETTINGS = (("f × 0.98", 0.98, 0.0, 0.0), ("f × 0.99", 0.99, 0.0, 0.0), ("true camera", 1.0, 0.0, 0.0),
            ("f × 1.01", 1.01, 0.0, 0.0), ("f × 1.02", 1.02, 0.0, 0.0), ("f × 1.05", 1.05, 0.0, 0.0),
            ("principal point + 20 px", 1.0, 20.0, 0.0), ("lens k1 = +0.2", 1.0, 0.0, 0.2))


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/probe_camera_error", seed=39,
                  quick="100 scenes per setting")
    p.add_argument("--scenes", type=int, default=500, help="scenes per setting")
    p.add_argument("--camera", default="sgm2022", help="the nominal camera (a preset)")
    p.add_argument("--algorithms", default="sgm,mlv,rpnet")
    p.add_argument("--sigma", type=float, default=0.5, help="position noise σ (px)")
    return p.parse_args(argv)


def true_camera(nominal: js.Camera, scale: float, shift_px: float) -> js.Camera:
    """The camera the scenes are taken with: ``f_px`` × ``scale``, principal point moved in x."""
    return dataclasses.replace(nominal, f_px=nominal.f_px * scale, cx=nominal.cx + shift_px)


def probe(module, db, config, catalog, nominal, scenes, truth_scale) -> dict:
    """Counts for one algorithm on one setting's scenes."""
    result = module.identify(db, scenes, config)
    named = js.name_from_attitude(catalog, nominal, scenes, result)
    row = {}
    for tag, res in (("", result), ("_named", named)):
        out = js.scene_outcomes(scenes, res, "strict")
        ok = np.asarray(res.ok)
        row[f"claimed{tag}"] = int(ok.sum())
        row[f"wrong{tag}"] = int(np.sum(ok & (np.asarray(out["n_wrong"]) > 0)))
        row[f"wrong_names{tag}"] = int(np.sum(np.where(ok, np.asarray(out["n_wrong"]), 0)))
    scale = getattr(named, "focal_scale", None)
    fitted = np.asarray(scale)[np.asarray(named.ok)] if scale is not None else np.zeros(0)
    row["fitted_focal_error_pct"] = float(100 * (np.median(fitted) - 1)) if fitted.size else None
    row["true_focal_error_pct"] = 100 * (truth_scale - 1)
    k1 = getattr(named, "distortion_k1", None)
    k1 = np.asarray(k1)[np.asarray(named.ok)] if k1 is not None else np.zeros(0)
    row["fitted_k1"] = float(np.median(k1)) if k1.size else None
    return row


def main(argv=None) -> dict:
    args = parse_args(argv)
    n = 100 if args.quick else args.scenes
    nominal = js.camera_preset(args.camera)
    catalog = js.load_catalog(nominal.mag_limit)
    names = args.algorithms.split(",")
    entries = {name: js.engine.default_config(name) for name in names}
    dbs = {name: js.algorithms.get(name).build_database(catalog, nominal, cfg)
           for name, cfg in entries.items()}
    rows = []
    for k, (label, scale, shift, k1) in enumerate(SETTINGS):
        cam = true_camera(nominal, scale, shift)
        scenes = js.simulate(jax.random.fold_in(jax.random.key(args.seed), k), catalog, cam,
                             js.NoiseConfig(position_sigma_px=args.sigma), batch_size=n, shard=True)
        if k1:
            scenes = js.camera_fit.distort_scenes(scenes, cam, k1)
        for name in names:
            row = {"setting": label, "algorithm": name, "scenes": n,
                   **probe(js.algorithms.get(name), dbs[name], entries[name], catalog, nominal, scenes,
                           scale)}
            rows.append(row)
            print(row, flush=True)
    columns = [("setting", "setting", "{}"), ("algorithm", "algorithm", "{}"),
               ("scenes", "scenes", "{:,}"), ("claimed", "claimed", "{:,}"),
               ("wrong", "claimed with a wrong name", "{:,}"),
               ("claimed_named", "claimed, name_from_attitude", "{:,}"),
               ("wrong_named", "… with a wrong name", "{:,}"),
               ("true_focal_error_pct", "true f error %", "{:+.1f}"),
               ("fitted_focal_error_pct", "fitted f error % (median)", "{:+.2f}"),
               ("fitted_k1", "fitted k1 (median)", "{:+.3f}")]
    table = ex.markdown_table(rows, columns, title=f"Camera errors on {args.camera}, σ = {args.sigma} px",
                              note="Scenes from the true camera, algorithms given the nominal one.")
    ex.write(args.out, config={"scenes": n, "seed": args.seed, "camera": nominal, "sigma": args.sigma,
                               "algorithms": names},
             results={"rows": rows}, table=table)
    print(table)
    return {"rows": rows}


if __name__ == "__main__":
    js.use_cpu_cores()
    js.enable_compilation_cache()
    main()
