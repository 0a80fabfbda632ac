"""Centroid files (an edge utility): a user's detections, one scene or many, read into lists.

Two formats, chosen by the file's suffix:

- **CSV / text** (``.csv``, ``.txt``): one detection per line, ``x, y[, magnitude]`` (commas or
  whitespace; px with the origin at the centre of pixel (0, 0), x to the right, y down). A line
  that is not numbers is a header (allowed first) or an error; ``#`` starts a comment. Scenes are
  separated by blank lines, or given by a leading ``scene`` column when the header names it
  (``scene, x, y, magnitude``).
- **JSON** (``.json``): a scene is ``[[x, y, mag], …]`` (or ``[x, y]`` pairs) or
  ``{"x": […], "y": […], "mag": […]}``; the file holds one scene, a list of scenes, or
  ``{"scenes": [...]}``.

Without magnitudes the file's order is taken as brightest first (:func:`jstarid.scenes_from_centroids`).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

__all__ = ["read_centroids"]


def read_centroids(path: str | Path) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
    """``(xy_list, mag_list)`` of every scene in a centroid file (see the module docstring).

    Returns:
        B arrays (n_i, 2) of centroids (px) and B arrays (n_i,) of magnitudes (``None`` where the
        file gives none); ready for :func:`jstarid.scenes_from_centroids`.

    Raises:
        ValueError: a missing, empty or malformed file (the message names the line or scene).
    """
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"cannot read the centroid file {path}: {err}") from None
    if not text.strip():
        raise ValueError(f"{path} is empty")
    scenes = _from_json(text, path) if path.suffix.lower() == ".json" else _from_csv(text, path)
    if not scenes:
        raise ValueError(f"{path} holds no centroids")
    xy = [s[:, :2] for s in scenes]
    mags = [s[:, 2] if s.shape[1] == 3 else None for s in scenes]
    return xy, mags


def _from_csv(text: str, path: Path) -> list[np.ndarray]:
    scenes: dict = {}
    current: list = []
    blocks: list = []
    has_scene_column = False
    width = None
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            if current:
                blocks.append(current)
                current = []
            continue
        cells = [c for c in re.split(r"[,\s;]+", line) if c]
        try:
            values = [float(c) for c in cells]
        except ValueError:
            if width is None and not blocks and not current:  # a header
                has_scene_column = cells[0].lower() == "scene"
                continue
            raise ValueError(f"{path}, line {number}: {raw.strip()!r} is not numbers "
                             "(expected x, y[, magnitude])") from None
        expected = (3, 4) if has_scene_column else (2, 3)
        if len(values) not in expected or (width is not None and len(values) != width):
            raise ValueError(f"{path}, line {number}: expected "
                             f"{'scene, ' if has_scene_column else ''}x, y[, magnitude] on every "
                             f"line, got {len(values)} values")
        width = len(values)
        if not np.all(np.isfinite(values)):
            raise ValueError(f"{path}, line {number}: values must be finite")
        if has_scene_column:
            scenes.setdefault(values[0], []).append(values[1:])
        else:
            current.append(values)
    if current:
        blocks.append(current)
    groups = list(scenes.values()) if has_scene_column else blocks
    return [np.asarray(g, np.float64) for g in groups]


def _from_json(text: str, path: Path) -> list[np.ndarray]:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON: {err}") from None
    if isinstance(data, dict) and "scenes" in data:
        data = data["scenes"]
    if isinstance(data, dict) or (isinstance(data, list) and data and _is_row(data[0])):
        data = [data]  # one scene
    if not isinstance(data, list):
        raise ValueError(f"{path}: expected a scene, a list of scenes or {{\"scenes\": [...]}}")
    return [_scene(s, path, i) for i, s in enumerate(data)]


def _is_row(item) -> bool:
    return isinstance(item, list) and all(isinstance(v, int | float) for v in item)


def _scene(scene, path: Path, i: int) -> np.ndarray:
    if isinstance(scene, dict):
        try:
            columns = [scene["x"], scene["y"]] + ([scene["mag"]] if scene.get("mag") is not None else [])
            arr = np.asarray(columns, np.float64).T
        except (KeyError, ValueError, TypeError):
            raise ValueError(f"{path}, scene {i}: expected {{\"x\": [...], \"y\": [...], "
                             "\"mag\": [...]}} of equal lengths") from None
    else:
        try:
            arr = np.asarray(scene, np.float64)
        except (ValueError, TypeError):
            arr = np.zeros((0, 0))
        if arr.ndim != 2 or arr.shape[1] not in (2, 3):
            raise ValueError(f"{path}, scene {i}: expected [[x, y, magnitude], ...] rows")
    if arr.shape[0] == 0:
        raise ValueError(f"{path}, scene {i} has no centroids")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{path}, scene {i}: values must be finite")
    return arr
