"""Identify the stars of real night-sky images, from the raw pixels to the attitude.

The four test images of ``shared/data/real`` (FLIR Blackfly S + 35 mm lens, 1024×768 px, ≈ 11.4°
horizontal field; the ``tetra3_test`` camera preset) go through the whole pipeline:
:func:`jstarid.centroid.extract_centroids` on the raw 16-bit TIFFs, the chosen algorithms with a
database built for this camera and a catalog to ``--mag-limit`` (positions at the images' epoch),
and :func:`jstarid.estimate_attitude`. The results are checked against an independent solve
(``reference.json``, cedar-solve 0.5.1):

- **ground truth for every detection**: the attitude fitted to the reference's matched list (its
  centroids shifted by −0.5 px: cedar-solve puts the pixel origin at a corner, ours at the first
  pixel's centre; the median offset of our centroids from its is measured and printed) projects the
  catalog into the image; a detection within ``--truth-px`` of a projected star (and of no other) is
  that star, every other detection is unlabelled (a star fainter than the catalog, a hot pixel, a
  ghost of a bright star);
- a named detection is **correct** when its name is its truth label and **wrong** otherwise (also when
  it is unlabelled: a failure is better than a guess);
- **boresight error**: the angle between our boresight and the reference's RA/Dec (arcsec).

``--set ALGORITHM.FIELD=VALUE`` changes one algorithm's config. Each starts from its defaults for
the camera and for real frames (``js.engine.default_config(..., frames=True)``: SGM's neighbor
circle 3.8°, the paper's 6° being wider than this 8.6°-high frame allows, and its magnitude-robust
``subgraph`` search, ``--set sgm.subgraph=false`` for the paper's; RpNet uses the ``quick``
network, trained for this camera on first use, then cached).

Usage::

    python experiments/real_images.py                       # MLV, RpNet (quick) and SGM
    python experiments/real_images.py --algorithms mlv --mag-limit 6.5
    python experiments/real_images.py --algorithms sgm --set sgm.radius_deg=4

Writes results/real_images/{config.json, results.json, table.md} and one figure per image
(``<image>.png``: the frame, the kept detections, the names and whether each is right).
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.centroid import CentroidConfig, extract_centroids
from jstarid.image_files import read_image

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
IMAGE_EPOCH = 2019.57  # 2019-07-29, the date in the file names (Julian years)
TRUTH_MAG_LIMIT = 9.0  # truth labels from Hipparcos to V 9 (the images reach V ≈ 7.5–8)


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/real_images")
    p.epilog = "--set takes ALGORITHM.FIELD=VALUE here, e.g. sgm.radius_deg=4 (SGM starts at 3.8)."
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder of images + reference.json")
    p.add_argument("--algorithms", nargs="+", default=["mlv", "rpnet", "sgm"])
    p.add_argument("--mag-limit", type=float, default=7.0, help="catalog depth (V)")
    p.add_argument("--capacity", type=int, default=24, help="brightest detections kept per image")
    p.add_argument("--truth-px", type=float, default=2.0, help="ground-truth matching radius (px)")
    p.add_argument("--tol-px", type=float, default=2.0,
                   help="js.name_from_attitude tolerance (px) for the 'all' columns")
    args = p.parse_args(argv)
    unknown = [item for item in args.set if item.split(".", 1)[0] not in args.algorithms]
    if unknown:
        p.error(f"--set {' '.join(unknown)}: write ALGORITHM.FIELD=VALUE, ALGORITHM one of --algorithms")
    return args


def algorithm_config(name: str, overrides, camera):
    """``name``'s config for these images (its defaults for ``camera``), with the ``--set`` items
    that start with ``name.``."""
    # RpNet: the quick network, trained for this camera on first use, then cached
    base = js.engine.default_config(name, camera=camera, frames=True)
    return ex.with_overrides(base, [i.split(".", 1)[1] for i in overrides if i.startswith(name + ".")])


def reference_truth(ref, catalog, camera, xy, valid, truth_px):
    """Truth labels (N,) Hipparcos numbers (−1 unlabelled) and the reference attitude (3, 3).

    ``catalog`` is the deep truth catalog (:data:`TRUTH_MAG_LIMIT`), so a detection of a star fainter
    than the identification catalog is labelled too (any name given to it is wrong).
    """
    c, ref_xy, _ = ex.reference_attitude(ref["matches"], catalog, camera)
    proj, in_front = (np.asarray(a) for a in camera.project(catalog.unit_vectors @ c.T))
    cand = np.nonzero(in_front & np.asarray(camera.contains(proj, -truth_px)))[0]
    d = np.linalg.norm(xy[:, None, :] - proj[None, cand, :], axis=-1)
    close = d <= truth_px
    truth = np.where(valid & (close.sum(1) == 1), catalog.hip[cand[np.argmax(close, axis=1)]], -1)
    return truth, c, ref_xy


def boresight_error_arcsec(c, ra_deg, dec_deg):
    ra, dec = math.radians(ra_deg), math.radians(dec_deg)
    ref = np.array([math.cos(ra) * math.cos(dec), math.sin(ra) * math.cos(dec), math.sin(dec)])
    return math.degrees(math.atan2(np.linalg.norm(np.cross(c[2], ref)), float(c[2] @ ref))) * 3600.0


def main(argv=None):
    args = parse_args(argv)
    reference = json.loads((args.data / "reference.json").read_text())
    names = sorted(reference)
    images = np.stack([read_image(args.data / n) for n in names])
    camera = js.camera_preset("tetra3_test")
    catalog = js.load_catalog(mag_limit=args.mag_limit, epoch=IMAGE_EPOCH)
    truth_catalog = js.load_catalog(mag_limit=TRUTH_MAG_LIMIT, epoch=IMAGE_EPOCH)
    centroid_cfg = CentroidConfig()
    with ex.Stopwatch() as t_centroid:
        scenes = extract_centroids(images, centroid_cfg, capacity=args.capacity)
        xy, valid = np.asarray(scenes.xy), np.asarray(scenes.valid)
    # every detection, for the statistics
    deep = extract_centroids(images, centroid_cfg, capacity=centroid_cfg.max_peaks)

    def v_of(hips):  # V (truth catalog) of Hipparcos numbers
        return truth_catalog.mag[truth_catalog.row_of_hip(np.asarray(hips))]

    per_image = []
    for i, name in enumerate(names):
        truth, c_ref, ref_xy = reference_truth(reference[name], truth_catalog, camera, xy[i], valid[i],
                                               args.truth_px)
        dvalid = np.asarray(deep.valid[i])
        dxy, dmag = np.asarray(deep.xy[i])[dvalid], np.asarray(deep.mag[i])[dvalid]
        d = np.linalg.norm(ref_xy[:, None] - dxy[None], axis=-1)
        found = d.min(axis=1) <= 1.0
        offset = np.median(dxy[d.argmin(axis=1)][found] - ref_xy[found], axis=0)
        # photometry: instrumental magnitude against V over every labelled detection
        deep_truth, _, _ = reference_truth(reference[name], truth_catalog, camera, dxy,
                                           np.ones(len(dxy), bool), args.truth_px)
        zp = v_of(deep_truth[deep_truth > 0]) - dmag[deep_truth > 0]
        per_image.append(dict(
            image=name, xy=np.round(xy[i][valid[i]], 3).tolist(),
            detections=int(np.asarray(deep.valid[i]).sum()),
            detections_overflow=bool(np.asarray(deep.overflow[i])),
            kept=int(valid[i].sum()), labelled=int((truth >= 0).sum()),
            reference_matches=len(ref_xy), reference_found=int(found.sum()),
            offset_from_reference_px=[round(float(v), 3) for v in offset],
            distance_to_reference_px={"median": round(float(np.median(d.min(axis=1)[found])), 3),
                                      "max": round(float(d.min(axis=1)[found].max()), 3)},
            zero_point={"median": round(float(np.median(zp)), 3),
                        "mad": round(float(np.median(np.abs(zp - np.median(zp)))), 3),
                        "stars": int(zp.size)},
            kept_labelled_v=np.round(v_of(truth[truth > 0]), 2).tolist(),
            reference_boresight_check_arcsec=round(boresight_error_arcsec(
                c_ref, reference[name]["boresight_ra_deg"], reference[name]["boresight_dec_deg"]), 1),
            truth=truth.tolist(), algorithms={}))

    timings, configs = {}, {a: algorithm_config(a, args.set, camera) for a in args.algorithms}
    for algo_name, cfg in configs.items():
        algo = js.algorithms.get(algo_name)
        db = algo.build_database(catalog, camera, cfg)
        with ex.Stopwatch() as clock:
            if algo_name == "sgm":  # with the diagnostics of why a scene failed
                result, info = algo.identify(db, scenes, cfg, diagnostics=True)
            else:
                result, info = algo.identify(db, scenes, cfg), None
        timings[algo_name] = clock.seconds
        full = js.name_from_attitude(catalog, camera, scenes, result, tol_px=args.tol_px)
        fits = {key: [np.asarray(a) for a in js.estimate_attitude(catalog, camera, scenes, res)]
                for key, res in (("own", result), ("all", full))}
        for i, name in enumerate(names):
            truth = np.asarray(per_image[i]["truth"])
            entry = dict(ok=bool(np.asarray(result.ok)[i]))
            for key, res in (("own", result), ("all", full)):
                ids_k = np.asarray(res.ids)[i]
                named = valid[i] & (ids_k >= 0)
                hip = np.where(named, catalog.hip[np.maximum(ids_k, 0)], -1)
                att, rms, have = (a[i] for a in fits[key])
                correct = int(np.sum(named & (hip == truth)))
                unnamed = valid[i] & ~named & (truth > 0)
                entry[key] = dict(named=int(named.sum()), correct=correct, hip=hip[valid[i]].tolist(),
                                  unnamed_labelled_v=np.round(v_of(truth[unnamed]), 2).tolist(),
                                  wrong=int(named.sum()) - correct,
                                  residual_arcsec=round(float(rms), 1) if have else None,
                                  boresight_error_arcsec=(round(boresight_error_arcsec(
                                      att, reference[name]["boresight_ra_deg"],
                                      reference[name]["boresight_dec_deg"]), 1) if have else None))
            if info is not None:
                main_hip = int(truth[info.main[i]])
                row = catalog.row_of_hip([main_hip])[0] if main_hip > 0 else -1
                graphs = np.nonzero(db.main == row)[0] if row >= 0 else []
                entry["sgm_details"] = dict(
                    image_graph_vertices=int(info.n_i[i]), best_error_deg=float(info.error[i]),
                    main_star_hip=main_hip, main_star_in_catalog=bool(row >= 0),
                    main_star_database_graph_vertices=[int(db.n[g]) for g in graphs])
            per_image[i]["algorithms"][algo_name] = entry

    config = dict(vars(args), epoch=IMAGE_EPOCH, centroid=centroid_cfg, algorithm_configs=configs)
    results = dict(images=per_image, centroid_seconds=t_centroid.seconds, identify_seconds=timings)
    table = format_table(results, args)
    figures = {Path(n).stem + ".png": functools.partial(plot, n, args.data) for n in names}
    ex.write(args.out, config=config, results=results, table=table, figures=figures)
    print(table)


def plot(image: str, data: Path, results, path):
    """The figure of ``image`` from the saved results: the frame, every kept detection, and the
    names of the first algorithm that solved it after ``name_from_attitude`` (green: the ground
    truth's, red: not). Reads the image file and the results; never recomputes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for im in results["images"]:
        if im["image"] != image:
            continue
        solved = [(a, e) for a, e in im["algorithms"].items() if e["ok"]]
        labels, correct, title = None, None, "not solved"
        if solved:
            algo, e = solved[0]
            hip, truth = e["all"]["hip"], im["truth"]
            labels = [f"HIP {h}" if h >= 0 else "" for h in hip]
            correct = [h == t if h >= 0 else None for h, t in zip(hip, truth, strict=False)]
            title = f"{algo} + name_from_attitude: {e['all']['named']} named, {e['all']['wrong']} wrong"
        ax = js.plotting.plot_image(read_image(data / im["image"]), im["xy"], labels=labels,
                                    correct=correct)
        ax.set_title(f"{im['image']}\n{title}", fontsize=8)
        ax.figure.tight_layout()
        ax.figure.savefig(path, dpi=110)
        plt.close(ax.figure)


def format_table(results, args) -> str:
    """Markdown: per algorithm its own names, then every detection its attitude explains."""
    head = " | ".join(f"{a}: own names (wrong) | {a} + name_from_attitude: names (wrong) / "
                      f"boresight error ″ / residual ″" for a in args.algorithms)
    lines = [f"Catalog V ≤ {args.mag_limit}, brightest {args.capacity} detections per image.", "",
             f"| image | detections | kept (labelled) | reference found | {head} |",
             "|---|---|---|---|" + "---|---|" * len(args.algorithms)]
    for im in results["images"]:
        cells = []
        for a in args.algorithms:
            e = im["algorithms"][a]
            if not e["ok"] or e["all"]["boresight_error_arcsec"] is None:
                cells += ["failed", "failed"]
                continue
            own, full = e["own"], e["all"]
            cells += [f"{own['named']} ({own['wrong']})",
                      f"{full['named']} ({full['wrong']}) / {full['boresight_error_arcsec']:.1f} / "
                      f"{full['residual_arcsec']:.1f}"]
        short = im["image"].split("_")[2]
        more = "> " if im["detections_overflow"] else ""
        lines.append(f"| {short} | {more}{im['detections']} | {im['kept']} ({im['labelled']}) | "
                     f"{im['reference_found']} of {im['reference_matches']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    js.use_cpu_cores()
    js.enable_compilation_cache()
    main()
