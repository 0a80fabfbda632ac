"""``jstarid identify`` (centroid files) and ``jstarid solve`` (raw images): names and attitude."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from jstarid.cli.cameras import FRAME_CAMERA, add_camera_options, camera_from_args
from jstarid.cli.centroid_input import add_centroid_file_options
from jstarid.solution import IMAGE_BLEND_PX, NAMING_CAPACITY


def add_commands(sub) -> None:
    i = sub.add_parser(
        "identify", help="centroid file(s) (CSV/TSV with named columns, or JSON) → star names and "
                         "attitude as JSON; exit 1 when a scene is not solved",
        description="Identify the stars of one scene or many given as centroids (px, origin at the "
                    "centre of pixel (0, 0)). Tables name their columns in a header, in any order: "
                    "x, y, mag (or flux), hip (true ids, copied to the output as true_hip), scene; "
                    "without a header x, y[, magnitude] per line, scenes split by blank lines. "
                    "JSON: [[x, y, mag], …], a list of those, or {\"scenes\": [...]}. Prints JSON "
                    "(or writes --out).")
    i.add_argument("files", nargs="+", type=Path, help="centroid files (.csv, .tsv, .txt or .json)")
    _frame_options(i, camera=FRAME_CAMERA, capacity=64)
    add_centroid_file_options(i)
    i.add_argument("--out", type=Path, default=None, help="write the JSON here instead of stdout")
    i.set_defaults(func=run_identify)
    s = sub.add_parser("solve", help="identify the stars of raw images (TIFF/PNG) and print the "
                                     "attitude; exit 1 when an image is not solved")
    s.add_argument("images", nargs="+", help="grayscale image files, all from one camera")
    _frame_options(s, camera=FRAME_CAMERA, capacity=24)
    s.add_argument("--out", default="results/solve", help="results directory (default results/solve)")
    s.set_defaults(func=run_solve)


def _frame_options(p, *, camera: str, capacity: int) -> None:
    add_camera_options(p, default=camera)
    p.add_argument("--algorithm", default="mlv", help="registry name (default mlv)")
    p.add_argument("--mag-limit", type=float, default=None,
                   help="identification catalog depth V (default: the camera's detection limit: "
                        "a preset's, else the field's depth, e.g. 8.5 for a 6° field; naming "
                        "goes deeper)")
    p.add_argument("--epoch", type=float, default=None,
                   help="Julian year of the observation, for proper motion (e.g. 2019.57); "
                        "default: the catalog's epoch J1991.25")
    p.add_argument("--capacity", type=int, default=capacity,
                   help=f"brightest detections the algorithm uses per scene (default {capacity}; "
                        f"naming looks at up to {NAMING_CAPACITY})")
    p.add_argument("--name-all", action=argparse.BooleanOptionalAction, default=True,
                   help="name every detection the solved attitude explains (js.name_from_attitude); "
                        "--no-name-all keeps the algorithm's own names")
    p.add_argument("--tol-px", type=float, default=2.0, help="tolerance of --name-all (px)")
    p.add_argument("--fov-max-error", type=float, default=0.1,
                   help="largest relative focal-length (field of view) correction the camera fit of "
                        "--name-all may make before a frame counts as not solved (default 0.1)")
    p.add_argument("--rpnet-network", choices=("quick", "table3"), default="quick",
                   help="RpNet network (trained for the camera on first use, then cached)")
    p.add_argument("--set", nargs="*", default=[], metavar="[ALGORITHM.]FIELD=VALUE",
                   help="Config overrides of --algorithm, VALUE in JSON (e.g. sgm.radius_deg=3.8)")


def _identify(args, scenes, labels: list[str], measured=None, blend_px=None) -> list[dict]:
    """Identify ``measured`` scenes (centroids as measured; ``scenes`` is accepted for the callers
    that undistorted them already and ignored) the way :func:`jstarid.solve` does, one JSON entry per
    scene."""
    from jstarid.solution import solve_scenes

    if args.capacity < 1:
        raise ValueError("--capacity must be ≥ 1")
    solutions = solve_scenes(scenes if measured is None else measured, camera_from_args(args),
                             args.algorithm, labels=labels, capacity=args.capacity, epoch=args.epoch,
                             mag_limit=args.mag_limit,
                             name_all=args.name_all, tol_px=args.tol_px,
                             fov_max_error=args.fov_max_error, overrides=algorithm_settings(args),
                             rpnet_network=args.rpnet_network, blend_px=blend_px)
    return [s.to_dict() for s in solutions]


def _summary(entry: dict) -> str:
    if not entry["solved"]:
        return f"{entry['scene']}: not solved ({entry['detections']} detections)"
    return (f"{entry['scene']}: {len(entry['stars'])} of {entry['detections']} detections identified; "
            f"boresight RA {entry['ra_deg']:.4f}°, Dec {entry['dec_deg']:+.4f}°, roll "
            f"{entry['roll_deg']:+.3f}°, residual {entry['residual_arcsec']:.1f}″"
            + (f", focal length × {entry['focal_scale']:.4f}" if "focal_scale" in entry else ""))


def algorithm_settings(args) -> list[str]:
    """``--set`` items for ``--algorithm`` (an ``ALGORITHM.`` prefix naming another is refused)."""
    out = []
    for item in args.set:
        target, dot, rest = item.partition(".")
        if dot and "=" not in target:
            if target != args.algorithm:
                raise ValueError(f"--set {item}: this command runs {args.algorithm}, not {target}")
            item = rest
        out.append(item)
    return out


def _note_epoch(args) -> None:
    if args.epoch is None:
        print("warning: no --epoch given: star positions at the catalog's epoch J1991.25, proper "
              "motion ignored (give the observation's year, e.g. --epoch 2019.57); the output "
              "records it",
              file=sys.stderr)


def _epoch_fields(args) -> dict:
    """The solution file's record of the star positions' epoch (issue: a missing --epoch is stated)."""
    if args.epoch is None:
        return {"epoch": 1991.25, "epoch_source": "catalog (no --epoch given; proper motion ignored)"}
    return {"epoch": args.epoch, "epoch_source": "--epoch (proper motion applied)"}


def run_identify(args) -> int:
    import jstarid as js
    from jstarid.cli.centroid_input import add_true_hips, combine, read_centroid_files

    camera = camera_from_args(args)  # a bad camera fails before any file is read
    found = combine(read_centroid_files(args))
    measured = found.scenes(max(NAMING_CAPACITY, args.capacity))
    _note_epoch(args)
    solutions = _identify(args, js.undistort_scenes(measured, camera), list(found.labels), measured)
    add_true_hips(solutions, found, measured)
    for entry in solutions:
        print(_summary(entry), file=sys.stderr)
    text = json.dumps({"camera": js.camera_files.camera_to_dict(camera), "algorithm": args.algorithm,
                       **_epoch_fields(args), "scenes": solutions}, indent=1)
    if args.out is None:
        print(text)
    else:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
        print(f"wrote {args.out}", file=sys.stderr)
    return 0 if all(s["solved"] for s in solutions) else 1


def run_solve(args) -> int:
    """Raw images → centroids → identification → attitude, one line per image plus a JSON file."""
    import jstarid as js

    cam = camera_from_args(args)
    images = [js.read_image(p) for p in args.images]
    if len({im.shape for im in images}) != 1 or images[0].shape != (cam.height, cam.width):
        raise ValueError(f"every image must be {cam.height}×{cam.width} px (camera {cam.name}); "
                         f"got {sorted({im.shape for im in images})}")
    _note_epoch(args)
    measured = js.extract_centroids(np.stack(images), capacity=max(NAMING_CAPACITY, args.capacity),
                                    shard=True)
    solutions = _identify(args, js.undistort_scenes(measured, cam), [str(p) for p in args.images],
                          measured, blend_px=IMAGE_BLEND_PX)
    for entry in solutions:
        entry["image"] = entry.pop("scene")
        print(_summary({**entry, "scene": entry["image"]}))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    settings = {k: v for k, v in vars(args).items() if k != "func"}  # not the handler's address
    (out / "solutions.json").write_text(json.dumps(
        {"args": settings, "camera": js.camera_files.camera_to_dict(cam), **_epoch_fields(args),
         "solutions": solutions}, indent=1, default=str))
    print(f"wrote {out / 'solutions.json'}")
    return 0 if all(s["solved"] for s in solutions) else 1
