"""End to end: identification from rendered frames against identification from simulated centroids.

For each sensor axis (exposure time, defocus) the engine draws one set of scenes per level from
pixels (``js.sweep(..., pixels=True)``: the sky to the camera's limit + 1.5 mag, rendered with the
camera's sensor, centroids extracted and labelled) and runs every algorithm on them. Beside it, the
same algorithms run on simulated centroids whose position noise σ is the centroid error the pixels
gave at that level (measured here: the labelled detections against their stars' true positions), so
the table says what the centroid-noise model predicts and what the pixels do. Also per level: the
detections per frame and the fraction of them that are catalog stars.

Usage::

    python experiments/end_to_end.py                    # MLV and RpNet on tetra3_test, ≈ 10 min
    python experiments/end_to_end.py --algorithms mlv --scenes 50

Writes results/end_to_end/{config.json, results.json, table.md, end_to_end.png}.
"""

from __future__ import annotations

import numpy as np

import jstarid as js
from jstarid import experiment as ex

AXES = {"exposure_s": [0.001, 0.002, 0.005, 0.01, 0.03, 0.33], "defocus_px": [0.0, 1.0, 2.0, 3.0, 4.0]}


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/end_to_end")
    p.add_argument("--algorithms", default="mlv,rpnet", help="comma-separated registry names")
    p.add_argument("--camera", default="tetra3_test", help="camera preset (its default sensor)")
    p.add_argument("--scenes", type=int, default=100, help="scenes per level")
    p.add_argument("--axes", nargs="+", default=list(AXES), choices=list(AXES))
    p.add_argument("--capacity", type=int, default=64, help="brightest detections kept per frame")
    return p.parse_args(argv)


def centroid_errors(scenes, catalog, camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per scene: RMS distance (px) of the labelled detections from their stars' true positions,
    the number of detections, and the fraction labelled (a catalog star)."""
    truth, valid = np.asarray(scenes.truth), np.asarray(scenes.valid)
    hit = valid & (truth >= 0)
    # each detection's star in the camera frame (B, N, 3), projected (px)
    body = np.einsum("bij,bnj->bni", np.asarray(scenes.attitude, np.float64),
                     catalog.unit_vectors[np.maximum(truth, 0)])
    proj, _ = camera.project(body)
    err2 = np.where(hit, np.sum((np.asarray(scenes.xy) - np.asarray(proj)) ** 2, axis=-1), np.nan)
    with np.errstate(invalid="ignore"):
        rms = np.sqrt(np.nanmean(err2, axis=1))
    n = valid.sum(1)
    labelled = np.where(n > 0, hit.sum(1) / np.maximum(n, 1), np.nan)
    return rms, n, labelled


def run_axis(axis, args, algorithms, camera) -> list[dict]:
    """One axis: the pixel sweep and the matching centroid sweep, one row per level and algorithm."""
    levels = AXES[axis]
    drawn = js.engine.simulate_levels(camera, axes={axis: levels}, scenes=args.scenes, seed=args.seed,
                                      capacity=args.capacity, pixels=True, progress=True)
    pix = js.compare(drawn.scenes, algorithms, drawn.catalog, drawn.camera, level_of=drawn.level_of,
                     levels=drawn.levels, progress=True)
    rms, n, labelled = centroid_errors(drawn.scenes, drawn.catalog, camera)
    # σ per axis of a 2-D error whose RMS length is r: r / √2 (NaN: no star detected at that level)
    sigma = [float(np.nanmedian(rms[drawn.level_of == i]) / np.sqrt(2))
             if np.isfinite(rms[drawn.level_of == i]).any() else float("nan") for i in range(len(levels))]
    measured = sorted({s for s in sigma if np.isfinite(s)})
    cen = js.sweep(algorithms, camera, axes={"position_sigma_px": measured}, scenes=args.scenes,
                   seed=args.seed, catalog=drawn.catalog, capacity=args.capacity, progress=True)
    by_sigma = {(r["label"], r["position_sigma_px"]): r for r in cen.rows()}
    rows = []
    for r_pix in pix.rows():
        i = levels.index(r_pix[axis])
        at = drawn.level_of == i
        r_cen = by_sigma.get((r_pix["label"], sigma[i]), {})
        rows.append({"axis": axis, "level": r_pix[axis], "algorithm": r_pix["label"],
                     "centroid_sigma_px": sigma[i], "detections": float(np.mean(n[at])),
                     "labelled": float(np.nanmean(labelled[at])),
                     "pixels_identified": r_pix["identification_rate"],
                     "pixels_low": r_pix["identification_low"], "pixels_high": r_pix["identification_high"],
                     "pixels_misid": r_pix["misid_rate"],
                     "centroids_identified": r_cen.get("identification_rate"),
                     "centroids_misid": r_cen.get("misid_rate")})
        print(rows[-1], flush=True)
    return rows


def draw(results, path):
    rows = results["rows"]
    Series = js.plotting.Series
    panels = []
    for axis in dict.fromkeys(r["axis"] for r in rows):
        series = []
        for k, name in enumerate(dict.fromkeys(r["algorithm"] for r in rows)):
            sel = [r for r in rows if r["axis"] == axis and r["algorithm"] == name]
            x = [r["level"] for r in sel]
            y = np.array([r["pixels_identified"] for r in sel])
            err = [y - [r["pixels_low"] for r in sel], [r["pixels_high"] for r in sel] - y]
            series += [Series(x, y, f"{name}: pixels", "o-", yerr=err, color=f"C{k}"),
                       Series(x, [r["centroids_identified"] for r in sel], f"{name}: centroids, same σ",
                              "s--", color=f"C{k}", alpha=0.7)]
        panels.append(js.plotting.Panel(series, xlabel=js.engine.AXES[axis], ylabel="identified",
                                        xscale="log" if axis == "exposure_s" else "linear",
                                        ylim=(-0.02, 1.02)))
    js.plotting.save_panels(panels, path,
                            title=f"{results['camera']}: from rendered frames vs from simulated centroids")


def main(argv=None):
    args = parse_args(argv)
    js.use_cpu_cores()
    js.enable_compilation_cache()
    camera = js.camera_preset(args.camera)
    algorithms = [a for a in args.algorithms.split(",") if a]
    rows = [row for axis in args.axes for row in run_axis(axis, args, algorithms, camera)]
    cols = [("axis", "axis", "{}"), ("level", "level", "{:g}"), ("algorithm", "algorithm", "{}"),
            ("detections", "detections/frame", "{:.0f}"), ("labelled", "in catalog", "{:.0%}"),
            ("centroid_sigma_px", "centroid σ (px)", "{:.3f}"),
            ("pixels_identified", "identified (pixels)", "{:.1%}"),
            ("pixels_misid", "misid (pixels)", "{:.1%}"),
            ("centroids_identified", "identified (centroids)", "{:.1%}"),
            ("centroids_misid", "misid (centroids)", "{:.1%}")]
    table = ex.markdown_table(rows, cols, title=f"End to end on {args.camera}",
                              note=f"{args.scenes} scenes per level, seed {args.seed}; the sensor "
                                   "is js.sensor_for_camera's with the level's value; centroids: "
                                   "simulated with position σ = the pixels' measured centroid error "
                                   "(– where no star was detected).")
    print(table)
    ex.write(args.out, config={**vars(args), "sensor": js.sensor_for_camera(camera)},
             results={"rows": rows, "camera": args.camera}, table=table, figures={"end_to_end.png": draw})


if __name__ == "__main__":
    main()
