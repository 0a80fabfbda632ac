"""``jstarid calibrate``: frames of one camera solved with a rough camera, then the camera fitted to
all their names (:func:`jstarid.calibration.calibrate`) and written as a camera file."""

from __future__ import annotations

import sys
from pathlib import Path

from jstarid.cli.cameras import FRAME_CAMERA, camera_from_args
from jstarid.solution import IMAGE_CAPACITY

ROUNDS = 2  # solve → fit, then solve again with the fitted camera (more names) → fit


def add_commands(sub) -> None:
    from jstarid.cli.frames import _frame_options

    p = sub.add_parser(
        "calibrate", help="frames (images or centroid files) of one camera → focal length, principal "
                          "point and lens distortion fitted over all of them → a camera file",
        description="Solve every frame with the rough camera (--camera, or --size/--fov), fit one "
                    "camera to all the named stars (focal length, principal point, Brown–Conrady "
                    "k1, k2, p1, p2; blends left out), solve again with it and fit again, then write "
                    "the camera file (--out) that later commands take as --camera.")
    p.add_argument("frames", nargs="+", type=Path, help="images (FITS, TIFF, PNG) or centroid files")
    _frame_options(p, camera=FRAME_CAMERA, capacity=IMAGE_CAPACITY)
    p.add_argument("--fit", default=None, metavar="NAME[,NAME…]",
                   help="parameters to fit (f_px, cx, cy, k1, k2, p1, p2; default all of them with "
                        "60 or more named stars, else f_px, k1, k2)")
    p.add_argument("--out", type=Path, default=Path("camera.toml"),
                   help="the camera file to write (.toml or .json; default camera.toml)")
    p.set_defaults(func=run_calibrate)


def run_calibrate(args) -> int:
    import jstarid as js
    from jstarid.calibration import calibrate
    from jstarid.cli.frames import _note_epoch, algorithm_settings

    camera = camera_from_args(args)
    fit = None if args.fit is None else [n.strip() for n in args.fit.split(",") if n.strip()]
    _note_epoch(args)
    frames = [str(p) for p in args.frames]
    for k in range(ROUNDS):
        solutions = js.solve(frames, camera, args.algorithm, epoch=args.epoch, mag_limit=args.mag_limit,
                             capacity=args.capacity, tol_px=args.tol_px,
                             fov_max_error=args.fov_max_error, overrides=algorithm_settings(args),
                             rpnet_network=args.rpnet_network)
        solutions = solutions if isinstance(solutions, list) else [solutions]
        solved = sum(s.solved for s in solutions)
        result = calibrate(solutions, camera, epoch=args.epoch, fit=fit)
        print(f"round {k + 1}: {solved} of {len(solutions)} frames solved; {result.stars} named stars "
              f"of {result.frames} frames; RMS {result.rms_before_px:.2f} px with the camera given, "
              f"{result.rms_after_px:.2f} px fitted ({', '.join(result.fitted)})", file=sys.stderr)
        camera = result.camera
    k1, k2, p1, p2 = (tuple(camera.distortion) + (0.0,) * 4)[:4]
    print(f"focal length {camera.f_px:.2f} px (field {camera.fov_x_deg:.4f}°), principal point "
          f"({camera.cx:.2f}, {camera.cy:.2f}) px, k1 {k1:+.5f}, k2 {k2:+.5f}, p1 {p1:+.6f}, "
          f"p2 {p2:+.6f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    print(f"wrote {js.save_camera(camera, args.out)}")
    return 0
