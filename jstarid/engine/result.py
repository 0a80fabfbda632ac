"""A sweep's result: per-scene outcomes of every entry, and the tidy table computed from them.

:class:`SweepResult` keeps, for every scene and entry, the outcome code and counts of
:func:`jstarid.metrics.scene_outcomes` and the attitude errors, plus each entry's timings. Its
:meth:`~SweepResult.rows` are the tidy table: one row per (entry, level) with scene counts, the
identification, failure and mis-identification rates with 95 % Wilson intervals, attitude error
quantiles, the claims' false-match probability (median, and whether it is calibrated), scenes/s and
peak memory. :meth:`~SweepResult.save` writes the harness's results
directory (``config.json``, ``results.json``, ``table.md``, ``scenes.npz``, ``rates.png``) and
:func:`load` reads it back; figures are drawn from the saved rows only.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from jstarid import experiment
from jstarid.false_match import WRONG_ATTITUDE_PX, calibrated
from jstarid.metrics import CORRECT, FAIL, OUTCOME_NAMES, WRONG, wilson_interval

__all__ = ["SweepResult", "load", "COLUMNS"]

# (key, header, format) of table.md
COLUMNS = (("identification_rate", "identified", "{:.2%}"),
           ("identification_ci", "95 % interval", "{}"),
           ("misid_rate", "misid", "{:.2%}"),
           ("misid_ci", "95 % interval", "{}"),
           ("failure_rate", "failed", "{:.2%}"),
           ("boresight_err_arcsec_median", "boresight ″ (median)", "{:.1f}"),
           ("false_match_median", "claims' false-match P (median)", "{:.1e}"),
           ("false_match_calibrated", "P calibrated", "{}"),
           ("scenes_per_second", "scenes/s", "{:,.0f}"),
           ("compile_seconds", "XLA compile s", "{:.1f}"),
           ("scenes_per_second_without_compile", "scenes/s, XLA compile excluded", "{:,.0f}"),
           ("peak_rss_mb", "peak MB", "{:,.0f}"))


@dataclasses.dataclass(frozen=True)
class SweepResult:
    """Outcomes of a sweep (or of :func:`~jstarid.engine.compare` on given scenes).

    Attributes:
        settings: what was run (camera, catalog, axes, scenes per level, seed, criterion, …).
        entries: per entry, ``{"label", "algorithm", "group", "config"}``.
        levels: per level, ``{noise field: value}``.
        level_of: (S,) int32 level of each scene.
        scenes: per-scene arrays (S, E): ``outcome`` (int8 code of :mod:`jstarid.metrics`),
            ``n_correct``, ``n_wrong``, ``n_identified``, ``boresight_err_arcsec`` and
            ``roll_err_arcsec`` (NaN where the entry gave no attitude), ``false_match`` (the claim's
            false-match probability, :func:`jstarid.false_match.of_solutions`; 1 where not
            claimed; absent from sweeps saved before it was recorded).
        seconds: (E, L) identify wall seconds per entry and level (compilation of shapes first met
            there included), added over processes.
        compile_seconds: (E, L) the part of ``seconds`` XLA spent compiling programs
            (:class:`jstarid.runtime.CountCompilations`; tracing and lowering not included), or
            ``None`` for a sweep saved before it was recorded.
        timing: per entry, ``database_seconds``, ``first_call_seconds`` (its first identify call,
            mostly compilation on a first run) and ``peak_rss_mb`` (the process's peak after the
            entry ran).
        processes: JAX processes that ran it.
        stars: (S,) int16 true stars among each scene's detections (valid detections whose truth is
            a catalog star), or ``None`` for a sweep saved before it was recorded; ``rows(stars=…)``
            reads it.
    """

    settings: dict
    entries: list
    levels: list
    level_of: np.ndarray
    scenes: dict
    seconds: np.ndarray
    timing: list
    processes: int = 1
    compile_seconds: np.ndarray | None = None
    stars: np.ndarray | None = None

    @classmethod
    def from_arrays(cls, *, entries, levels, level_of, arrays, timing, settings, processes=1, stars=None):
        """Build from the engine's arrays (``arrays["seconds"]`` (E, L), the rest (S, E)) and the
        scenes' (S,) true-star counts."""
        from jstarid.engine.entries import describe

        arrays = dict(arrays)
        seconds = np.asarray(arrays.pop("seconds"), np.float64)
        compiled = arrays.pop("compile_seconds", None)
        return cls(settings=experiment.to_json(settings), entries=[describe(e) for e in entries],
                   levels=[dict(lv) for lv in levels], level_of=np.asarray(level_of, np.int32),
                   scenes={k: np.asarray(v) for k, v in arrays.items()}, seconds=seconds,
                   timing=experiment.to_json(list(timing)), processes=int(processes),
                   compile_seconds=None if compiled is None else np.asarray(compiled, np.float64),
                   stars=None if stars is None else np.asarray(stars, np.int16))

    @property
    def labels(self) -> list[str]:
        return [e["label"] for e in self.entries]

    def rows(self, stars: tuple[int, int] | None = None) -> list[dict[str, Any]]:
        """The tidy table: one dict per (entry, level), entries outer, levels inner.

        Args:
            stars: ``(lo, hi)``: only the scenes with ``lo`` … ``hi`` true stars among their
                detections (:attr:`stars`; each row then says so under ``"stars"``). Rates and
                errors are over those scenes; ``seconds`` and the rates in scenes/s stay the
                level's (timed over all its scenes).

        Raises:
            ValueError: ``stars`` on a result without star counts, or not ``0 ≤ lo ≤ hi``.
        """
        out = []
        codes = self.scenes["outcome"]
        chosen = self._with_stars(stars)
        for e, entry in enumerate(self.entries):
            for lv, level in enumerate(self.levels):
                take = (self.level_of == lv) & chosen
                code = codes[take, e]
                n = int(code.size)
                counts = {name: int(np.sum(code == c)) for c, name in OUTCOME_NAMES.items()}
                row = {"label": entry["label"], "algorithm": entry["algorithm"],
                       **entry.get("setting", {}), **level,
                       **({} if stars is None else {"stars": f"{stars[0]}–{stars[1]}"}),
                       "scenes": n, **{f"n_{k}": v for k, v in counts.items()}}
                for rate, k in (("identification", "correct"), ("misid", "wrong"),
                                ("failure", "fail")):
                    lo, hi = wilson_interval(counts[k], n)
                    row[f"{rate}_rate"] = counts[k] / n if n else float("nan")
                    row[f"{rate}_low"], row[f"{rate}_high"] = float(lo), float(hi)
                answered = n - counts["fail"]
                row["accuracy"] = counts["correct"] / answered if answered else None
                ok = code == CORRECT
                errors = self.scenes["boresight_err_arcsec"][take, e][ok]
                errors = errors[np.isfinite(errors)]
                row["boresight_err_arcsec_median"] = float(np.median(errors)) if errors.size else None
                row["boresight_err_arcsec_p95"] = (float(np.percentile(errors, 95)) if errors.size
                                                   else None)
                row["mean_identified"] = float(np.mean(self.scenes["n_identified"][take, e])) if n else None
                row.update(self._false_match(take, e, code))
                sec = float(self.seconds[e, lv])
                timed = int(np.sum(self.level_of == lv))  # the level's scenes, all of them timed
                row["seconds"] = sec
                row["scenes_per_second"] = timed / sec if sec > 0 else None
                compiled = None if self.compile_seconds is None else float(self.compile_seconds[e, lv])
                row["compile_seconds"] = compiled
                rest = None if compiled is None else sec - compiled
                row["scenes_per_second_without_compile"] = (timed / rest if rest is not None and rest > 0
                                                            else None)
                row["peak_rss_mb"] = self.timing[e]["peak_rss_mb"]
                out.append(row)
        return out

    def _false_match(self, take, e, code) -> dict:
        """A row's false-match columns: the median P of its claims, and whether P is calibrated on
        them (:func:`jstarid.false_match.calibrated`; a wrong claim is a wrong attitude, boresight
        over :data:`~jstarid.false_match.WRONG_ATTITUDE_PX` off or none: P speaks of the attitude,
        and a right attitude with one wrong name is the misid column's); ``None`` for a sweep saved
        before P was recorded, or a row without claims."""
        if "false_match" not in self.scenes:
            return {"false_match_median": None, "false_match_calibrated": None}
        p = self.scenes["false_match"][take, e]
        claimed = code != FAIL
        if not claimed.any():
            return {"false_match_median": None, "false_match_calibrated": None}
        f_px = self.settings.get("camera", {}).get("f_px")
        off = self.scenes["boresight_err_arcsec"][take, e]
        if f_px:  # the radius in arcsec at the camera's pixel scale
            wrong = claimed & ~(off <= WRONG_ATTITUDE_PX * math.degrees(1.0) * 3600.0 / f_px)
        else:  # a result without its camera: any wrong name (stricter)
            wrong = code == WRONG
        return {"false_match_median": float(np.median(p[claimed])),
                "false_match_calibrated": bool(calibrated(p, claimed, wrong))}

    def _with_stars(self, stars) -> np.ndarray:
        """(S,) bool: the scenes ``rows(stars=…)`` counts."""
        if stars is None:
            return np.ones(self.level_of.shape, bool)
        lo, hi = stars
        if self.stars is None:
            raise ValueError("this sweep has no star counts per scene (saved before they were recorded)")
        if not (0 <= lo <= hi):
            raise ValueError(f"stars must be (lo, hi) with 0 ≤ lo ≤ hi, got {stars}")
        return (self.stars >= lo) & (self.stars <= hi)

    def table(self, title: str | None = None, stars: tuple[int, int] | None = None) -> str:
        """``rows(stars)`` as markdown (rates in %, Wilson intervals in brackets)."""
        axes = list(self.levels[0])
        rows = []
        for r in self.rows(stars):
            r = dict(r)
            for rate in ("identification", "misid"):
                r[f"{rate}_ci"] = f"{100 * r[f'{rate}_low']:.1f}–{100 * r[f'{rate}_high']:.1f}"
            rows.append(r)
        columns = ([("label", "algorithm", "{}")] + [(a, a, "{:g}") for a in axes]
                   + ([] if stars is None else [("stars", "true stars", "{}")])
                   + [("scenes", "scenes", "{:,}")] + list(COLUMNS))
        s = self.settings
        note = (f"Camera {s.get('camera', {}).get('name', '?')}, {s.get('boresight', '?')} boresights, "
                f"criterion {s.get('criterion', '?')}, seed {s.get('seed', '?')}, fixed "
                f"{s.get('fixed') or 'nothing else'}. Intervals: 95 % Wilson. scenes/s: identify "
                "wall time per process, compilation of the shapes a level meets first included; "
                "XLA compile s: the part XLA spent compiling, and the rate without it (tracing "
                "still included; experiments/bench_compile.py measures fresh-scene rates); peak MB: "
                "the process's resident peak after the algorithm ran.")
        if stars is not None:
            note += (f" Only the scenes with {stars[0]}–{stars[1]} true stars among their detections; "
                     "scenes/s over all the level's scenes.")
        if s.get("pixels"):
            note += (f" From pixels: frames rendered (sky to the camera's limit + "
                     f"{s.get('render_depth_mag', '?')} mag) and their centroids extracted, "
                     f"{s.get('render_extract_seconds', 0):.0f} s in all.")
        return experiment.markdown_table(rows, columns, title=title, note=note)

    def save(self, out: str | Path, *, title: str | None = None, figure: bool = True) -> Path:
        """Write ``config.json``, ``results.json`` (rows, timing), ``table.md``, ``scenes.npz`` and
        ``rates.png`` (drawn from ``results.json``) under ``out``."""
        from jstarid.plotting import plot_sweep

        config = {"settings": self.settings, "entries": self.entries, "levels": self.levels,
                  "processes": self.processes}
        results = {"rows": self.rows(), "timing": self.timing, "seconds": self.seconds,
                   "compile_seconds": self.compile_seconds}
        out = experiment.write(out, config=config, results=results, table=self.table(title),
                               figures={"rates.png": plot_sweep} if figure else None)
        extra = {} if self.stars is None else {"n_stars": self.stars}
        np.savez_compressed(out / "scenes.npz", level_of=self.level_of, **extra, **self.scenes)
        return out

    def equal_outcomes(self, other: SweepResult, *, rtol: float = 0.0) -> bool:
        """Same levels, entries and per-scene outcome arrays (timings aside), bit for bit.

        With ``rtol`` > 0, counts and flags (names right and wrong, identified, failed, …) must
        still be equal and measured floats (a claim's false-match probability, the boresight error)
        equal within ``rtol``: they come from the camera check's fit, whose calls cut the detections
        to the columns their scenes fill (:func:`jstarid.camera_fit.check_width`), so a scene run in
        another batch — a grid's entry alone rather than in the grid's one batch — can round them
        otherwise in the last digits (a P of 8.596e-05 against 8.597e-05).
        """
        def same(a, b):
            a, b = np.asarray(a), np.asarray(b)
            if rtol and a.dtype.kind == "f" and b.dtype.kind == "f":
                return a.shape == b.shape and bool(np.allclose(a, b, rtol=rtol, atol=0.0, equal_nan=True))
            return np.array_equal(a, b, equal_nan=a.dtype.kind == "f")

        return (self.labels == other.labels and self.levels == other.levels
                and np.array_equal(self.level_of, other.level_of)
                and (self.stars is None or other.stars is None or np.array_equal(self.stars, other.stars))
                and set(self.scenes) == set(other.scenes)
                and all(same(self.scenes[k], other.scenes[k]) for k in self.scenes))


def load(out: str | Path) -> SweepResult:
    """A :class:`SweepResult` as saved by :meth:`SweepResult.save`.

    Raises:
        FileNotFoundError: ``out`` holds no saved sweep.
    """
    out = Path(out)
    if not (out / "scenes.npz").exists():
        raise FileNotFoundError(f"{out} holds no saved sweep (scenes.npz missing)")
    config, results = experiment.load(out)
    with np.load(out / "scenes.npz") as z:
        arrays = {k: z[k] for k in z.files}
    level_of = arrays.pop("level_of")
    stars = arrays.pop("n_stars", None)
    return SweepResult(settings=config["settings"], entries=config["entries"],
                       levels=config["levels"], level_of=level_of, scenes=arrays,
                       seconds=np.asarray(results["seconds"], np.float64), timing=results["timing"],
                       processes=config.get("processes", 1),
                       compile_seconds=(None if results.get("compile_seconds") is None
                                        else np.asarray(results["compile_seconds"], np.float64)),
                       stars=stars)

