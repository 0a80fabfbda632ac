"""The papers' experiments as sweep-engine runs, and their comparison with the papers' figures.

Each :class:`Experiment` is one figure or table of a paper: its camera, catalog depth, scene mode,
noise axis and levels, outcome criterion and the values the paper quotes. :func:`run` runs it
through :func:`jstarid.sweep` (every level in one simulate call, the algorithm in bounded chunks)
and saves it under ``<out>/<paper>/<name>/``; :func:`comparison` puts ours beside the paper's.

Differences from the per-paper scripts in ``experiments/`` (presets over the same engine, which
add their extra outputs: SGM's naming ceiling and resumable full-size levels, MLV's Δv tuning,
RpNet's weight search): here SGM's main stars are drawn at random from the catalog rather than
taken one by one, so a full-size run has the paper's scene count (5,070 per level) but not exactly
its stars.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from jstarid.papers import mlv as mlv_paper
from jstarid.papers import rpnet as rpnet_paper
from jstarid.papers import sgm as sgm_paper

__all__ = ["Experiment", "PAPERS", "comparison", "experiments", "run", "summary"]

PAPERS = ("sgm", "mlv", "rpnet")


class Experiment(NamedTuple):
    """One of a paper's experiments (a figure or a Table 2 row).

    Attributes:
        paper, name: e.g. ``"mlv"``, ``"fig6"``.
        camera: camera preset. mag_limit: catalog depth V.
        axis: the noise field varied; levels: its values; fixed: other noise settings.
        boresight: ``"random"`` or ``"stars"`` (:func:`jstarid.sweep`).
        criterion: outcome rule. capacity: detections per scene.
        scenes, quick_scenes: scenes per level of a full and of a ``--quick`` run.
        label: the x axis. paper_values: the paper's quoted identification rate (%) by level.
        note: the paper's own words on the figure.
    """

    paper: str
    name: str
    camera: str
    mag_limit: float
    axis: str
    levels: tuple
    fixed: dict
    boresight: str
    criterion: str
    capacity: int
    scenes: int
    quick_scenes: int
    label: str
    paper_values: dict
    note: str


def experiments(paper: str) -> list[Experiment]:
    """The experiments of ``paper`` (``"sgm"``, ``"mlv"`` or ``"rpnet"``).

    Raises:
        ValueError: another name.
    """
    if paper == "mlv":
        return [Experiment("mlv", name, mlv_paper.CAMERA, mlv_paper.MAG_LIMIT, s.field, tuple(s.levels),
                           dict(s.fixed), "random", "mlv", 64, 10_000, 200, s.label,
                           dict(mlv_paper.PAPER[name]["values"]), mlv_paper.PAPER[name]["note"])
                for name, s in mlv_paper.SWEEPS.items()]
    if paper == "rpnet":
        return [Experiment("rpnet", name, rpnet_paper.CAMERA, 6.0, s.field, tuple(s.levels), dict(s.fixed),
                           "stars", "rpnet", 128, 10_000, 200, s.label,
                           dict(rpnet_paper.PAPER[name]["values"]), rpnet_paper.PAPER[name]["note"])
                for name, s in rpnet_paper.SWEEPS.items()]
    if paper == "sgm":
        fixed = {"position": {}, "lost": {"n_missing": 1}, "fake": {"n_false": 1}}
        return [Experiment("sgm", name, sgm_paper.CAMERA, sgm_paper.MAG_LIMIT, "position_sigma_px",
                           tuple(sgm_paper.SIGMAS), fixed[name], "stars", "sgm", sgm_paper.CAPACITY,
                           5070, 60, "position noise σ (px)", {},
                           "Table 2: MA {MA} %, stdA {stdA}, RA {RA}, ALN {ALN} %".format(
                               **sgm_paper.PAPER[name]))
                for name in sgm_paper.EXPERIMENTS]
    raise ValueError(f"unknown paper {paper!r}; choose one of {PAPERS} or all")


def run(experiment: Experiment, out: str | Path, *, quick: bool = False, scenes: int | None = None,
        seed: int = 0, progress: bool = True, rpnet_network: str = "quick", config=None,
        capacity: int | None = None, baselines: bool = False):
    """Run one experiment through the engine and save it under ``out/<paper>/<name>``.

    Args:
        config: the algorithm's config (default: :func:`jstarid.engine.default_config`).
        capacity: detections per scene (default: the experiment's).
        baselines: also run the classic baselines (:data:`jstarid.algorithms.BASELINES`) on the
            same scenes, scored by the same criterion.

    Returns:
        The :class:`~jstarid.engine.SweepResult`.
    """
    import jstarid as js

    n = scenes or (experiment.quick_scenes if quick else experiment.scenes)
    entry = (experiment.paper if config is None
             else js.Entry(experiment.paper, experiment.paper, config))
    others = list(js.algorithms.BASELINES) if baselines else []
    result = js.sweep([entry, *others], experiment.camera,
                      axes={experiment.axis: list(experiment.levels)}, fixed=experiment.fixed,
                      scenes=n, seed=seed, catalog=js.load_catalog(experiment.mag_limit),
                      capacity=capacity or experiment.capacity, boresight=experiment.boresight,
                      criterion=experiment.criterion, rpnet_network=rpnet_network, progress=progress)
    result.save(Path(out) / experiment.paper / experiment.name,
                title=f"{experiment.paper.upper()} {experiment.name}: {experiment.label}")
    return result


def summary(rows) -> dict[str, float]:
    """SGM Table 2's MA, stdA, RA and ALN (%) over a sweep's levels (accuracy = correct / answered)."""
    acc = 100 * np.array([r["accuracy"] if r["accuracy"] is not None else np.nan for r in rows])
    return {"MA": float(np.nanmean(acc)), "stdA": float(np.nanstd(acc)),
            "RA": float(np.nanmax(acc) - np.nanmin(acc)), "ALN": float(acc[-1])}


# What each criterion asks of a scene (docs/conventions.md §5), beside the baselines' rates.
_CRITERION_NOTES = {
    "strict": "`strict`: ≥ 3 stars named correctly, none wrong",
    "mlv": "`mlv`: ≥ 3 stars named correctly, none wrong",
    "sgm": "`sgm`: every star detected in the main star's 6° circle named correctly; the baselines "
           "name only the stars of their match, so they seldom meet it (the cross-algorithm "
           "table compares them under the strict criterion)",
    "rpnet": "`rpnet`: the main star named correctly, nothing wrong",
}


def _rates(row) -> str:
    return "" if row is None else f"{100 * row['identification_rate']:.1f} / {100 * row['misid_rate']:.1f}"


def comparison(experiment: Experiment, rows) -> str:
    """Markdown: our identification and mis-identification per level beside the paper's values, then
    (when the run had them) the baselines' on the same scenes."""
    rows = list(rows)
    others = [r for r in rows if r.get("label", experiment.paper) != experiment.paper]
    rows = [r for r in rows if r.get("label", experiment.paper) == experiment.paper]
    lines = [f"### {experiment.paper.upper()} {experiment.name}: {experiment.label}", "",
             f"Paper: {experiment.note}.", ""]
    if experiment.paper == "sgm":
        ours = summary(rows)
        lines += ["| | MA % | stdA | RA | ALN % |", "|---|---|---|---|---|",
                  "| paper | {MA} | {stdA} | {RA} | {ALN} |".format(**sgm_paper.PAPER[experiment.name]),
                  "| jstarid | {MA:.2f} | {stdA:.2f} | {RA:.2f} | {ALN:.2f} |".format(**ours), ""]
    lines += ["| level | scenes | identified % (95 % interval) | misid % | failed % | paper % |",
              "|---|---|---|---|---|---|"]
    for r in rows:
        level = r[experiment.axis]
        quoted = experiment.paper_values.get(level)
        lines.append(f"| {level:g} | {r['scenes']:,} | {100 * r['identification_rate']:.2f} "
                     f"({100 * r['identification_low']:.1f}–{100 * r['identification_high']:.1f}) | "
                     f"{100 * r['misid_rate']:.2f} | {100 * r['failure_rate']:.2f} | "
                     f"{'' if quoted is None else f'{quoted:g}'} |")
    if others:
        labels = list(dict.fromkeys(r["label"] for r in others))
        by = {(r["label"], r[experiment.axis]): r for r in others}
        lines += ["", f"Baselines on the same scenes, scored by the same criterion "
                      f"({_CRITERION_NOTES[experiment.criterion]}), identified % / misid %:", "",
                  "| level | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels)]
        for r in rows:
            level = r[experiment.axis]
            cells = [_rates(by.get((b, level))) for b in labels]
            lines.append(f"| {level:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
