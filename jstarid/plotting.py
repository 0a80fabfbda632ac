"""Figures (matplotlib). Plot functions draw from arrays or saved results; they never simulate."""

from __future__ import annotations

import numpy as np

__all__ = ["plot_scene"]


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
