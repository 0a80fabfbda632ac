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


def read_labelled_files(args) -> list[tuple[str, CentroidSet]]:
    """:func:`read_centroid_files`, refusing a file without true ids."""
    sets = read_centroid_files(args)
    for path, found in sets:
        if not found.labelled:
            raise ValueError(f"{path} has no true ids (a 'hip' column, a JSON \"hip\" list, or the "
                             "line layout's id lines)")
    return sets


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


def named_detections(solutions: list[dict], found: CentroidSet) -> list[np.ndarray]:
    """The HIP each detection of ``found`` (brightest first, the scenes ``solutions`` were made from:
    a star's ``detection`` is its slot) was given, −1 where none; detections past the capacity were
    never offered and stay −1."""
    out = []
    for entry, xy in zip(solutions, found.xy, strict=True):
        names = np.full(len(xy), -1, np.int64)
        names[[star["detection"] for star in entry["stars"]]] = [star["hip"] for star in entry["stars"]]
        out.append(names)
    return out


def add_true_hips(solutions: list[dict], found: CentroidSet) -> None:
    """Give every named star of a labelled scene its detection's ``true_hip`` (in place)."""
    for entry, hip in zip(solutions, found.hip, strict=True):
        if hip is not None:
            for star in entry["stars"]:
                star["true_hip"] = int(hip[star["detection"]])
