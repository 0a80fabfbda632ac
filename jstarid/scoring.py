"""Strict scores of named detections against true Hipparcos numbers (labelled test sets).

The rules, at the Hipparcos-number level (``jstarid score``; conventions §5 scores catalog rows of
simulated scenes instead):

- a detection's name is **correct** when it equals the detection's true HIP;
- a **blend** when it names another star whose direction lies within the blend radius of the true
  star's (:func:`close_pairs`): the spot holds both, and the catalog keeps one of each close pair
  (the brighter, ``double_sep_deg``), so the name is not wrong but not counted correct either;
- **wrong** otherwise, a name given to a false star (true HIP −1) included.

A scene is **wrong** when any name in it is wrong, **right** when it is solved and holds a correct
name and no wrong one, and **failed** otherwise (not solved, or nothing named correctly). Per star,
``recall`` = correct / detections with a true HIP (every labelled detection of the file, those past
the scene capacity included) and ``precision`` = correct / (correct + wrong): blends are counted
apart, in neither.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from jstarid.catalog import DOUBLE_SEP_DEG as CATALOG_DOUBLE_SEP_DEG
from jstarid.catalog import load_every_star
from jstarid.false_match import calibrated

__all__ = ["CATALOG_DOUBLE_SEP_DEG", "close_pairs", "score_scene", "summarize"]


def close_pairs(hip_a, hip_b, radius_deg: float, *, epoch: float | None = None) -> np.ndarray:
    """Whether Hipparcos stars ``hip_a[k]`` and ``hip_b[k]`` lie within ``radius_deg`` of each other.

    Args:
        hip_a, hip_b: (K,) Hipparcos numbers.
        radius_deg: the blend radius (deg).
        epoch: Julian year for proper motion (``None``: J1991.25).

    Returns:
        (K,) bool; False where either number is not a Hipparcos star (V ≤ 12.5).
    """
    hip_a, hip_b = np.atleast_1d(hip_a), np.atleast_1d(hip_b)
    if hip_a.size == 0:
        return np.zeros(0, bool)
    cat = load_every_star(epoch)
    ra, rb = cat.row_of_hip(hip_a), cat.row_of_hip(hip_b)
    found = (ra >= 0) & (rb >= 0)
    cos = np.sum(cat.unit_vectors[ra] * cat.unit_vectors[rb], axis=-1)
    return found & (cos >= np.cos(np.radians(radius_deg)))


def score_scene(named_hip, true_hip, solved: bool, *,
                blends: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> dict:
    """One scene's strict score (module docstring).

    Args:
        named_hip: (n,) HIP given to each detection, −1 where none.
        true_hip: (n,) true HIP of each detection, −1 for a false star.
        solved: the identifier solved the scene.
        blends: ``(named, true) → bool`` for pairs of different stars (e.g. :func:`close_pairs` with a
            radius); ``None``: no blends.

    Returns:
        ``outcome`` (``"right"``, ``"wrong"`` or ``"failed"``), ``solved``, the counts
        ``detections``, ``true_stars``, ``named``, ``correct_names``, ``wrong_names`` and
        ``blend_names``, and ``wrong_detections`` and ``blend_detections`` (detection indices).
    """
    named_hip, true_hip = np.asarray(named_hip, np.int64), np.asarray(true_hip, np.int64)
    if named_hip.shape != true_hip.shape or named_hip.ndim != 1:
        raise ValueError(f"named and true ids must be (n,) alike, got {named_hip.shape} and {true_hip.shape}")
    named = named_hip >= 0
    correct = named & (named_hip == true_hip)
    other = named & ~correct & (true_hip >= 0)
    blend = np.zeros_like(named)
    if blends is not None and other.any():
        blend[other] = blends(named_hip[other], true_hip[other])
    wrong = named & ~correct & ~blend
    n_correct, n_wrong = int(correct.sum()), int(wrong.sum())
    outcome = "wrong" if n_wrong else "right" if solved and n_correct else "failed"
    return {"outcome": outcome, "solved": bool(solved), "detections": int(named_hip.size),
            "true_stars": int((true_hip >= 0).sum()), "named": int(named.sum()),
            "correct_names": n_correct, "wrong_names": n_wrong, "blend_names": int(blend.sum()),
            "wrong_detections": np.nonzero(wrong)[0].tolist(),
            "blend_detections": np.nonzero(blend)[0].tolist()}


def summarize(scores: Sequence[dict]) -> dict:
    """Totals of :func:`score_scene` results: scenes right / wrong / failed, star counts, recall and
    precision (NaN where the denominator is zero), and — where the scores carry each solved scene's
    ``false_match_probability`` — whether that probability is calibrated on them
    (:func:`jstarid.false_match.calibrated`, a wrong scene counting as a wrong claim; ``None`` where
    no score carries it)."""
    total = {"scenes": len(scores)}
    total.update({k: sum(s["outcome"] == k for s in scores) for k in ("right", "wrong", "failed")})
    for key in ("detections", "true_stars", "named", "correct_names", "wrong_names", "blend_names"):
        total[key] = sum(s[key] for s in scores)
    correct, decided = total["correct_names"], total["correct_names"] + total["wrong_names"]
    total["recall"] = correct / total["true_stars"] if total["true_stars"] else float("nan")
    total["precision"] = correct / decided if decided else float("nan")
    total["false_match_calibrated"] = _calibrated(scores)
    return total


def _calibrated(scores: Sequence[dict]) -> bool | None:
    if not any(s.get("false_match_probability") is not None for s in scores):
        return None
    claimed = np.array([bool(s["solved"]) for s in scores])
    p = np.array([1.0 if s.get("false_match_probability") is None else s["false_match_probability"]
                  for s in scores])
    return bool(calibrated(p, claimed, np.array([s["outcome"] == "wrong" for s in scores]) & claimed))
