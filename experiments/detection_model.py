"""The detection model beside rendered and real frames: completeness, magnitude and position residuals by
magnitude, and detections per frame, for the ``tetra3_test`` camera.

Three sources, measured the same way (every catalog star in the field, V ≤ 10, is a star that could be
detected; a detection within 1.5 px of one is that star):

- ``model``: ``js.simulate(..., detection=js.DetectionModel.from_sensor(camera))``, centroids drawn
  straight from the model (no pixels);
- ``rendered``: the same attitudes rendered (``js.render``, ``js.sensor_for_camera``) and extracted
  (``js.extract_centroids``);
- ``real``: the four frames of ``shared/data/real`` (when present), at the attitudes fitted to their
  reference solutions' matched stars, extracted the same way;
- ``fitted``: ``js.DetectionModel.fit`` to the real frames' stars, simulated at the model's attitudes
  (with the fit's floors as ``NoiseConfig``).

Usage::

    python experiments/detection_model.py               # 200 frames per source, ≈ 2 min on 2 cores

Writes results/detection_model/{config.json, results.json, table.md, curves.png}.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.engine.pixels import detect_scenes

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
IMAGE_EPOCH = 2019.57  # the real frames' date (Julian years)
DEEP = 10.0  # V: catalog stars to this depth are the stars that could be detected
BINS = np.arange(3.0, 10.01, 0.5)
MATCH_PX = 1.5


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/detection_model")
    p.add_argument("--frames", type=int, default=200, help="simulated and rendered frames")
    p.add_argument("--data", type=Path, default=DATA, help="folder of real frames + reference.json")
    return p.parse_args(argv)


def matched(det_xy, det_mag, star_xy, star_v):
    """Per star of one frame: detected?, measured − catalog magnitude, position residual (2,) (px);
    and the magnitudes of the detections that are no star (``ex.claim_detections``, brightest star
    first)."""
    order = np.argsort(star_v, kind="stable")
    star_of = ex.claim_detections(det_xy, star_xy[order], MATCH_PX)
    claimed = star_of >= 0
    stars = order[star_of[claimed]]
    found = np.zeros(len(star_xy), bool)
    dmag = np.full(len(star_xy), np.nan)
    dxy = np.full((len(star_xy), 2), np.nan)
    found[stars] = True
    dmag[stars] = det_mag[claimed] - star_v[stars]
    dxy[stars] = det_xy[claimed] - star_xy[stars]
    return found, dmag, dxy, det_mag[~claimed]


def curves(frames) -> dict:
    """Binned curves from ``[(found, dmag, dxy, star_v, n_detections), …]`` (one per frame)."""
    found = np.concatenate([f[0] for f in frames])
    dmag = np.concatenate([f[1] for f in frames])
    dxy = np.concatenate([f[2] for f in frames])
    v = np.concatenate([f[3] for f in frames])
    out = {"completeness": [], "mag_bias": [], "mag_sigma": [], "position_sigma_px": [], "stars": []}
    for lo in BINS[:-1]:
        sel = (v >= lo) & (v < lo + 0.5)
        hit = sel & found
        out["stars"].append(int(sel.sum()))
        out["completeness"].append(float(found[sel].mean()) if sel.sum() >= 5 else None)
        if hit.sum() >= 5:
            r = dmag[hit]
            out["mag_bias"].append(float(np.median(r)))
            out["mag_sigma"].append(float(1.4826 * np.median(np.abs(r - np.median(r)))))
            p = dxy[hit] - np.median(dxy[hit], axis=0)
            out["position_sigma_px"].append(float(1.4826 * np.median(np.abs(p))))
        else:
            for k in ("mag_bias", "mag_sigma", "position_sigma_px"):
                out[k].append(None)
    out["detections_per_frame"] = float(np.median([f[4] for f in frames]))
    return out


def simulated_sources(args, camera, sensor, model, fitted=None) -> dict:
    """Model and rendered frames (and the fitted model's) at the same random attitudes."""
    catalog = js.load_catalog(DEEP, sim_margin=0.5)
    deep = dataclasses.replace(camera, mag_limit=DEEP)
    key = jax.random.key(args.seed)
    sky = js.simulate(key, catalog, deep, batch_size=args.frames, capacity=1024)
    drawn = js.simulate(key, catalog, camera, js.NoiseConfig(), batch_size=args.frames, capacity=512,
                        detection=model)
    frame_keys = jax.random.split(jax.random.key(args.seed + 1), args.frames)
    rendered, _ = detect_scenes(frame_keys, sky, deep, sensor, js.CentroidConfig(), capacity=512)
    sources = [("model", drawn), ("rendered", rendered)]
    if fitted is not None:
        sources.append(("fitted", js.simulate(key, catalog, camera, fitted.noise(), batch_size=args.frames,
                                              capacity=512, detection=fitted.model)))
    out = {}
    for name, scenes in sources:
        frames = []
        for b in range(args.frames):
            sv = np.asarray(sky.valid[b])
            star_xy, star_v = np.asarray(sky.xy[b])[sv], np.asarray(sky.mag[b])[sv]
            dv = np.asarray(scenes.valid[b])
            det_xy, det_mag = np.asarray(scenes.xy[b])[dv], np.asarray(scenes.mag[b])[dv]
            frames.append((*matched(det_xy, det_mag, star_xy, star_v)[:3], star_v, int(dv.sum())))
        out[name] = curves(frames)
        out[name]["overflow_frames"] = int(np.asarray(scenes.overflow).sum())
    return out


def real_source(args, camera, sensor):
    """The shared real frames at their reference attitudes, extracted as the rendered ones: their
    curves and the fitted model (``None`` without the frames)."""
    if not (args.data / "reference.json").exists():
        return None
    catalog = js.load_catalog(DEEP, epoch=IMAGE_EPOCH)
    ref = json.loads((args.data / "reference.json").read_text())
    centroid = js.CentroidConfig(zero_point=sensor.zero_point())
    frames, loose = [], []
    for name, r in sorted(ref.items()):
        image = js.read_image(args.data / name).astype(np.float32)
        c, _, _ = ex.reference_attitude(r["matches"], catalog, camera)
        proj, front = (np.asarray(a) for a in camera.project(np.einsum("ij,nj->ni", c, catalog.unit_vectors)))
        inside = front & np.asarray(camera.contains(proj))
        found = js.extract_centroids(image[None], centroid, capacity=512)
        dv = np.asarray(found.valid[0])
        det_xy, det_mag = np.asarray(found.xy[0])[dv], np.asarray(found.mag[0])[dv]
        star_v = catalog.mag[inside]
        found, dmag, dxy, unmatched = matched(det_xy, det_mag, proj[inside], star_v)
        frames.append((found, dmag, dxy, star_v, int(dv.sum())))
        loose.append(unmatched)
    v, found, dmag, dxy = (np.concatenate([f[i] for f in frames]) for i in (3, 0, 1, 2))
    # the sensor's zero point sets the electrons' unit: the frames' magnitude scatter is dominated by
    # the floors (vignetting, colour), which leave the shot-noise term that would fix it unmeasured
    fitted = js.DetectionModel.fit(v, found, v + dmag, dxy, zero_point_e=sensor.star_electrons(0.0),
                                   unmatched_mag=np.concatenate(loose), frames=len(frames))
    return curves(frames) | {"frames": len(frames)}, fitted


def main(argv=None):
    args = parse_args(argv)
    js.use_cpu_cores()
    camera = js.camera_preset("tetra3_test")
    sensor = js.sensor_for_camera(camera)
    model = js.DetectionModel.from_sensor(camera, sensor)
    real, fitted = real_source(args, camera, sensor) or (None, None)
    results = simulated_sources(args, camera, sensor, model, fitted)
    if real is not None:
        results["real"] = real
        results["fitted_fields"] = {**dataclasses.asdict(fitted.model),
                                    "magnitude_sigma": fitted.magnitude_sigma,
                                    "position_sigma_px": fitted.position_sigma_px,
                                    "magnitude_offset": fitted.magnitude_offset, "stars": fitted.stars,
                                    **fitted.clutter}
    results["model_fields"] = dataclasses.asdict(model)
    results["bins_v"] = BINS.tolist()
    ex.write(args.out, config=vars(args), results=results, table=format_table(results),
             figures={"curves.png": draw})
    print(format_table(results))


def _cell(x, fmt):
    return "–" if x is None else format(x, fmt)


def format_table(results) -> str:
    """table.md: one row per magnitude bin, the three sources side by side."""
    sources = [s for s in ("model", "rendered", "real", "fitted") if s in results]
    head = ["V"] + [f"{q} {s}" for q in ("complete", "Δm", "σm", "σxy px") for s in sources]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, lo in enumerate(results["bins_v"][:-1]):
        row = [f"{lo:.1f}–{lo + 0.5:.1f}"]
        for q, fmt in (("completeness", ".2f"), ("mag_bias", "+.2f"), ("mag_sigma", ".2f"),
                       ("position_sigma_px", ".3f")):
            row += [_cell(results[s][q][i], fmt) for s in sources]
        lines.append("| " + " | ".join(row) + " |")
    lines.append("")
    lines.append("Detections per frame (median): " + ", ".join(
        f"{s} {results[s]['detections_per_frame']:.0f}" for s in sources))
    return "\n".join(lines) + "\n"


def draw(results, path):
    mid = np.asarray(results["bins_v"][:-1]) + 0.25
    curves = (("completeness", "completeness"), ("mag_bias", "measured − catalog V (mag)"),
              ("mag_sigma", "magnitude σ (mag)"), ("position_sigma_px", "position σ per axis (px)"))
    sources = (("model", "-o"), ("rendered", "--s"), ("real", ":^"), ("fitted", "-.v"))
    panels = [js.plotting.Panel(
        [js.plotting.Series(mid, results[source][key], source, style) for source, style in sources
         if source in results],
        xlabel="catalog V (mag)", ylabel=label, yscale="log" if key == "position_sigma_px" else "linear",
        legend=key == "completeness") for key, label in curves]
    js.plotting.save_panels(panels, path, size=(4.0, 3.8), dpi=110,
                            title="tetra3_test: the sensor's detection model beside rendered frames; real "
                                  "frames and the model fitted to them")


if __name__ == "__main__":
    main()
