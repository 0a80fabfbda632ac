"""Cameras from what a user knows: a preset name, a small camera file, or a size and field of view.

A camera file is TOML or JSON with these keys (lengths in the units their names give)::

    name = "my tracker"          # optional; default: the file's stem
    width = 1280                 # px (or size = [1280, 960])
    height = 960
    fov_deg = 15.0               # exactly one of: fov_deg (horizontal, edge to edge),
                                 #   fov_diagonal_deg, f_px, or focal_length_mm with pixel_size_um
    cx = 639.5                   # optional principal point (px); default: the image centre
    cy = 479.5
    mag_limit = 6.5              # detection limit (V mag); default: the field's depth
                                 #   (jstarid.sky_depth.identification_depth: V 8.5 at 6°, 6.0 at 20°)
    distortion = [-0.05, 0.01]   # optional, OpenCV's order (k1, k2, p1, p2, k3), any leading part
                                 #   (or the keys k1, k2, p1, p2, k3 one by one)

:func:`load_camera` turns a preset name, such a file or a :class:`~jstarid.Camera` into a camera,
optionally resized or given another field of view (the CLI's ``--camera``, ``--size`` and ``--fov``).
A camera whose field the user describes (a file without ``mag_limit``, or a new size or field of view)
gets the catalog depth of that field (:func:`jstarid.sky_depth.identification_depth`); a preset keeps
its paper's.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path

from jstarid.camera import Camera, camera_preset, preset_names
from jstarid.sky_depth import identification_depth

__all__ = ["camera_from_dict", "camera_to_dict", "load_camera", "save_camera"]

_FOCAL_KEYS = ("fov_deg", "fov_diagonal_deg", "f_px", "focal_length_mm")
_DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")
_KEYS = {"name", "width", "height", "size", "cx", "cy", "mag_limit", "distortion", "pixel_size_um",
         *_FOCAL_KEYS, *_DISTORTION_KEYS}


def camera_from_dict(fields: Mapping, *, name: str = "custom") -> Camera:
    """A :class:`~jstarid.Camera` from a camera file's keys (module docstring).

    Args:
        fields: the keys and values (as parsed from TOML or JSON).
        name: the name when ``fields`` gives none.

    Raises:
        ValueError: an unknown key, a missing size or focal length, two ways of giving the focal
            length at once, or a value the camera refuses (its message says which).
    """
    unknown = sorted(set(fields) - _KEYS)
    if unknown:
        raise ValueError(f"unknown camera key(s) {', '.join(unknown)}; known: {', '.join(sorted(_KEYS))}")
    if "size" in fields:
        if "width" in fields or "height" in fields:
            raise ValueError("give either size or width and height, not both")
        if len(fields["size"]) != 2:
            raise ValueError(f"size must be [width, height] (px), got {fields['size']!r}")
        width, height = fields["size"]
    elif "width" in fields and "height" in fields:
        width, height = fields["width"], fields["height"]
    else:
        raise ValueError("a camera needs width and height (px), or size = [width, height]")
    width, height = _whole(width, "width"), _whole(height, "height")
    focal = [k for k in _FOCAL_KEYS if k in fields]
    if len(focal) != 1:
        raise ValueError("give the focal length exactly one way: fov_deg (horizontal), "
                         "fov_diagonal_deg, f_px, or focal_length_mm with pixel_size_um; got "
                         f"{', '.join(focal) or 'none'}")
    if (focal[0] == "focal_length_mm") != ("pixel_size_um" in fields):
        raise ValueError("focal_length_mm and pixel_size_um go together")
    f_px = _focal_px(focal[0], fields, width, height)
    if "distortion" in fields and any(k in fields for k in _DISTORTION_KEYS):
        raise ValueError("give distortion as a list or as k1, k2, p1, p2, k3, not both")
    if "distortion" in fields:
        distortion = tuple(float(c) for c in fields["distortion"])
    else:
        distortion = tuple(float(fields.get(k, 0.0)) for k in _DISTORTION_KEYS)
    camera = Camera(width, height, f_px, cx=_optional_float(fields.get("cx")),
                    cy=_optional_float(fields.get("cy")),
                    mag_limit=float(fields.get("mag_limit", 6.0)),
                    name=str(fields.get("name", name)), distortion=distortion)
    if "mag_limit" in fields:
        return camera
    return dataclasses.replace(camera, mag_limit=identification_depth(camera))


def camera_to_dict(camera: Camera) -> dict:
    """A camera file's keys for ``camera`` (its focal length as ``f_px``); inverse of
    :func:`camera_from_dict`."""
    out = {"name": camera.name, "width": camera.width, "height": camera.height,
           "f_px": camera.f_px, "cx": camera.cx, "cy": camera.cy, "mag_limit": camera.mag_limit}
    if camera.distortion:
        out["distortion"] = list(camera.distortion)
    return out


def save_camera(camera: Camera, path: str | Path) -> Path:
    """Write ``camera`` as a camera file: TOML for ``.toml``, JSON otherwise."""
    path = Path(path)
    fields = camera_to_dict(camera)
    if path.suffix.lower() == ".toml":
        lines = [f"{k} = {json.dumps(v)}" for k, v in fields.items()]  # JSON scalars/lists are TOML
        path.write_text("\n".join(lines) + "\n")
    else:
        path.write_text(json.dumps(fields, indent=1) + "\n")
    return path


def load_camera(spec: str | Path | Camera, *, size: tuple[int, int] | None = None,
                fov_deg: float | None = None) -> Camera:
    """A camera from a preset name, a camera file or a :class:`~jstarid.Camera`, optionally changed.

    Args:
        spec: a preset name (:func:`jstarid.preset_names`), the path of a ``.toml`` or ``.json``
            camera file (module docstring), or a camera.
        size: ``(width, height)`` px: the frame's new size, principal point at its centre; without
            ``fov_deg`` the horizontal field of view is kept.
        fov_deg: the horizontal field of view (deg, edge to edge) that sets the focal length.
            With ``size`` or ``fov_deg`` the detection limit becomes the new field's catalog depth.

    Returns:
        The camera; named after its spec, with ``WxH`` and the field appended when changed.

    Raises:
        ValueError: neither a preset nor a readable camera file, a malformed file, or a bad size
            or field of view.
    """
    if isinstance(spec, Camera):
        camera = spec
    elif str(spec) in preset_names():
        camera = camera_preset(str(spec))
    elif Path(spec).is_file():
        camera = _read_file(Path(spec))
    else:
        raise ValueError(f"unknown camera {str(spec)!r}: neither a preset ({', '.join(preset_names())}) "
                         "nor a camera file (.toml or .json)")
    if size is None and fov_deg is None:
        return camera
    if fov_deg is not None and not (math.isfinite(fov_deg) and 0.0 < fov_deg < 180.0):
        raise ValueError(f"the field of view must be between 0 and 180 deg, got {fov_deg}")
    width, height = camera.width, camera.height
    changes = {}
    if size is not None:
        width, height = (_whole(v, "size") for v in size)
        changes.update(width=width, height=height, cx=None, cy=None)
    fov = camera.fov_x_deg if fov_deg is None else float(fov_deg)
    changes["f_px"] = (width / 2.0) / math.tan(math.radians(fov) / 2.0)
    changes["name"] = f"{camera.name} {width}x{height} {fov:.4g}deg"
    changed = dataclasses.replace(camera, **changes)
    return dataclasses.replace(changed, mag_limit=identification_depth(changed))


def _read_file(path: Path) -> Camera:
    try:
        text = path.read_text()
        fields = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"camera file {path}: cannot read it ({err})") from None
    if not isinstance(fields, dict):
        raise ValueError(f"camera file {path}: expected a table of keys, got {type(fields).__name__}")
    try:
        return camera_from_dict(fields, name=path.stem)
    except (ValueError, TypeError) as err:
        raise ValueError(f"camera file {path}: {err}") from None


def _focal_px(key: str, fields: Mapping, width: int, height: int) -> float:
    value = float(fields[key])
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{key} must be a positive number, got {fields[key]!r}")
    if key == "f_px":
        return value
    if key == "focal_length_mm":
        pixel_um = float(fields["pixel_size_um"])
        if not (math.isfinite(pixel_um) and pixel_um > 0):
            raise ValueError(f"pixel_size_um must be a positive number, got {fields['pixel_size_um']!r}")
        return value / (pixel_um * 1e-3)
    if value >= 180.0:
        raise ValueError(f"{key} must be below 180 deg, got {value}")
    half_extent = width / 2.0 if key == "fov_deg" else math.hypot(width, height) / 2.0
    return half_extent / math.tan(math.radians(value) / 2.0)


def _whole(value, what: str) -> int:
    if isinstance(value, bool) or not float(value).is_integer() or int(value) < 2:
        raise ValueError(f"{what} must be a whole number of pixels ≥ 2, got {value!r}")
    return int(value)


def _optional_float(value) -> float | None:
    return None if value is None else float(value)
