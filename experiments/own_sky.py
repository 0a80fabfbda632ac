"""Real frames of a camera the defaults were never tuned on, solved with only its size and field of view.

The OreSat star-tracker frames (``shared/data/oresat``: 22 frames, 17.06° × 12.8° at 1280×960 and the
same frames binned to 640×480, each plate-solved by astrometry.net) go through the one-call path,
:func:`jstarid.solve`, with a camera made of nothing but ``--size`` and the field of view
(``js.load_camera("tetra3_test", size=…, fov_deg=…)`` — what ``jstarid solve --size WxH --fov DEG``
builds), the observation epoch, and every other setting at its default. Per frame, against the
independent solution:

- **solved** (and by the plate solver: all 22 were);
- **names** of the plate solution's matched stars (``truth/stars.csv``, Hipparcos within 10″): the
  nearest of our named detections within ``--match-px`` is ``right`` when its number is the star's,
  ``blend`` when the star is one of its blend's numbers (:class:`jstarid.solution.Star`), ``wrong``
  otherwise; a matched star with no named detection near it is ``unnamed``. A named detection with no
  matched star near it is not judged (the plate solver matched only some stars), nor is a matched
  star whose own residual in the plate solution exceeds ``--match-px`` (``loose``: astrometry.net
  matches within a generous radius, up to 7.6 px on the binned frames, where no detection of that
  star lies within ``--match-px`` of its catalog position);
- **boresight**: the angle between our boresight and the plate solution's sky position of our
  principal point (arcsec, through astropy's reading of its TAN-SIP header);
- **WCS gap**: the matched stars put through our WCS (:meth:`jstarid.Solution.wcs`) and through the
  plate solution's: their distance (px, RMS and largest over the solved frames);
- **recall**: matched stars named right or as a blend, over all frames and over the solved ones.

Usage::

    python experiments/own_sky.py                     # MLV on the three sets
    python experiments/own_sky.py --algorithm sgm --sets exp1000

Writes results/own_sky/{config.json, results.json, table.md}.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

import jstarid as js
from jstarid import experiment as ex

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "oresat"
EPOCH = 2018.3  # the frames were captured before 2018-05-18 (README of the data)
FOV_DEG = {"exp1000": 17.06, "exp2500": 17.06, "downsample": 17.06}


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/own_sky")
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the oresat folder")
    p.add_argument("--sets", nargs="+", default=list(FOV_DEG))
    p.add_argument("--algorithm", default="mlv")
    p.add_argument("--match-px", type=float, default=3.0,
                   help="largest distance (px) between a matched star and our detection of it")
    return p.parse_args(argv)


def read_truth(folder: Path) -> tuple[dict, dict]:
    """``(stars, frames)``: per image the matched stars (x, y, hip, the plate solution's residual in
    px, RA, Dec in deg) and the frame's row."""
    stars: dict[str, list] = {}
    with open(folder / "truth" / "stars.csv") as f:
        for row in csv.DictReader(f):
            star = (float(row["x"]), float(row["y"]), int(row["hip"]), float(row["anet_resid_px"]),
                    float(row["ra_deg_j2000"]), float(row["dec_deg_j2000"]))
            stars.setdefault(row["image"], []).append(star)
    with open(folder / "truth" / "frames.csv") as f:
        frames = {row["image"]: row for row in csv.DictReader(f)}
    return stars, frames


def against_plate_solution(solution, wcs_path: Path, truth: list) -> dict:
    """Our solution against the plate solver's TAN-SIP header (astropy reads both): the boresight
    error (arcsec: our boresight against their sky position of our principal point) and how far
    apart the two WCSs put the matched stars (``truth`` rows; px, RMS and largest)."""
    import astropy.units as u
    from astropy.coordinates import SkyCoord
    from astropy.io import fits
    from astropy.wcs import WCS

    cam = solution.camera
    with fits.open(wcs_path) as hdus:
        theirs = WCS(hdus[0].header)
    ra, dec = theirs.all_pix2world([[cam.cx, cam.cy]], 0)[0]
    error = SkyCoord(solution.ra_deg * u.deg, solution.dec_deg * u.deg).separation(
        SkyCoord(ra * u.deg, dec * u.deg)).arcsec
    radec = np.array([(r, d) for *_, r, d in truth])
    gap = np.linalg.norm(solution.wcs().all_world2pix(radec, 0) - theirs.all_world2pix(radec, 0), axis=1)
    return {"boresight_arcsec": round(float(error), 1), "wcs_gaps_px": gap.tolist()}


def judge(solution, truth: list, match_px: float) -> dict:
    """Counts of right / blend / wrong / unnamed / loose matched stars (module docstring)."""
    counts = {"right": 0, "blend": 0, "wrong": 0, "unnamed": 0, "loose": 0}
    named = np.array([[s.x, s.y] for s in solution.stars]).reshape(-1, 2)
    for x, y, hip, plate_residual, *_ in truth:
        if hip < 0:
            continue
        if plate_residual > match_px:
            counts["loose"] += 1
            continue
        d = np.hypot(named[:, 0] - x, named[:, 1] - y) if len(named) else np.array([])
        if not len(d) or d.min() > match_px:
            counts["unnamed"] += 1
            continue
        star = solution.stars[int(np.argmin(d))]
        kind = "right" if star.hip == hip else "blend" if hip in star.blend else "wrong"
        counts[kind] += 1
    return counts


def _gaps(gaps: list) -> str:
    return f"{np.sqrt(np.mean(np.square(gaps))):.2f} / {max(gaps):.2f}" if gaps else "—"


def _recall(recs: list) -> str:
    """Matched stars named right or as a blend, over those of ``recs``."""
    good = sum(r["right"] + r["blend"] for r in recs)
    matched = sum(r["right"] + r["blend"] + r["wrong"] + r["unnamed"] for r in recs)
    return f"{100 * good / max(matched, 1):.1f} %"


def main(argv=None):
    args = parse_args(argv)
    records = []
    for name in args.sets:
        folder = args.data / name
        truth, frames = read_truth(folder)
        first = next(iter(frames.values()))
        camera = js.load_camera("tetra3_test", size=(int(first["width"]), int(first["height"])),
                                fov_deg=FOV_DEG[name])
        images = sorted(folder.glob("images/*.png"), key=lambda p: int(p.stem))
        print(f"{name}: {len(images)} frames, {camera.width}×{camera.height} px, "
              f"{camera.fov_x_deg:.2f}°, catalog V ≤ {camera.mag_limit:g}", flush=True)
        solutions = js.solve([str(p) for p in images], camera, args.algorithm, epoch=EPOCH)
        for path, sol in zip(images, solutions, strict=True):
            rec = {"set": name, "image": path.name, "solved": sol.solved, "detections": sol.detections,
                   "named": len(sol.stars), **judge(sol, truth.get(path.name, []), args.match_px)}
            if sol.solved:
                rec.update(against_plate_solution(sol, folder / frames[path.name]["wcs_file"],
                                                  truth.get(path.name, [])))
            records.append(rec)
            print(f"  {path.name}: {'solved' if sol.solved else 'not solved'}, {len(sol.stars)} of "
                  f"{sol.detections} named; matched stars {rec['right']} right, {rec['blend']} blend, "
                  f"{rec['wrong']} wrong, {rec['unnamed']} unnamed, {rec['loose']} loose"
                  + (f"; boresight {rec['boresight_arcsec']}″" if sol.solved else ""), flush=True)
    rows = []
    for name in args.sets:
        recs = [r for r in records if r["set"] == name]
        solved = [r for r in recs if r["solved"]]
        total = {k: sum(r[k] for r in recs) for k in ("right", "blend", "wrong", "unnamed", "loose", "named",
                                                      "detections")}
        matched = total["right"] + total["blend"] + total["wrong"] + total["unnamed"]
        errors = [r["boresight_arcsec"] for r in solved]
        rows.append({"set": name, "solved": f"{len(solved)} / {len(recs)}",
                     "right": total["right"], "blend": total["blend"], "wrong": total["wrong"],
                     "unnamed": total["unnamed"], "loose": total["loose"],
                     "recall": f"{100 * (total['right'] + total['blend']) / max(matched, 1):.1f} %",
                     "recall_solved": _recall([r for r in recs if r["solved"]]),
                     "boresight": (f"{np.median(errors):.0f} / {max(errors):.0f}" if errors else "—"),
                     "wcs": _gaps([g for r in solved for g in r["wcs_gaps_px"]])})
    table = ex.markdown_table(rows, [("set", "set", "{}"), ("solved", "solved / plate-solved", "{}"),
                                     ("right", "matched stars right", "{}"), ("blend", "blend", "{}"),
                                     ("wrong", "wrong", "{}"), ("unnamed", "unnamed", "{}"),
                                     ("loose", f"loose (plate residual > {args.match_px:g} px)", "{}"),
                                     ("recall", "recall", "{}"),
                                     ("recall_solved", "recall, solved frames", "{}"),
                                     ("boresight", "boresight ″ median / max", "{}"),
                                     ("wcs", "WCS gap px RMS / max", "{}")])
    print(table)
    ex.write(args.out, config={"algorithm": args.algorithm, "sets": args.sets, "epoch": EPOCH,
                               "match_px": args.match_px},
             results={"frames": records, "sets": rows}, table=table)


if __name__ == "__main__":
    main()
