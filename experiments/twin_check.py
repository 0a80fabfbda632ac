"""The twin check on real frames: OreSat's detections, labelled by an independent plate solution, against
their simulated twin, algorithm by algorithm.

The OreSat frames (``shared/data/oresat``, sets ``exp1000`` and ``exp2500``: 15 frames of one camera,
1280×960 px, 17.06° × 12.8°, each solved by astrometry.net) become a labelled centroid file:

- detections: :func:`jstarid.extract_centroids` on each frame (the settings ``jstarid solve`` names
  stars with), magnitudes instrumental (−2.5 log10 flux);
- labels: every Hipparcos star (V ≤ 10, epoch 2018.3) put in the frame by the plate solver's TAN-SIP
  header (astropy) claims the nearest detection within ``--match-px``, brightest star first; a
  detection no star claims is −1 (a false star, or a star past Hipparcos).

No jstarid solution enters the labels. Then ``js.twin.twin_check`` — what ``jstarid twin
FILE --camera …`` runs — fits the detection model to the file, simulates the twin near the frames'
pointings and runs each algorithm with its defaults for the camera on both.

Usage::

    python experiments/twin_check.py                       # MLV, SGM, RpNet; 1000 twin scenes
    python experiments/twin_check.py --algorithms mlv --scenes 200
    python experiments/twin_check.py --sky exact --scenes 300   # each frame's own attitude, 20 twins each

Writes results/twin_check/{oresat_labelled.csv, twin.json, table.md, config.json, results.json}.
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.centroid_files import read_centroid_set

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "oresat"
SETS = ("exp1000", "exp2500")  # one camera (downsample/ is these frames binned: another camera)
EPOCH = 2018.3
SIZE, FOV_DEG = (1280, 960), 17.06
LABEL_DEPTH = 10.0  # V: the Hipparcos stars that may claim a detection


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/twin_check", quick="200 twin scenes, MLV")
    p.add_argument("--data", type=Path, default=DATA, help="the oresat folder")
    p.add_argument("--algorithms", default="mlv,sgm,rpnet")
    p.add_argument("--scenes", type=int, default=1000, help="twin scenes (default 1000)")
    p.add_argument("--sky", choices=js.twin.SKIES, default="real",
                   help="the twin's pointings (js.twin.twin_scenes; default real: near the frames')")
    p.add_argument("--match-px", type=float, default=2.0,
                   help="farthest a detection may lie from the star the plate solution puts there")
    p.add_argument("--train-on-fit", action="store_true",
                   help="RpNet trains on the detection model fitted to the frames")
    return p.parse_args(argv)


def plate_solution(wcs_path: Path):
    from astropy.io import fits
    from astropy.wcs import WCS

    with fits.open(wcs_path) as hdus:
        return WCS(hdus[0].header)


def labelled_file(args, out: Path) -> Path:
    """The frames' detections and labels as one CSV (module docstring)."""
    from jstarid.solution import NAMING_CAPACITY, NAMING_CENTROIDS

    catalog = js.load_catalog(LABEL_DEPTH, epoch=EPOCH, double_sep_deg=0.0)
    v = catalog.unit_vectors
    ra = np.degrees(np.arctan2(v[:, 1], v[:, 0])) % 360.0
    dec = np.degrees(np.arcsin(np.clip(v[:, 2], -1, 1)))
    rows = [("scene", "x", "y", "mag", "hip")]
    for name in SETS:
        folder = args.data / name
        with open(folder / "truth" / "frames.csv") as f:
            frames = {row["image"]: row for row in csv.DictReader(f)}
        for path in sorted(folder.glob("images/*.png"), key=lambda p: int(p.stem)):
            image = js.read_image(path).astype(np.float32)
            found = js.extract_centroids(image[None], NAMING_CENTROIDS, capacity=NAMING_CAPACITY)
            valid = np.asarray(found.valid[0])
            xy, mag = np.asarray(found.xy[0], np.float64)[valid], np.asarray(found.mag[0], np.float64)[valid]
            wcs = plate_solution(folder / frames[path.name]["wcs_file"])
            # the stars within the field's diagonal of the reference point (SIP diverges far out)
            near = np.nonzero(np.einsum("nj,j->n", v, _axis(wcs)) > np.cos(np.radians(FOV_DEG)))[0]
            px = wcs.all_world2pix(np.column_stack([ra[near], dec[near]]), 0)
            inside = (px[:, 0] > -1) & (px[:, 0] < SIZE[0]) & (px[:, 1] > -1) & (px[:, 1] < SIZE[1])
            star = ex.claim_detections(xy, px[inside], args.match_px)  # the catalog's order: brightest first
            hip = np.where(star >= 0, catalog.hip[near[inside]][np.maximum(star, 0)], -1)
            rows += [(f"{name}/{path.name}", f"{x:.3f}", f"{y:.3f}", f"{m:.3f}", int(h))
                     for (x, y), m, h in zip(xy, mag, hip, strict=True)]
            print(f"{name}/{path.name}: {len(xy)} detections, {int((hip >= 0).sum())} labelled", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "oresat_labelled.csv"
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(rows)
    return path


def _axis(wcs) -> np.ndarray:
    """The unit vector of the plate solution's reference point (stars behind it are not projected)."""
    ra, dec = np.radians(wcs.wcs.crval)
    return np.array([np.cos(ra) * np.cos(dec), np.sin(ra) * np.cos(dec), np.sin(dec)])


def clutter_radii(found, camera, capacity: int = 64) -> dict:
    """Where the brightest ``capacity`` detections that are no catalog star lie: percentiles (10, 25,
    50, 75) of their distance from the principal point (px), beside those of points uniform over the
    frame (the twin's clutter)."""
    radii = []
    for xy, mag, hip in zip(found.xy, found.mag, found.hip, strict=True):
        top = np.argsort(mag, kind="stable")[:capacity]
        loose = top[hip[top] < 0]
        radii.append(np.hypot(xy[loose, 0] - camera.cx, xy[loose, 1] - camera.cy))
    rng = np.random.default_rng(0)
    uniform = np.hypot(rng.uniform(0, camera.width - 1, 100_000) - camera.cx,
                       rng.uniform(0, camera.height - 1, 100_000) - camera.cy)
    q = [10, 25, 50, 75]
    return {"per_frame": float(np.mean([r.size for r in radii])),
            "real_px": np.percentile(np.concatenate(radii), q).round(0).tolist(),
            "uniform_px": np.percentile(uniform, q).round(0).tolist(), "percentiles": q}


def scene_table(check) -> str:
    """Markdown: each frame's outcome beside the share of its twin scenes identified, per algorithm."""
    rows = check.scene_rows()
    if not rows:
        return ""
    labels = [e["label"] for e in check.result.entries]
    lines = ["| frame | twins | " + " | ".join(f"{a} real | {a} twin" for a in labels) + " |",
             "|---|---:|" + "---|---:|" * len(labels)]
    for r in rows:
        cells = " | ".join(f"{r[a + '_real']} | {100 * r[a + '_twin']:.0f} %" for a in labels)
        lines.append(f"| {r['scene']} | {r['twin_scenes']} | {cells} |")
    # were each frame solved with its twins' rate p_i: Σ p_i frames expected, variance Σ p_i (1 − p_i)
    lines.append("")
    for a in labels:
        p = np.array([r[a + "_twin"] for r in rows])
        solved = sum(r[a + "_real"] == "correct" for r in rows)
        lines.append(f"{a}: the twins expect {p.sum():.1f} ± {np.sqrt(np.sum(p * (1 - p))):.1f} of the "
                     f"{len(rows)} frames identified; the frames gave {solved}")
    return "\n".join(lines) + "\n"


def main(argv=None):
    args = parse_args(argv)
    js.use_cpu_cores()
    if not (args.data / SETS[0]).exists():
        raise SystemExit(f"no OreSat frames at {args.data}")
    algorithms = "mlv" if args.quick else args.algorithms
    scenes = 200 if args.quick else args.scenes
    path = labelled_file(args, args.out)
    camera = js.load_camera("tetra3_test", size=SIZE, fov_deg=FOV_DEG)
    check = js.twin.twin_check(read_centroid_set(path), camera, algorithms, scenes=scenes, seed=args.seed,
                               epoch=EPOCH, sky=args.sky, train_on_fit=args.train_on_fit)
    fit = check.labelled.fit
    radii = clutter_radii(read_centroid_set(path), camera)
    results = {"rows": check.rows(), "scenes": check.scene_rows(), "detections_per_scene": check.detections,
               "clutter_radii": radii,
               "fitted": {"model": dataclasses.asdict(fit.model),
                          "magnitude_sigma": fit.magnitude_sigma, "position_sigma_px": fit.position_sigma_px,
                          "magnitude_offset": fit.magnitude_offset, "clutter": fit.clutter,
                          "stars": fit.stars, "detected": fit.detected,
                          "depth_mag": check.labelled.depth_mag,
                          "residual_px_median": float(np.nanmedian(check.labelled.residual_px))}}
    ex.write(args.out, config={**vars(args), "camera": camera}, results=results, table=check.table())
    check.result.save(args.out / "sweep", title="twin check: OreSat (twin=0) and its twin (twin=1)",
                      figure=False)
    print(check.table())
    print(scene_table(check))
    print(f"Clutter among the 64 brightest detections: {radii['per_frame']:.1f} per frame; radius "
          f"percentiles {radii['percentiles']} real {radii['real_px']} px, uniform {radii['uniform_px']} px")


if __name__ == "__main__":
    main()
