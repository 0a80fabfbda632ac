"""The experiment harness: one results layout, one config style, timing, memory and provenance.

Every experiment (the scripts in ``experiments/``, the CLI, a notebook) writes the same directory::

    results/<name>/
        config.json    the settings, the seed, and where the figures come from (commit, machine,
                       command line, date)
        results.json   the measured values (rows of a table, per-level rates, timings)
        table.md       the human-readable table
        *.png          figures, drawn from results.json only (never recomputed)

Algorithm settings are changed with one style everywhere: ``--set FIELD=VALUE`` (VALUE is JSON,
e.g. ``--set max_error_deg=0.2 verify=false``), checked against the config's fields
(:func:`with_overrides`).

Usage::

    from jstarid import experiment as ex

    parser = ex.parser("Reproduce Fig. 6", out="results/fig6")   # --out --seed --quick --set
    args = parser.parse_args()
    config = ex.with_overrides(mlv.Config(), args.set)
    with ex.Stopwatch() as clock:
        ...
    ex.write(args.out, config={"algorithm": config, "seed": args.seed}, results=results,
             table=ex.markdown_table(rows, [("level", "σ (px)", "{:g}"), ...]))
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jstarid.config_tree import with_fields
from jstarid.serialization import to_json

__all__ = ["Stopwatch", "clutter_and_random_sets", "dump_json", "load", "machine", "markdown_table",
           "parser", "peak_rss_mb", "reference_attitude",
           "provenance", "time_call", "to_json", "with_overrides", "write"]


def parser(description: str, *, out: str, seed: int = 0, quick: str | None = None) -> argparse.ArgumentParser:
    """An ``argparse`` parser with the options every experiment shares.

    Args:
        description: first line of ``--help``.
        out: default results directory (``--out``).
        seed: default PRNG seed (``--seed``).
        quick: help text of ``--quick`` (a smaller run); ``None``: no ``--quick``.

    Returns:
        The parser; add the experiment's own options to it.
    """
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--out", type=Path, default=Path(out), help=f"results directory (default {out})")
    p.add_argument("--seed", type=int, default=seed, help=f"PRNG seed (default {seed})")
    if quick is not None:
        p.add_argument("--quick", action="store_true", help=quick)
    p.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="algorithm Config overrides, VALUE in JSON (e.g. max_error_deg=0.2 verify=false)")
    return p


def with_overrides(config, items: Sequence[str] | Mapping[str, Any] | None):
    """``config`` with fields replaced from ``["field=json", …]`` (or a mapping).

    A dotted name sets a field of a nested config: ``finishing.focal_search=[]`` replaces
    ``config.finishing.focal_search`` (a JSON object given for a nested config sets it whole, through
    its own validation; a bool given for a nested config with an ``on`` field switches it:
    ``screen=false``); :func:`jstarid.config_tree.with_fields`.

    Raises:
        ValueError: an item without ``=``, a value that is not JSON, or an unknown field (the
            message lists the config's fields).
    """
    if not items:
        return config
    return with_fields(config, dict(items.items() if isinstance(items, Mapping) else map(_split, items)))


def _split(item: str) -> tuple[str, Any]:
    if "=" not in item:
        raise ValueError(f"override {item!r} is not FIELD=VALUE")
    name, text = item.split("=", 1)
    try:
        return name.strip(), json.loads(text)
    except json.JSONDecodeError:
        raise ValueError(f"override {item!r}: VALUE must be JSON (e.g. 0.2, true, null, [1, 2])") from None


class Stopwatch:
    """Wall-clock seconds of a ``with`` block (``seconds`` after it closes).

    Block on the arrays a timed block produces (``jax.block_until_ready``) inside it: JAX dispatches
    asynchronously.
    """

    def __enter__(self) -> Stopwatch:
        self.seconds = float("nan")
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        self.seconds = time.perf_counter() - self._start


def time_call(fn: Callable[[int], Any], repeats: int = 3) -> tuple[float, float]:
    """``(first, steady)`` seconds of ``fn(i)`` (i = call number, to vary the input): the first call
    (compilation included) and the median of ``repeats`` further calls, each blocked until ready."""
    with Stopwatch() as first:
        jax.block_until_ready(fn(0))
    steady = []
    for i in range(repeats):
        with Stopwatch() as clock:
            jax.block_until_ready(fn(i + 1))
        steady.append(clock.seconds)
    return first.seconds, float(np.median(steady)) if steady else float("nan")


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def machine() -> dict:
    """What the figures were measured on: host, CPU count, JAX backend, devices and versions."""
    devices = jax.devices()
    return {"host": platform.node(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "backend": jax.default_backend(),
            "devices": f"{len(devices)} × {devices[0].device_kind}", "jax": jax.__version__,
            "python": platform.python_version()}


def _git_commit() -> str | None:
    root = Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--", "jstarid"],
                               capture_output=True, text=True, timeout=5, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return f"{out}+changes" if dirty else out


def _command() -> str:
    """The command line, its program named as a user would type it: a script of the repository by
    its relative path, an installed command (``jstarid``) by its name."""
    program = Path(sys.argv[0]) if sys.argv and sys.argv[0] else Path("python")
    name = program.name
    if program.suffix == ".py":
        try:
            name = "python " + str(program.resolve().relative_to(Path(__file__).resolve().parent.parent))
        except ValueError:
            name = f"python {name}"
    return " ".join([name, *sys.argv[1:]])


def provenance() -> dict:
    """Commit (``+changes`` when the package has uncommitted edits), machine, command line, date."""
    return {"commit": _git_commit(), "machine": machine(), "command": _command(),
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")}


def write(out: str | Path, *, config: Mapping, results: Mapping, table: str | None = None,
          figures: Mapping[str, Callable[[dict, Path], None]] | None = None) -> Path:
    """Write an experiment's directory (see the module docstring).

    Args:
        out: the results directory (created).
        config: the settings (configs, seed, sizes); :func:`provenance` is added under
            ``"provenance"``.
        results: the measured values.
        table: markdown for ``table.md`` (:func:`markdown_table`).
        figures: ``{"name.png": draw}``; each ``draw(results, path)`` is called with the results
            as read back from ``results.json``, so a figure shows only what was saved.

    Returns:
        The directory.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(to_json({**config, "provenance": provenance()}), indent=2))
    (out / "results.json").write_text(json.dumps(to_json(results), indent=2))
    if table is not None:
        (out / "table.md").write_text(table.rstrip() + "\n")
    if figures:
        _, saved = load(out)
        for name, draw in figures.items():
            draw(saved, out / name)
    return out


def dump_json(path: str | Path | None, value) -> None:
    """Write ``value`` (:func:`to_json`) to ``path``; nothing when ``path`` is ``None``."""
    if path is not None:
        Path(path).write_text(json.dumps(to_json(value), indent=2))


def load(out: str | Path) -> tuple[dict, dict]:
    """``(config, results)`` as written by :func:`write`."""
    out = Path(out)
    return json.loads((out / "config.json").read_text()), json.loads((out / "results.json").read_text())


def markdown_table(rows: Sequence[Mapping], columns: Sequence[tuple[str, str, str]], *,
                   title: str | None = None, note: str | None = None) -> str:
    """A markdown table of ``rows``.

    Args:
        rows: dicts holding the columns' keys.
        columns: ``(key, header, format)`` per column, e.g. ``("misid_rate", "misid %", "{:.2%}")``;
            a missing or ``None`` value prints as ``–``.
        title: a ``#`` heading above the table. note: a paragraph below it.
    """
    lines = [f"# {title}", ""] if title else []
    lines += ["| " + " | ".join(h for _, h, _ in columns) + " |",
              "|" + "|".join("---" for _ in columns) + "|"]
    for row in rows:
        cells = []
        for key, _, fmt in columns:
            value = row.get(key)
            cells.append("–" if value is None else fmt.format(value))
        lines.append("| " + " | ".join(cells) + " |")
    if note:
        lines += ["", note]
    return "\n".join(lines) + "\n"


REFERENCE_ORIGIN_PX = -0.5  # a reference solution's pixel origin (a corner) → jstarid's (a pixel centre)


def reference_attitude(matches, catalog, camera):
    """The attitude of a frame from its reference solution's matched stars (``shared/data/real``'s
    ``reference.json``: ``[{"hip", "x", "y"}, …]``, pixel origin at a corner).

    Returns:
        ``(C (3, 3), xy (n, 2), rows (n,))``: the attitude fitted to the matches ``catalog`` holds
        (Wahba, equal weights), the matches' centroids in jstarid's pixels and their catalog rows (−1
        where the catalog lacks the star).
    """
    from jstarid.attitude import solve_wahba

    rows = catalog.row_of_hip([m["hip"] for m in matches])
    xy = np.array([[m["x"], m["y"]] for m in matches], np.float64).reshape(-1, 2) + REFERENCE_ORIGIN_PX
    keep = rows >= 0
    body = np.asarray(camera.unproject(xy[keep]))
    c = np.asarray(solve_wahba(body, catalog.unit_vectors[rows[keep]], np.ones(int(keep.sum()))))
    return c, xy, rows


def claim_detections(det_xy, star_xy, match_px: float) -> np.ndarray:
    """One-to-one labels of a frame's detections by where its stars are predicted: each star, in the
    order given (brightest first), claims the nearest detection no brighter star claimed, within
    ``match_px``.

    Args:
        det_xy: (N, 2) detections (px). star_xy: (M, 2) predicted star positions (px).
        match_px: farthest claim (px).

    Returns:
        (N,) int64 index into the stars of each detection's star, −1 where none claimed it.
    """
    star_of = np.full(len(det_xy), -1, np.int64)
    if not len(det_xy):
        return star_of
    det_xy = np.asarray(det_xy, np.float64)
    for s, xy in enumerate(np.asarray(star_xy, np.float64).reshape(-1, 2)):
        d = np.hypot(det_xy[:, 0] - xy[0], det_xy[:, 1] - xy[1])
        d[star_of >= 0] = np.inf
        j = int(np.argmin(d))
        if d[j] <= match_px:
            star_of[j] = s
    return star_of


def clutter_and_random_sets(catalog, camera, *, seed: int, scenes: int, false_counts: Sequence[int],
                            points: Sequence[int], capacity: int = 64):
    """The scene sets of the false-match experiments: ``(name, scenes, truth_known)`` per set.

    One set per count in ``false_counts`` (that many false detections of star-like magnitude, V 1 to
    the camera's limit distributed as the catalog's stars, ``CATALOG_MAG_SLOPE``; 0.5 px centroid
    noise; level k drawn from ``fold_in(key(seed), k)``), then one per count in ``points`` of random
    points uniform over the frame (no star; magnitudes uniform in V 1 to the limit), each
    ``scenes`` scenes of ``capacity`` detections (the brightest kept, the overflow flagged).
    """
    import jstarid as js  # the package face imports this module: here, not at the top

    key = jax.random.key(seed)
    for level, n_false in enumerate(false_counts):
        noise = js.NoiseConfig(position_sigma_px=0.5, n_false=n_false, false_mag_min=1.0,
                               false_mag_max=camera.mag_limit, false_mag_slope=js.CATALOG_MAG_SLOPE)
        yield (f"{n_false} false", js.simulate(jax.random.fold_in(key, level), catalog, camera, noise,
                                               batch_size=scenes, capacity=capacity), True)
    rng = np.random.default_rng(seed)
    size = np.array([camera.width - 1, camera.height - 1])
    for n_points in points:
        xy = [rng.uniform(0, 1, (n_points, 2)) * size for _ in range(scenes)]
        mag = [np.sort(rng.uniform(1.0, camera.mag_limit, n_points)) for _ in range(scenes)]
        yield f"{n_points} random points", js.scenes_from_centroids(xy, mag, capacity=capacity), False
