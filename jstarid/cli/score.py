"""``jstarid score``: labelled centroid files identified as ``jstarid identify`` does, then scored.

The strict rules are :mod:`jstarid.scoring`'s: per scene right / wrong / failed, per star recall and
precision, blends (a name of the other star of a close pair) counted apart.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from jstarid.cli.cameras import camera_from_args
from jstarid.solution import NAMING_CAPACITY


def add_commands(sub) -> None:
    from jstarid.cli.frames import centroid_file_command

    p = sub.add_parser(
        "score", help="labelled centroid files (true HIP per detection) → identified and scored: "
                      "scenes right / wrong / failed, star recall and precision, blends",
        description="Identify every scene of labelled centroid files exactly as `jstarid identify` "
                    "does and score the names against the true Hipparcos numbers (a 'hip' column, "
                    "a JSON \"hip\" list, or the line layout's id lines; −1 for a false star). A "
                    "scene is wrong when any detection is named other than its true star, right "
                    "when it is solved with a correct name and no wrong one, failed otherwise. A "
                    "name of another star within the blend radius (the catalog's close-pair "
                    "separation or --tol-px, whichever is wider) is a blend, neither right nor wrong. "
                    "Prints a table (and writes --out as JSON).")
    centroid_file_command(p, "labelled centroid files (.csv, .tsv, .txt, .json)")
    p.add_argument("--out", type=Path, default=None, help="write the scores as JSON here")
    p.set_defaults(func=run_score)


def run_score(args) -> int:
    import jstarid as js
    from jstarid import scoring
    from jstarid.cli.centroid_input import combine, named_detections, read_labelled_files
    from jstarid.cli.frames import _epoch_fields, _identify, _note_epoch
    from jstarid.scoring import close_pairs, score_scene, summarize

    camera = camera_from_args(args)  # a bad camera fails before any file is read
    sets = read_labelled_files(args)
    found = combine(sets)
    measured = found.scenes(max(NAMING_CAPACITY, args.capacity))
    _note_epoch(args)
    solutions = _identify(args, measured, list(found.labels))
    radius_deg = blend_radius_deg(args, camera)

    def blends(named, true):
        return close_pairs(named, true, radius_deg, epoch=args.epoch)

    scores = []
    named = named_detections(solutions, found)
    for i, entry in enumerate(solutions):
        score = score_scene(named[i], found.hip[i], entry["solved"], blends=blends)
        for key in ("wrong_detections", "blend_detections"):  # indices → the detections themselves
            score[key] = [{"x": float(found.xy[i][j, 0]), "y": float(found.xy[i][j, 1]),
                           "hip": int(named[i][j]), "true_hip": int(found.hip[i][j])} for j in score[key]]
        scores.append({"scene": entry["scene"], **score,
                       "false_match_probability": entry.get("false_match_probability")})
    sets_out, start = [], 0
    for path, one in sets:
        per_scene = scores[start:start + len(one)]
        start += len(one)
        sets_out.append({"file": path, **summarize(per_scene), "scenes_scored": per_scene})
    total = summarize(scores)
    print(_table(sets_out, total))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(_finite({
            "camera": js.camera_files.camera_to_dict(camera), "algorithm": args.algorithm,
            **_epoch_fields(args), "blend_radius_deg": radius_deg, "rules": scoring.__doc__,
            "total": total, "sets": sets_out}), indent=1))
        print(f"wrote {args.out}", file=sys.stderr)
    return 0


def blend_radius_deg(args, camera) -> float:
    """The identification catalog's close-pair separation or the naming tolerance (``--tol-px`` at
    the camera's pixel scale), whichever is wider."""
    from jstarid.scoring import CATALOG_DOUBLE_SEP_DEG

    return max(CATALOG_DOUBLE_SEP_DEG, math.degrees(args.tol_px / camera.f_px))


def _table(sets: list[dict], total: dict) -> str:
    rows = ["| set | scenes | right | wrong | failed | recall | precision | blends | P calibrated |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for name, s in [(s["file"], s) for s in sets] + ([("all", total)] if len(sets) > 1 else []):
        calibrated = {None: "–", True: "yes", False: "no"}[s["false_match_calibrated"]]
        rows.append(f"| {name} | {s['scenes']} | {s['right']} | {s['wrong']} | {s['failed']} | "
                    f"{s['recall']:.3f} | {s['precision']:.3f} | {s['blend_names']} | {calibrated} |")
    return "\n".join(rows)


def _finite(value):
    """JSON without NaN (``null`` instead): a recall over no true star is undefined."""
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value
