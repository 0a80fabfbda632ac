"""Centroid files (an edge utility): a user's detections, one scene or many, optionally labelled.

Pixels follow conventions §1 (origin at the centre of pixel (0, 0), x along columns, y along rows).
Three layouts; ``format="auto"`` picks one from the suffix and the first line:

- **Table** (``.csv``, ``.tsv``, ``.txt``, …): one detection per line, cells separated by commas,
  tabs, semicolons or spaces; ``#`` starts a comment. A header names the columns, in any order and
  any case:

  ===========  =====================================================================================
  ``x``, ``y`` centroid (px), required
  brightness   ``mag`` / ``magnitude`` / ``v`` / ``vmag`` / ``hpmag``, or ``flux`` (read as the
               relative magnitude −2.5 log10 flux). An empty cell or a non-positive flux becomes
               the file's faintest + 1 mag: the detection stays, offered last. A magnitude wins
               over a flux.
  ``hip``      the detection's true Hipparcos number, −1 for a false star (``hip_id``, ``true_hip``,
               ``id``)
  ``scene``    a label, text or number (``image``, ``frame``, ``file``); scenes keep the order in
               which their labels first appear
  ===========  =====================================================================================

  Any other column is an error unless it is named in ``ignore``: a column read by a wrong guess
  (``x, y, hip`` taken for magnitudes) costs more than a line asking for ``--ignore-columns``.
  Without a scene column, blank lines separate scenes. A file without a header holds
  ``x, y[, magnitude]`` per line.
- **Lines** (benchmark test sets): each scene is one line of ``x y mag`` triples
  (``x1 y1 m1 x2 y2 m2 …``), followed by a line of as many true Hipparcos numbers, −1 for a false
  star. ``auto`` recognises it when the file has no header and its first line holds six values or
  more (a table line holds three at most); a set whose first scene has one detection needs
  ``format="lines"``.
- **JSON** (``.json``): a scene is ``[[x, y, mag], …]`` (or ``[x, y]`` pairs) or
  ``{"x": […], "y": […], "mag": […], "hip": […]}`` (``mag`` and ``hip`` optional); the file holds
  one scene, a list of scenes, or ``{"scenes": [...]}``.

Without magnitudes the file's order is taken as brightest first (:func:`jstarid.scenes_from_centroids`).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

__all__ = ["CentroidSet", "read_centroid_set", "read_centroids"]

_COLUMNS = {  # role → accepted names (lower case)
    "x": ("x",), "y": ("y",), "mag": ("mag", "magnitude", "v", "vmag", "hpmag"), "flux": ("flux",),
    "hip": ("hip", "hip_id", "true_hip", "id"), "scene": ("scene", "image", "frame", "file"),
}
_ROLE = {name: role for role, names in _COLUMNS.items() for name in names}
_KNOWN = "; ".join(" / ".join(names) for names in _COLUMNS.values())
_FORMATS = ("auto", "table", "lines", "json")


@dataclasses.dataclass(frozen=True, eq=False)
class CentroidSet:
    """Scenes of detections as a file gives them (host arrays, the file's order).

    Attributes:
        labels: B scene labels (the scene column's values, else ``"0"``, ``"1"``, …).
        xy: B arrays (n_i, 2) float64 centroids (px).
        mag: B arrays (n_i,) float64 magnitudes (smaller is brighter), ``None`` where not given.
        hip: B arrays (n_i,) int64 true Hipparcos numbers (−1: a false star), ``None`` where not given.
    """

    labels: tuple[str, ...]
    xy: tuple[np.ndarray, ...]
    mag: tuple[np.ndarray | None, ...]
    hip: tuple[np.ndarray | None, ...]

    def __post_init__(self):
        if not len(self.labels) == len(self.xy) == len(self.mag) == len(self.hip):
            raise ValueError("labels, xy, mag and hip must hold one entry per scene")
        for i, (xy, mag, hip) in enumerate(zip(self.xy, self.mag, self.hip, strict=True)):
            n = len(xy)
            if np.shape(xy) != (n, 2) or any(a is not None and np.shape(a) != (n,) for a in (mag, hip)):
                raise ValueError(f"scene {self.labels[i]!r}: xy must be (n, 2), mag and hip (n,)")

    def __len__(self) -> int:
        return len(self.labels)

    @property
    def labelled(self) -> bool:
        """Every scene carries true Hipparcos numbers."""
        return len(self) > 0 and all(h is not None for h in self.hip)

    def brightest_first(self) -> CentroidSet:
        """The same detections sorted by magnitude (stable; unchanged where there are none), so that
        detection j of a scene is slot j of :meth:`scenes` (for j below the capacity)."""
        xy, mag, hip = [], [], []
        for x, m, h in zip(self.xy, self.mag, self.hip, strict=True):
            order = np.arange(len(x)) if m is None else np.argsort(m, kind="stable")
            xy.append(x[order])
            mag.append(None if m is None else m[order])
            hip.append(None if h is None else h[order])
        return CentroidSet(self.labels, tuple(xy), tuple(mag), tuple(hip))

    def scenes(self, capacity: int = 64, *, camera=None, catalog=None):
        """A :class:`~jstarid.Scene` batch (:func:`jstarid.scenes_from_centroids`).

        Args:
            capacity: static N; a scene with more detections keeps its brightest N (``overflow``).
            camera: the measuring :class:`~jstarid.Camera`, whose distortion is undone; ``None``:
                pinhole pixels.
            catalog: a :class:`~jstarid.Catalog` to turn true Hipparcos numbers into ``truth`` rows
                (−1 for a false star or a star outside it); ``None``: every truth −1.

        Returns:
            B scenes; slot j of scene i is detection j of :meth:`brightest_first`.
        """
        import jax.numpy as jnp

        from jstarid.scene import scenes_from_centroids

        s = self.brightest_first()
        mags = list(s.mag)
        if all(m is None for m in mags):
            mags = None
        else:  # a scene without magnitudes keeps its order, as scenes_from_centroids would
            mags = [np.arange(len(x), dtype=float) if m is None else m for x, m in zip(s.xy, mags,
                                                                                        strict=True)]
        packed = scenes_from_centroids(list(s.xy), mags, capacity=capacity, camera=camera)
        if catalog is None or all(h is None for h in s.hip):
            return packed
        truth = np.full((len(s), capacity), -1, np.int32)
        for i, h in enumerate(s.hip):
            if h is not None and len(h):
                h = h[:capacity]
                truth[i, :len(h)] = np.where(h >= 0, catalog.row_of_hip(h), -1)
        return dataclasses.replace(packed, truth=jnp.asarray(truth))


def read_centroids(path: str | Path) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
    """``(xy_list, mag_list)`` of every scene in a centroid file (:func:`read_centroid_set`, kept
    for the callers that want the two lists of :func:`jstarid.scenes_from_centroids`)."""
    found = read_centroid_set(path)
    return list(found.xy), list(found.mag)


def read_centroid_set(path: str | Path, *, ignore: Iterable[str] = (), format: str = "auto") -> CentroidSet:
    """Every scene of a centroid file (see the module docstring for the layouts).

    Args:
        path: a table (CSV, TSV, whitespace), line-layout or JSON file.
        ignore: header names (any case) to skip rather than refuse.
        format: ``"auto"``, ``"table"``, ``"lines"`` or ``"json"``.

    Returns:
        A :class:`CentroidSet` in the file's order.

    Raises:
        ValueError: a missing, empty or malformed file, an unknown or missing column (the message
            names the line, column or scene).
    """
    if format not in _FORMATS:
        raise ValueError(f"format must be one of {', '.join(_FORMATS)}, got {format!r}")
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"cannot read the centroid file {path}: {err}") from None
    if not text.strip():
        raise ValueError(f"{path} is empty")
    if format == "json" or (format == "auto" and path.suffix.lower() == ".json"):
        found = _from_json(text, path)
    else:
        lines = _lines(text)
        header = _header(lines)
        if format == "lines" or (format == "auto" and header is None and lines
                                 and len(lines[0][1]) >= 6 and len(lines[0][1]) % 3 == 0):
            if header is not None:
                raise ValueError(f"{path}, line {lines[0][0]}: the line layout has no header")
            found = _from_lines(lines, path)
        else:
            found = _from_table(lines, header, path, {_name(c) for c in ignore})
    if not found:
        raise ValueError(f"{path} holds no centroids")
    return found


def _name(cell: str) -> str:
    return cell.strip().strip("\"'").strip().lower()


def _cells(line: str) -> list[str]:
    for sep in (",", "\t", ";"):
        if sep in line:
            return [c.strip() for c in line.split(sep)]
    return line.split()


def _lines(text: str) -> list[tuple[int, list[str] | None]]:
    """(line number, cells) of every line, ``None`` cells for a blank (or comment-only) line."""
    out = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        out.append((number, _cells(line) if line else None))
    while out and out[0][1] is None:
        out.pop(0)
    return out


def _header(lines) -> list[str] | None:
    """The first line's names when it is not all numbers (it is then removed from ``lines``)."""
    if not lines:
        return None
    try:
        [float(c) for c in lines[0][1]]
    except ValueError:
        return [_name(c) for c in lines.pop(0)[1]]
    return None


def _roles(header: list[str], ignore: set[str], path: Path) -> dict[str, int]:
    roles: dict[str, int] = {}
    unknown = []
    for k, name in enumerate(header):
        if name in ignore:
            continue
        role = _ROLE.get(name)
        if role is None:
            unknown.append(repr(name) if name else f"an unnamed column ({k + 1})")
        elif role in roles:
            raise ValueError(f"{path}: columns {header[roles[role]]!r} and {name!r} both give the "
                             f"{role}; name one in ignore (--ignore-columns)")
        else:
            roles[role] = k
    if unknown:
        raise ValueError(f"{path}: unknown column {', '.join(unknown)} (known: {_KNOWN}); skip it with "
                         f"ignore=(...) or --ignore-columns")
    for axis in ("x", "y"):
        if axis not in roles:
            raise ValueError(f"{path}: no {axis!r} column (header: {', '.join(header)})")
    if "mag" in roles:
        roles.pop("flux", None)  # a magnitude wins over a flux
    return roles


def _number(cell: str, path: Path, number: int, column: str, *, empty: bool = False) -> float:
    if empty and not cell:
        return np.nan  # a brightness not measured: the detection is kept, as the faintest
    try:
        value = float(cell)
    except ValueError:
        raise ValueError(f"{path}, line {number}: {cell!r} in column {column!r} is not a number") from None
    if not np.isfinite(value):
        raise ValueError(f"{path}, line {number}: values must be finite (column {column!r})")
    return value


def _hip(cell: str, path: Path, number: int) -> int:
    value = _number(cell, path, number, "hip")
    if value != int(value) or value < -1:
        raise ValueError(f"{path}, line {number}: a true id must be a Hipparcos number or −1, got {cell!r}")
    return int(value)


def _from_table(lines, header, path: Path, ignore: set[str]) -> CentroidSet:
    if header is None:
        return _headerless(lines, path)
    roles = _roles(header, ignore, path)
    groups: dict[str, list] = {}
    block = 0  # without a scene column, blank lines separate scenes
    for number, cells in lines:
        if cells is None:
            if "scene" not in roles and groups.get(str(block)):
                block += 1
            continue
        if len(cells) != len(header):
            raise ValueError(f"{path}, line {number}: expected {len(header)} values ({', '.join(header)}), "
                             f"got {len(cells)}")
        label = cells[roles["scene"]] if "scene" in roles else str(block)
        row = [_number(cells[roles[c]], path, number, header[roles[c]]) for c in ("x", "y")]
        for role in ("mag", "flux"):
            if role in roles:
                row.append(_number(cells[roles[role]], path, number, header[roles[role]], empty=True))
        if "hip" in roles:
            row.append(_hip(cells[roles["hip"]], path, number))
        groups.setdefault(label, []).append(row)
    if not groups:
        return CentroidSet((), (), (), ())
    arrays = [np.asarray(g, np.float64) for g in groups.values()]
    bright = "mag" in roles or "flux" in roles
    mags = [a[:, 2] if bright else None for a in arrays]
    if "flux" in roles:
        mags = _flux_to_mag(mags, path)
    elif bright:
        mags = _fill_faintest(mags, path)
    hips = [a[:, -1].astype(np.int64) if "hip" in roles else None for a in arrays]
    return CentroidSet(tuple(groups), tuple(a[:, :2] for a in arrays), tuple(mags), tuple(hips))


def _flux_to_mag(fluxes: list[np.ndarray], path: Path) -> list[np.ndarray]:
    """Relative magnitudes −2.5 log10 flux; a missing or non-positive flux becomes NaN, then the
    file's faintest + 1 (:func:`_fill_faintest`)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        mags = [np.where(f > 0, -2.5 * np.log10(np.where(f > 0, f, 1.0)), np.nan) for f in fluxes]
    return _fill_faintest(mags, path, what="positive flux")


def _fill_faintest(mags: list[np.ndarray], path: Path, what: str = "magnitude") -> list[np.ndarray]:
    """Missing magnitudes (NaN) set to the file's faintest + 1 mag: kept, and offered last."""
    every = np.concatenate(mags)
    if not np.any(np.isfinite(every)):
        raise ValueError(f"{path}: no {what} in the brightness column")
    faintest = np.nanmax(every) + 1.0
    return [np.where(np.isfinite(m), m, faintest) for m in mags]


def _headerless(lines, path: Path) -> CentroidSet:
    blocks: list[list] = [[]]
    width = None
    for number, cells in lines:
        if cells is None:
            if blocks[-1]:
                blocks.append([])
            continue
        try:
            values = [float(c) for c in cells]
        except ValueError:
            raise ValueError(f"{path}, line {number}: {' '.join(cells)!r} is not numbers "
                             "(expected x, y[, magnitude], or a header line first)") from None
        if len(values) not in (2, 3) or (width is not None and len(values) != width):
            raise ValueError(f"{path}, line {number}: expected x, y[, magnitude] on every line, got "
                             f"{len(values)} values (other columns need a header naming them)")
        width = len(values)
        if not np.all(np.isfinite(values)):
            raise ValueError(f"{path}, line {number}: values must be finite")
        blocks[-1].append(values)
    arrays = [np.asarray(b, np.float64) for b in blocks if b]
    return CentroidSet(tuple(str(k) for k in range(len(arrays))), tuple(a[:, :2] for a in arrays),
                       tuple(a[:, 2] if width == 3 else None for a in arrays), (None,) * len(arrays))


def _from_lines(lines, path: Path) -> CentroidSet:
    rows = [(number, cells) for number, cells in lines if cells is not None]
    if len(rows) % 2:
        raise ValueError(f"{path}, line {rows[-1][0]}: a scene line (x y mag triples) without its line "
                         "of true ids")
    xy, mag, hip = [], [], []
    for (n1, coords), (n2, ids) in zip(rows[::2], rows[1::2], strict=True):
        if len(coords) != 3 * len(ids):
            raise ValueError(f"{path}, lines {n1}–{n2}: a scene line of 3n values (x y mag triples) must "
                             f"be followed by n true ids; got {len(coords)} values, then {len(ids)}")
        values = np.asarray([_number(c, path, n1, "x y mag") for c in coords]).reshape(-1, 3)
        xy.append(values[:, :2])
        mag.append(values[:, 2])
        hip.append(np.asarray([_hip(c, path, n2) for c in ids], np.int64))
    return CentroidSet(tuple(str(k) for k in range(len(xy))), tuple(xy), tuple(mag), tuple(hip))


def _from_json(text: str, path: Path) -> CentroidSet:
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
    scenes = [_json_scene(s, path, i) for i, s in enumerate(data)]
    return CentroidSet(tuple(str(k) for k in range(len(scenes))), tuple(s[0] for s in scenes),
                       tuple(s[1] for s in scenes), tuple(s[2] for s in scenes))


def _is_row(item) -> bool:
    return isinstance(item, list) and all(isinstance(v, int | float) for v in item)


def _json_scene(scene, path: Path, i: int):
    hip = None
    if isinstance(scene, dict):
        try:
            columns = [scene["x"], scene["y"]] + ([scene["mag"]] if scene.get("mag") is not None else [])
            arr = np.asarray(columns, np.float64).T
            if scene.get("hip") is not None:
                hip = np.asarray(scene["hip"], np.float64)
                if hip.shape != (len(arr),):
                    raise ValueError
        except (KeyError, ValueError, TypeError):
            raise ValueError(f"{path}, scene {i}: expected {{\"x\": [...], \"y\": [...], \"mag\": [...], "
                             "\"hip\": [...]}} of equal lengths") from None
        if hip is not None and not np.all((hip == np.round(hip)) & (hip >= -1)):
            raise ValueError(f"{path}, scene {i}: true ids must be Hipparcos numbers or −1")
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
    return arr[:, :2], (arr[:, 2] if arr.shape[1] == 3 else None), (
        None if hip is None else hip.astype(np.int64))
