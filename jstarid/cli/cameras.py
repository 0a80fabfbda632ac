"""The camera options every command shares: ``--camera PRESET|FILE``, ``--size`` and ``--fov``."""

from __future__ import annotations

from jstarid.solution import DEFAULT_CAMERA as FRAME_CAMERA  # noqa: F401  (the commands' default)


def add_camera_options(p, *, default: str) -> None:
    """Add ``--camera``, ``--size`` and ``--fov`` to parser ``p`` (``default``: a preset name)."""
    p.add_argument("--camera", default=default,
                   help=f"camera preset (`jstarid list`) or camera file (.toml/.json: size, field of "
                        f"view or focal length, principal point, distortion, detection limit; see "
                        f"the README); default {default}")
    p.add_argument("--size", default=None, metavar="WxH",
                   help="image size in px (e.g. 1280x960), principal point at the centre; replaces "
                        "the camera's (its horizontal field of view kept unless --fov is given)")
    p.add_argument("--fov", type=float, default=None, metavar="DEG",
                   help="horizontal field of view (deg, edge to edge); replaces the camera's")


def camera_from_args(args):
    """The :class:`~jstarid.Camera` the options of :func:`add_camera_options` describe."""
    import jstarid as js

    size = None
    if args.size is not None:
        parts = args.size.lower().replace("×", "x").split("x")
        try:
            size = tuple(int(v) for v in parts)
        except ValueError:
            size = ()
        if len(size) != 2:
            raise ValueError(f"--size must be WIDTHxHEIGHT in px (e.g. 1280x960), got {args.size!r}")
    return js.load_camera(args.camera, size=size, fov_deg=args.fov)
