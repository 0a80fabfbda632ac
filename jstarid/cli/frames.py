"""``jstarid identify`` (centroid files) and ``jstarid solve`` (raw images): names and attitude."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from jstarid.cli.cameras import FRAME_CAMERA, add_camera_options, camera_from_args
from jstarid.cli.centroid_input import add_centroid_file_options
from jstarid.solution import (
    CENTROID_CAPACITY,
    IMAGE_BLEND_PX,
    IMAGE_CAPACITY,
    NAMING_CAPACITY,
    image_detections,
)


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
    centroid_file_command(i, "centroid files (.csv, .tsv, .txt or .json)")
    i.add_argument("--out", type=Path, default=None, help="write the JSON here instead of stdout")
    i.set_defaults(func=run_identify)
    s = sub.add_parser(
        "solve", help="identify the stars of raw images (FITS, TIFF, PNG) and print the attitude; "
                      "writes a FITS WCS per solved image; exit 1 when an image is not solved",
        description="Raw images → centroids → star names → attitude. Writes <out>/solutions.json and, "
                    "per solved image, <out>/<stem>.wcs (a FITS WCS header, TAN or TAN-SIP) and, for "
                    "FITS input, <out>/<stem>.fits (the image with that WCS in its header). From a "
                    "FITS header: DATE-OBS gives the epoch when --epoch is not given, and FOCALLEN / "
                    "XPIXSZ the focal length (and the image its size) when neither --camera nor --fov "
                    "is given.")
    s.add_argument("images", nargs="+", help="image files (FITS, TIFF, PNG, …; colour is taken as "
                                             "luminance), all from one camera")
    _frame_options(s, camera=FRAME_CAMERA, capacity=IMAGE_CAPACITY)
    s.add_argument("--out", default="results/solve", help="results directory (default results/solve)")
    s.add_argument("--annotate", action="store_true",
                   help="also write <out>/<stem>.png: the frame with each named star circled and "
                        "labelled HIP n")
    # no --camera given is told apart from the default preset: a FITS header may give the focal length
    s.set_defaults(func=run_solve, camera=None)


def centroid_file_command(p, files_help: str) -> None:
    """The arguments of a command on centroid files (``identify``, ``score``): the files, the frame
    options and the file-layout options."""
    p.add_argument("files", nargs="+", type=Path, help=files_help)
    _frame_options(p, camera=FRAME_CAMERA, capacity=CENTROID_CAPACITY)
    add_centroid_file_options(p)


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
                   help="how far off the field of view (focal length) may be, relative: unsolved "
                        "frames are tried again at 1 %% steps out to it, and a frame needing more "
                        "counts as not solved (default 0.1)")
    p.add_argument("--rpnet-network", choices=("quick", "table3"), default="quick",
                   help="RpNet network (trained for the camera on first use, then cached)")
    p.add_argument("--set", nargs="*", default=[], metavar="[ALGORITHM.]FIELD=VALUE",
                   help="Config overrides of --algorithm, VALUE in JSON (e.g. sgm.radius_deg=3.8)")


def _identify(args, measured, labels: list[str], blend_px=None) -> list[dict]:
    """Identify ``measured`` scenes (centroids as measured, brightest first) the way
    :func:`jstarid.solve` does, one JSON entry per scene."""
    from jstarid.solution import solve_scenes

    if args.capacity < 1:
        raise ValueError("--capacity must be ≥ 1")
    solutions = solve_scenes(measured, camera_from_args(args),
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
            + (f", focal length × {entry['focal_scale']:.4f}" if "focal_scale" in entry else "")
            + f"; false-match probability ≤ {entry['false_match_probability']:.1e}")


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
    solutions = _identify(args, measured, list(found.labels))
    add_true_hips(solutions, found)
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
    """Raw images → centroids → identification → attitude, one line per image, a JSON file and the
    standard outputs (a ``.wcs`` per solved image, a FITS copy with its WCS for FITS input, and with
    ``--annotate`` a PNG of the named stars)."""
    import jstarid as js
    from jstarid.image_files import read_image_file

    files = [read_image_file(p) for p in args.images]
    _camera_from_headers(args, files)
    cam = camera_from_args(args)
    measured = image_detections([f.pixels for f in files], cam)
    header_epoch = _epoch_from_headers(args, files)
    _note_epoch(args)
    solutions = _identify(args, measured, [str(p) for p in args.images], blend_px=IMAGE_BLEND_PX)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for entry, file, stem in zip(solutions, files, _stems(args.images), strict=True):
        entry["image"] = entry.pop("scene")
        if file.epoch is not None:
            entry["observation_epoch"] = file.epoch
        entry.update(_write_outputs(args, cam, entry, file, out, stem))
        print(_summary({**entry, "scene": entry["image"]}))
    settings = {k: v for k, v in vars(args).items() if k != "func"}  # not the handler's address
    epoch = _epoch_fields(args)
    if header_epoch:
        epoch["epoch_source"] = "DATE-OBS of the FITS headers (proper motion applied)"
    (out / "solutions.json").write_text(json.dumps(
        {"args": settings, "camera": js.camera_files.camera_to_dict(cam), **epoch,
         "solutions": solutions}, indent=1, default=str))
    print(f"wrote {out / 'solutions.json'}" + ("" if not any("wcs" in e for e in solutions) else
                                               " and a WCS per solved image"))
    return 0 if all(s["solved"] for s in solutions) else 1


def _camera_from_headers(args, files) -> None:
    """With neither ``--camera`` nor ``--fov``, the focal length of the first FITS header that gives
    one (FOCALLEN / XPIXSZ) and the image's size become ``--fov`` and ``--size``; otherwise the
    default preset stands. Edits ``args``, so every later step builds the same camera."""
    header_focal = [f.focal_px for f in files if f.focal_px is not None]
    use_header = args.camera is None and args.fov is None and bool(header_focal)
    if args.camera is None:
        args.camera = FRAME_CAMERA
    if not use_header:
        return
    height, width = files[0].pixels.shape
    if args.size is None:
        args.size = f"{width}x{height}"
    else:
        try:
            width = int(args.size.lower().replace("×", "x").split("x")[0])
        except ValueError:
            return  # camera_from_args reports the malformed --size
    args.fov = float(np.degrees(2.0 * np.arctan(width / 2.0 / header_focal[0])))
    spread = max(header_focal) / min(header_focal) - 1.0
    print(f"camera: focal length {header_focal[0]:.1f} px (field {args.fov:.3f}°) from the FITS "
          f"header's FOCALLEN / XPIXSZ" + (f"; the headers differ by {spread:.1%}, the first kept"
                                           if spread > 1e-3 else ""), file=sys.stderr)


def _epoch_from_headers(args, files) -> bool:
    """Without ``--epoch``, the mean DATE-OBS of the FITS headers that give one becomes it (proper
    motion over the frames' spread is far below a pixel unless it spans decades); True when used."""
    epochs = [f.epoch for f in files if f.epoch is not None]
    if args.epoch is not None or not epochs:
        return False
    args.epoch = round(float(np.mean(epochs)), 4)
    if max(epochs) - min(epochs) > 1.0:
        print(f"warning: the images' DATE-OBS span {min(epochs):.2f}–{max(epochs):.2f}; star "
              f"positions at their mean, {args.epoch:.2f}", file=sys.stderr)
    return True


def _stems(paths) -> list[str]:
    """Output names: each image's name without its suffix (``a.fits.gz`` → ``a``), ``-2``, ``-3`` …
    appended where two images share one."""
    seen: dict[str, int] = {}
    out = []
    for p in paths:
        name = Path(p).name
        for packed in (".gz", ".fz", ".bz2"):
            name = name.removesuffix(packed)
        stem = Path(name).stem or name
        seen[stem] = seen.get(stem, 0) + 1
        out.append(stem if seen[stem] == 1 else f"{stem}-{seen[stem]}")
    return out


def _write_outputs(args, camera, entry: dict, file, out: Path, stem: str) -> dict:
    """The standard outputs of one image; returns the entry's record of the files written."""
    from jstarid.plotting import save_solution_plot
    from jstarid.wcs import wcs_from_solution, write_fits_with_wcs, write_wcs

    written = {}
    if entry["solved"]:
        wcs = wcs_from_solution(camera, entry)
        written["wcs"] = str(write_wcs(wcs, out / f"{stem}.wcs"))
        if file.header is not None:  # FITS input
            target = out / f"{stem}.fits"
            if target.resolve() == Path(entry["image"]).resolve():  # never over the input
                target = out / f"{stem}-wcs.fits"
            written["fits"] = str(write_fits_with_wcs(entry["image"], wcs, target))
    if args.annotate:
        save_solution_plot(file.pixels, entry, out / f"{stem}.png")
        written["annotated"] = str(out / f"{stem}.png")
    return written
