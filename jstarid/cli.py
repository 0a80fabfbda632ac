"""The ``jstarid`` command line: a thin shell over the public API."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def _demo(args) -> int:
    import jax
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import jstarid as js

    t0 = time.perf_counter()
    cat = js.load_catalog(args.mag_limit)
    cam = js.camera_preset(args.camera)
    noise = js.NoiseConfig(position_sigma_px=args.sigma, magnitude_sigma=args.mag_sigma,
                           n_missing=args.missing, n_false=args.false)
    print(f"catalog: {len(cat)} stars with V ≤ {cat.mag_limit} ({len(cat.sim_mag)} in the "
          f"simulation list), loaded in {time.perf_counter() - t0:.2f} s")
    print(f"camera {cam.name}: {cam.width}x{cam.height} px, FOV {cam.fov_x_deg:.2f}° x "
          f"{cam.fov_y_deg:.2f}°, detection limit V {cam.mag_limit}")
    t0 = time.perf_counter()
    scenes = js.simulate(jax.random.key(args.seed), cat, cam, noise, batch_size=args.batch,
                         capacity=args.capacity)
    jax.block_until_ready(scenes)
    dt = time.perf_counter() - t0
    n = np.asarray(scenes.n_stars)
    truth, valid = np.asarray(scenes.truth), np.asarray(scenes.valid)
    n_true = (valid & (truth >= 0)).sum(1)
    stats = {
        "scenes": int(args.batch), "seed": args.seed, "noise": {k: float(v) for k, v in
                                                                 vars(noise).items()},
        "stars_per_scene_mean": float(n.mean()), "stars_per_scene_min": int(n.min()),
        "stars_per_scene_max": int(n.max()), "catalog_stars_per_scene_mean": float(n_true.mean()),
        "scenes_with_fewer_than_3_stars": float(np.mean(n < 3)),
        "overflow_rate": float(np.asarray(scenes.overflow).mean()),
        "simulate_seconds_incl_compile": dt,
    }
    print(f"simulated {args.batch} scenes in {dt:.2f} s (including compilation)")
    for k, v in stats.items():
        if k not in ("noise", "scenes", "seed", "simulate_seconds_incl_compile"):
            print(f"  {k:34s} {v:.3f}" if isinstance(v, float) else f"  {k:34s} {v}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "scene_stats.json").write_text(json.dumps(stats, indent=1))
    ax = js.plotting.plot_scene(scenes, 0, cat, cam)
    ax.set_title(f"{cam.name}: scene 0 of {args.batch}, σ = {args.sigma} px")
    fig = ax.figure
    fig.tight_layout()
    fig.savefig(out / "scene.png", dpi=120)
    plt.close(fig)
    print(f"wrote {out / 'scene.png'} and {out / 'scene_stats.json'}")
    return 0


def _compare(args) -> int:
    """Run the chosen algorithms on one shared scene set and print their rates side by side."""
    import jax

    import jstarid as js

    cat = js.load_catalog(args.mag_limit)
    cam = js.camera_preset(args.camera)
    noise = js.NoiseConfig(position_sigma_px=args.sigma, magnitude_sigma=args.mag_sigma,
                           n_missing=args.missing, n_false=args.false)
    scenes = js.simulate(jax.random.key(args.seed), cat, cam, noise, batch_size=args.batch,
                         capacity=args.capacity)
    names = [n for n in args.algorithms.split(",") if n]
    rows = []
    for name in names:
        algo = js.algorithms.get(name)
        cfg = algo.Config()
        t0 = time.perf_counter()
        db = algo.build_database(cat, cam, cfg)
        t_db = time.perf_counter() - t0
        t0 = time.perf_counter()
        result = algo.identify(db, scenes, cfg)
        jax.block_until_ready(result.ids)
        t_id = time.perf_counter() - t0
        rep = js.evaluate(scenes, result, "strict")
        rows.append({"algorithm": name, "identification": rep["identification_rate"],
                     "failure": rep["failure_rate"], "misid": rep["misid_rate"],
                     "database_s": t_db, "identify_s_incl_compile": t_id})
    print(f"{args.batch} scenes, camera {cam.name}, σ = {args.sigma} px, magnitude σ = "
          f"{args.mag_sigma}, {args.missing} missing, {args.false} false; strict criterion "
          f"(≥ 3 correct, none wrong)")
    print("| algorithm | identification | failure | mis-identification | database s | identify s |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['algorithm']} | {r['identification']:.4f} | {r['failure']:.4f} | "
              f"{r['misid']:.4f} | {r['database_s']:.1f} | {r['identify_s_incl_compile']:.1f} |")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps({"args": vars(args), "rows": rows}, indent=1,
                                                 default=str))
    return 0


def _solve(args) -> int:
    """Raw images → centroids → identification → attitude, one line per image plus a JSON file."""
    import jstarid as js

    cat = js.load_catalog(args.mag_limit, epoch=args.epoch)
    cam = js.camera_preset(args.camera)
    images = [js.read_image(p) for p in args.images]
    if len({im.shape for im in images}) != 1 or images[0].shape != (cam.height, cam.width):
        raise ValueError(f"every image must be {cam.height}×{cam.width} px (camera {cam.name}); "
                         f"got {sorted({im.shape for im in images})}")
    scenes = js.extract_centroids(np.stack(images), capacity=args.capacity, shard=True)
    algo = js.algorithms.get(args.algorithm)
    # RpNet trains a network per camera on first use: the quick preset takes minutes, the paper's hours
    cfg = ((algo.Config.quick() if args.rpnet_network == "quick" else algo.Config())
           if args.algorithm == "rpnet" else algo.Config())
    result = algo.identify(algo.build_database(cat, cam, cfg), scenes, cfg)
    if args.name_all:
        result = js.name_from_attitude(cat, cam, scenes, result, tol_px=args.tol_px)
    att, rms_arcsec, have = (np.asarray(a) for a in js.estimate_attitude(cat, cam, scenes, result))
    ra, dec, roll = (np.degrees(np.asarray(a)) for a in js.rotation_to_radec_roll(att))
    ids, xy, ok = np.asarray(result.ids), np.asarray(scenes.xy), np.asarray(result.ok)
    n_det = np.asarray(scenes.valid).sum(axis=1)
    solutions = []
    for i, path in enumerate(args.images):
        named = np.nonzero(ids[i] >= 0)[0]
        solved = bool(ok[i] and have[i])
        entry = {"image": str(path), "detections": int(n_det[i]), "solved": solved,
                 "stars": [{"hip": int(cat.hip[ids[i, j]]), "x": float(xy[i, j, 0]),
                            "y": float(xy[i, j, 1]), "v": float(cat.mag[ids[i, j]])} for j in named]}
        if solved:
            entry.update(ra_deg=float(ra[i]), dec_deg=float(dec[i]), roll_deg=float(roll[i]),
                         residual_arcsec=float(rms_arcsec[i]), attitude=att[i].tolist())
            print(f"{path}: {len(named)} of {n_det[i]} detections identified; boresight RA "
                  f"{ra[i]:.4f}°, Dec {dec[i]:+.4f}°, roll {roll[i]:+.3f}°, residual "
                  f"{rms_arcsec[i]:.1f}″")
        else:
            print(f"{path}: not solved ({n_det[i]} detections)")
        solutions.append(entry)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "solutions.json").write_text(json.dumps({"args": vars(args), "solutions": solutions},
                                                   indent=1, default=str))
    print(f"wrote {out / 'solutions.json'}")
    return 0 if all(s["solved"] for s in solutions) else 1


def _catalog(args) -> int:
    import jstarid as js

    cat = js.load_catalog(args.mag_limit, double_sep_deg=args.double_sep,
                          double_mode=args.double_mode)
    print(cat)
    hist, edges = np.histogram(cat.mag, bins=np.arange(-1.5, args.mag_limit + 0.5, 1.0))
    for h, e in zip(hist, edges, strict=False):
        print(f"  V {e:5.1f} – {e + 1:4.1f}: {h}")
    return 0


def _list(args) -> int:
    import jstarid as js

    print("algorithms:", ", ".join(js.algorithms.names()))
    print("cameras:   ", ", ".join(js.preset_names()))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jstarid", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    d = sub.add_parser("demo", help="simulate a batch, print scene statistics, draw one scene")
    d.add_argument("--camera", default="sgm2022")
    d.add_argument("--mag-limit", type=float, default=6.0)
    d.add_argument("--batch", type=int, default=1000)
    d.add_argument("--capacity", type=int, default=64)
    d.add_argument("--sigma", type=float, default=1.0, help="position noise σ (px)")
    d.add_argument("--mag-sigma", type=float, default=0.0, help="magnitude noise σ (mag)")
    d.add_argument("--missing", type=int, default=0)
    d.add_argument("--false", type=int, default=0)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--out", default="results/demo")
    d.set_defaults(func=_demo)
    m = sub.add_parser("compare", help="run algorithms on one shared scene set, rates side by side")
    m.add_argument("--algorithms", default="sgm,mlv,rpnet",
                   help="comma-separated registry names (see `jstarid list`)")
    m.add_argument("--camera", default="sgm2022")
    m.add_argument("--mag-limit", type=float, default=6.0)
    m.add_argument("--batch", type=int, default=1000)
    m.add_argument("--capacity", type=int, default=64)
    m.add_argument("--sigma", type=float, default=1.0)
    m.add_argument("--mag-sigma", type=float, default=0.0)
    m.add_argument("--missing", type=int, default=0)
    m.add_argument("--false", type=int, default=0)
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--out", default="results/compare")
    m.set_defaults(func=_compare)
    s = sub.add_parser("solve", help="identify the stars of raw images (TIFF/PNG) and print the "
                                     "attitude; exit 1 when an image is not solved")
    s.add_argument("images", nargs="+", help="grayscale image files, all from one camera")
    s.add_argument("--camera", default="tetra3_test", help="camera preset (see `jstarid list`)")
    s.add_argument("--algorithm", default="mlv")
    s.add_argument("--mag-limit", type=float, default=7.0, help="catalog depth (V)")
    s.add_argument("--epoch", type=float, default=None,
                   help="Julian year of the images (proper motion), e.g. 2019.57")
    s.add_argument("--capacity", type=int, default=24, help="brightest detections used per image")
    s.add_argument("--name-all", action=argparse.BooleanOptionalAction, default=True,
                   help="name every detection the solved attitude explains (js.name_from_attitude); "
                        "--no-name-all keeps the algorithm's own names")
    s.add_argument("--tol-px", type=float, default=2.0, help="tolerance of --name-all (px)")
    s.add_argument("--rpnet-network", choices=("quick", "table3"), default="quick",
                   help="RpNet network (trained for the camera on first use, then cached)")
    s.add_argument("--out", default="results/solve")
    s.set_defaults(func=_solve)
    ls = sub.add_parser("list", help="registered algorithms and camera presets")
    ls.set_defaults(func=_list)
    c = sub.add_parser("catalog", help="catalog statistics")
    c.add_argument("--mag-limit", type=float, default=6.0)
    c.add_argument("--double-sep", type=float, default=0.05)
    c.add_argument("--double-mode", default="drop")
    c.set_defaults(func=_catalog)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if argv is None:  # a command-line run (tests pass argv): keep compiled code for the next run
        from jstarid.compilation_cache import enable_compilation_cache
        from jstarid.runtime import use_cpu_cores
        enable_compilation_cache()
        use_cpu_cores()  # SGM's pair kernels split over every core (one JAX device each)
    try:
        return args.func(args)
    except ValueError as err:  # bad settings: a clear message, not a traceback
        print(f"jstarid: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
