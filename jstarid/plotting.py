"""Figures (matplotlib). Plot functions draw from arrays or saved results; they never simulate."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

__all__ = ["Panel", "Series", "draw_panels", "plot_image", "plot_scene", "plot_solution", "plot_sweep",
           "plot_sweep_axes", "save_panels", "save_solution_plot"]


class Series(NamedTuple):
    """One line of a :class:`Panel`.

    Attributes:
        x, y: (n,) values (NaN: a gap).
        label: its legend entry (``None``: none).
        style: a matplotlib format string (marker and line style: ``"o-"``, ``"s--"``, ``":^"``).
        yerr: (n,) or (2, n) error bars (below, above); ``None``: none.
        color: a matplotlib colour (``"C2"``); ``None``: the next of the cycle.
        alpha: opacity.
        marker_size: points.
    """

    x: Sequence[float]
    y: Sequence[float]
    label: str | None = None
    style: str = "o-"
    yerr: Any = None
    color: str | None = None
    alpha: float = 1.0
    marker_size: float = 4.0


class Panel(NamedTuple):
    """One axes of a figure drawn by :func:`draw_panels`: its lines and how its axes read.

    Attributes:
        series: the :class:`Series` drawn, in order.
        xlabel, ylabel, title: the axes' texts.
        xscale, yscale: ``"linear"`` or ``"log"``.
        ylim: ``(bottom, top)`` (either ``None``: free); ``None``: free.
        legend: draw a legend (of the series with a label).
    """

    series: Sequence[Series]
    xlabel: str = ""
    ylabel: str = ""
    title: str = ""
    xscale: str = "linear"
    yscale: str = "linear"
    ylim: tuple[float | None, float | None] | None = None
    legend: bool = True


def draw_panels(panels: Sequence[Panel], *, title: str = "", size: tuple[float, float] = (5.0, 3.8)):
    """Panels side by side in one figure: the line charts of the experiment scripts, drawn from
    values they read from their saved results.

    Args:
        panels: one :class:`Panel` per axes, left to right.
        title: the figure's title (``""``: none).
        size: (width, height) of one panel (inches).

    Returns:
        The matplotlib figure (close it with ``plt.close``, or use :func:`save_panels`).
    """
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(size[0] * len(panels), size[1]), squeeze=False)
    for ax, panel in zip(axes[0], panels, strict=True):
        for line in panel.series:
            y = np.asarray([np.nan if v is None else v for v in line.y], float)
            options = dict(label=line.label, alpha=line.alpha, ms=line.marker_size)
            if line.color is not None:
                options["color"] = line.color
            if line.yerr is None:
                ax.plot(line.x, y, line.style, **options)
            else:
                ax.errorbar(line.x, y, yerr=np.clip(np.asarray(line.yerr, float), 0, None),
                            fmt=line.style, capsize=3, **options)
        ax.set_xlabel(panel.xlabel)
        ax.set_ylabel(panel.ylabel)
        if panel.title:
            ax.set_title(panel.title, fontsize=9)
        ax.set_xscale(panel.xscale)
        ax.set_yscale(panel.yscale)
        if panel.ylim is not None:
            ax.set_ylim(*panel.ylim)
        ax.grid(alpha=0.3)
        if panel.legend and any(line.label for line in panel.series):
            ax.legend(fontsize=7)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def save_panels(panels: Sequence[Panel], path, *, title: str = "", size: tuple[float, float] = (5.0, 3.8),
                dpi: int = 120) -> None:
    """:func:`draw_panels` into ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = draw_panels(panels, title=title, size=size)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def plot_scene(scenes, index: int, catalog, camera, *, ids=None, ax=None, label_limit: int = 40):
    """Draw scene ``index`` of a batch: detections sized by magnitude, labelled with HIP numbers.

    Args:
        scenes: :class:`~jstarid.scene.Scene` batch.
        index: which scene.
        catalog: the catalog whose rows ``truth``/``ids`` refer to (for HIP labels).
        camera: the camera (frame size).
        ids: optional (B, N) identification; identified stars are ringed green when correct and red
            when wrong.
        ax: matplotlib axes (a new figure when ``None``).
        label_limit: label at most this many (brightest) stars.

    Returns:
        The axes.
    """
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(7, 7 * camera.height / camera.width))
    valid = np.asarray(scenes.valid[index])
    xy = np.asarray(scenes.xy[index])[valid]
    mag = np.asarray(scenes.mag[index])[valid]
    truth = np.asarray(scenes.truth[index])[valid]
    size = 4.0 * 2.0 ** np.clip(6.5 - mag, 0.0, 7.0)
    ax.set_facecolor("black")
    real = truth >= 0
    ax.scatter(xy[real, 0], xy[real, 1], s=size[real], c="white", edgecolors="none")
    ax.scatter(xy[~real, 0], xy[~real, 1], s=size[~real], c="orange", marker="x", label="false / "
               "not in catalog")
    for k in range(min(label_limit, len(xy))):
        text = f"HIP {catalog.hip[truth[k]]}" if truth[k] >= 0 else "?"
        ax.annotate(text, xy[k], xytext=(4, 4), textcoords="offset points", color="lightskyblue",
                    fontsize=7)
    if ids is not None:
        given = np.asarray(ids[index])[valid]
        named = given >= 0
        ok = named & (given == truth)
        ax.scatter(xy[ok, 0], xy[ok, 1], s=140, facecolors="none", edgecolors="lime", label="correct")
        bad = named & ~ok
        ax.scatter(xy[bad, 0], xy[bad, 1], s=140, facecolors="none", edgecolors="red", label="wrong")
    ax.set_xlim(-0.5, camera.width - 0.5)
    ax.set_ylim(camera.height - 0.5, -0.5)  # rows grow downwards, as in the image
    ax.set_aspect("equal")
    ax.set_xlabel("x (column, px)")
    ax.set_ylabel("y (row, px)")
    ax.legend(loc="lower right", fontsize=7)
    return ax


def plot_image(image, xy, *, labels=None, correct=None, ax=None):
    """Draw a raw frame (asinh stretch between its 1st and 99.9th percentiles) with its detections.

    Args:
        image: (H, W) pixel values.
        xy: (n, 2) detections (px, column/row, origin at the centre of pixel (0, 0)).
        labels: optional n strings drawn next to the detections ("" for none).
        correct: optional (n,) bool or None per detection: labelled detections are ringed green when
            True, red when False, white when None / not given.
        ax: matplotlib axes (a new figure when ``None``).

    Returns:
        The axes.
    """
    import matplotlib.pyplot as plt

    image = np.asarray(image, np.float64)
    h, w = image.shape
    if ax is None:
        _, ax = plt.subplots(figsize=(9, 9 * h / w))
    lo, hi = np.percentile(image, [1.0, 99.9])
    scaled = np.arcsinh(np.clip((image - lo) / max(hi - lo, 1e-12), 0.0, None) * 10.0) / np.arcsinh(10.0)
    ax.imshow(scaled, cmap="gray", vmin=0.0, vmax=1.0, origin="upper",
              extent=(-0.5, w - 0.5, h - 0.5, -0.5))
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    n = len(xy)
    labels = [""] * n if labels is None else list(labels)
    correct = [None] * n if correct is None else list(correct)
    for (x, y), text, good in zip(xy, labels, correct, strict=True):
        color = "white" if good is None or not text else ("lime" if good else "red")
        ax.add_patch(plt.Circle((x, y), 9.0, fill=False, color=color, linewidth=0.8))
        if text:
            ax.annotate(text, (x, y), xytext=(7, 7), textcoords="offset points", color=color, fontsize=6)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_xlabel("x (column, px)")
    ax.set_ylabel("y (row, px)")
    return ax


def plot_solution(image, solution: dict, *, ax=None):
    """Draw a frame as ``jstarid solve`` solved it: each named star circled and labelled ``HIP n``.

    Args:
        image: (H, W) pixel values.
        solution: one entry of the solve's ``solutions`` (its JSON): ``stars`` (``hip``, ``x``, ``y``
            in px, measured), and ``ra_deg``, ``dec_deg``, ``roll_deg`` when solved; ``image`` or
            ``scene`` names it in the title.
        ax: matplotlib axes (a new figure when ``None``).

    Returns:
        The axes.
    """
    stars = solution.get("stars", [])
    xy = np.array([[s["x"], s["y"]] for s in stars], np.float64).reshape(-1, 2)
    ax = plot_image(image, xy, labels=[f"HIP {s['hip']}" for s in stars], ax=ax)
    name = Path(str(solution.get("image", solution.get("scene", "")))).name
    if solution.get("solved"):
        ax.set_title(f"{name}: {len(stars)} stars named; boresight RA {solution['ra_deg']:.3f}°, "
                     f"Dec {solution['dec_deg']:+.3f}°, roll {solution['roll_deg']:+.2f}°", fontsize=8)
    else:
        ax.set_title(f"{name}: not solved", fontsize=8)
    return ax


def save_solution_plot(image, solution: dict, path) -> None:
    """:func:`plot_solution` into ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plot_solution(image, solution).figure
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_sweep_axes(rows, *, axes=None, x_field: str | None = None, labels: dict | None = None):
    """Identification and mis-identification rates against one noise axis, one line per entry.

    Args:
        rows: a sweep's tidy rows (:meth:`jstarid.engine.SweepResult.rows`, or ``results.json``'s
            ``"rows"``): ``label``, the axis fields, ``*_rate``, ``*_low``, ``*_high``.
        axes: two matplotlib axes (identification, mis-identification); new when ``None``.
        x_field: the x axis (default: the first noise field of the rows). With a second noise
            field, each of its values is a separate line (``label, field=value``).
        labels: ``{field: axis label}`` (default :data:`jstarid.engine.levels.AXES`).

    Returns:
        The two axes. Error bars are the 95 % Wilson intervals.
    """
    import matplotlib.pyplot as plt

    from jstarid.engine.levels import AXES

    labels = AXES if labels is None else labels
    fields = [k for k in rows[0] if k in AXES]
    x_field = x_field or fields[0]
    others = [f for f in fields if f != x_field]
    if axes is None:
        _, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    lines: dict[str, list] = {}
    for r in rows:
        name = r["label"] + "".join(f", {f}={r[f]:g}" for f in others)
        lines.setdefault(name, []).append(r)
    xs = np.array([r[x_field] for r in rows], float)
    span = float(np.ptp(xs)) or 1.0
    for k, (name, group) in enumerate(lines.items()):
        # lines side by side (a small dodge) so that overlapping intervals stay readable
        dodge = (k - (len(lines) - 1) / 2) * 0.012 * span
        x = np.array([r[x_field] for r in group], float) + dodge
        for ax, rate in zip(axes, ("identification", "misid"), strict=True):
            y = np.array([100 * r[f"{rate}_rate"] for r in group])
            err = np.clip([[100 * (r[f"{rate}_rate"] - r[f"{rate}_low"]) for r in group],
                           [100 * (r[f"{rate}_high"] - r[f"{rate}_rate"]) for r in group]], 0, None)
            ax.errorbar(x, y, yerr=err, marker="o", ms=4, capsize=2, elinewidth=1, label=name)
    for ax, title in zip(axes, ("identified (%)", "mis-identified (%)"), strict=True):
        ax.set_xlabel(labels.get(x_field, x_field))
        ax.set_ylabel(title)
        ax.grid(alpha=0.3)
    axes[0].set_ylim(top=101)
    axes[1].set_ylim(bottom=-0.2)
    axes[0].legend(fontsize=8)
    return axes


def plot_sweep(results: dict, path) -> None:
    """Draw ``results["rows"]`` (a saved sweep's ``results.json``) into ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes = plot_sweep_axes(results["rows"])
    fig = axes[0].figure
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
