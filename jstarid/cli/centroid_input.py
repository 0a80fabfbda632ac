"""The centroid-file options and reading that ``jstarid identify`` and ``jstarid score`` share."""

from __future__ import annotations

import numpy as np

from jstarid.centroid_files import CentroidSet, read_centroid_set


def add_centroid_file_options(p) -> None:
    """Add ``--format`` and ``--ignore-columns`` to parser ``p``."""
    p.add_argument("--format", choices=("auto", "table", "lines", "json"), default="auto",
                   help="centroid file layout (default auto: JSON by suffix; the line layout when "
                        "the first line holds 6+ values; else a table)")
    p.add_argument("--ignore-columns", default="", metavar="NAME[,NAME…]",
                   help="table columns to skip (any other column the reader does not know is an "
                        "error)")


def read_centroid_files(args) -> list[tuple[str, CentroidSet]]:
    """``(path, set)`` of every file in ``args.files``, read with the options above."""
    ignore = [c for c in args.ignore_columns.split(",") if c.strip()]
    return [(str(path), read_centroid_set(path, ignore=ignore, format=args.format)) for path in args.files]


def combine(sets: list[tuple[str, CentroidSet]]) -> CentroidSet:
    """One set of every file's scenes, brightest first, each labelled ``path`` (a file of one scene)
    or ``path#label``."""
    labels, xy, mag, hip = [], [], [], []
    for path, found in sets:
        found = found.brightest_first()
        labels += [path] if len(found) == 1 else [f"{path}#{label}" for label in found.labels]
        xy += found.xy
        mag += found.mag
        hip += found.hip
    return CentroidSet(tuple(labels), tuple(xy), tuple(mag), tuple(hip))


def star_detections(solutions: list[dict], measured) -> list[list[int]]:
    """The detection (slot of ``measured``) of every named star of each of ``solutions``.

    ``solutions`` are :func:`jstarid.cli.frames._identify`'s entries for ``measured``: they report
    each star at its slot's pixels, so a star's slot is the one at its ``x, y``. For scenes made by
    :meth:`CentroidSet.scenes`, slot j is detection j of :meth:`CentroidSet.brightest_first`.
    """
    xy = np.asarray(measured.xy, np.float64)
    n_valid = np.asarray(measured.valid).sum(axis=1)
    return [[int(np.argmin(np.sum((xy[i, :n_valid[i]] - [s["x"], s["y"]]) ** 2, axis=1)))
             for s in entry["stars"]] for i, entry in enumerate(solutions)]


def named_detections(solutions: list[dict], found: CentroidSet, measured) -> list[np.ndarray]:
    """The HIP each detection of ``found`` (brightest first, ``measured = found.scenes(...)``) was
    given, −1 where none; detections past the capacity were never offered and stay −1."""
    out = []
    for i, slots in enumerate(star_detections(solutions, measured)):
        names = np.full(len(found.xy[i]), -1, np.int64)
        names[slots] = [star["hip"] for star in solutions[i]["stars"]]
        out.append(names)
    return out


def add_true_hips(solutions: list[dict], found: CentroidSet, measured) -> None:
    """Give every named star of a labelled scene its detection's ``true_hip`` (in place)."""
    for i, slots in enumerate(star_detections(solutions, measured)):
        if found.hip[i] is not None:
            for star, j in zip(solutions[i]["stars"], slots, strict=True):
                star["true_hip"] = int(found.hip[i][j])
