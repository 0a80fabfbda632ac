"""Validate the renderer (``js.render``): real frames side by side, centroid error against the
Cramér–Rao bound, detection completeness, the extractor's settings, and speed.

Sections (``--sections``, all by default):

- ``real``: the four frames of ``shared/data/real`` against frames rendered at the same attitudes
  (fitted to the reference's matched stars) with the ``tetra3_test`` sensor
  (``js.sensor_for_camera``) and Hipparcos to V 9: background level and fall-off to the corners,
  pixel noise, PSF width, the extractor's zero point, star peaks, detections per frame.
- ``crb``: single stars at random sub-pixel positions over a range of brightness on a flat
  background; RMS error of ``js.extract_centroids`` per axis against the Cramér–Rao bound of the same
  pixel model (Gaussian PSF integrated over pixels, shot + read noise), as a function of SNR.
- ``completeness``: random attitudes on the ``tetra3_test`` camera: the fraction of the stars of
  each magnitude bin found (within 1.5 px), false detections per frame, and the centroid error, for
  a few ``CentroidConfig`` choices (threshold, window, pixel threshold).
- ``speed``: rendered frames per second at 1024 × 1024 and at the ``tetra3_test`` size.

Usage::

    python experiments/render_validation.py                      # everything, ≈ 3 min on 2 cores
    python experiments/render_validation.py --sections real crb

Writes results/render_validation/{config.json, results.json, table.md, crb.png, completeness.png}.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jstarid as js
from jstarid import experiment as ex

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
IMAGE_EPOCH = 2019.57  # the real frames' date (Julian years)
DEEP_MAG = 9.0  # stars rendered down to V 9 (the real frames show stars to V ≈ 7.5–8)
MATCH_PX = 1.5  # a detection within this of a rendered star is that star
SECTIONS = ("real", "crb", "completeness", "speed")


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/render_validation")
    p.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    p.add_argument("--data", type=Path, default=DATA, help="folder of real frames + reference.json")
    p.add_argument("--frames", type=int, default=200, help="frames per setting (completeness)")
    p.add_argument("--stars", type=int, default=4000, help="single-star frames per SNR level (crb)")
    return p.parse_args(argv)


# --- frame statistics, computed the same way on real and rendered frames ---------------------------

def local_noise(img) -> float:
    """Pixel noise σ (counts) from neighbouring-pixel differences (MAD): blind to gradients."""
    d = (img[:, 1:] - img[:, :-1]).ravel() / math.sqrt(2)
    return float(1.4826 * np.median(np.abs(d - np.median(d))))


def corner_ratio(img, tile=32) -> float:
    """Background in the corner tiles over the median tile (medians of 32² tiles, bias included)."""
    h, w = (s // tile * tile for s in img.shape)
    t = np.median(img[:h, :w].reshape(h // tile, tile, w // tile, tile), axis=(1, 3))
    return float(np.mean([t[0, 0], t[0, -1], t[-1, 0], t[-1, -1]]) / np.median(t))


def psf_sigma(img, xy, background, saturated) -> list[float]:
    """σ (px) of a round Gaussian fitted to each unsaturated star well above the noise."""
    from scipy.optimize import least_squares

    out = []
    yy, xx = np.mgrid[-6:7, -6:7]
    for x, y in xy:
        xi, yi = int(round(x)), int(round(y))
        if not (7 <= xi < img.shape[1] - 7 and 7 <= yi < img.shape[0] - 7):
            continue
        st = img[yi - 6:yi + 7, xi - 6:xi + 7].astype(np.float64)
        if not (2000 < st.max() - background and st.max() < saturated):
            continue

        def res(p, st=st):
            a, x0, y0, s, b = p
            return (a * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * s * s)) + b - st).ravel()

        out.append(abs(least_squares(res, [st.max() - background, 0, 0, 1.0, background]).x[3]))
    return out


def frame_stats(img, star_xy, star_v, centroid: js.CentroidConfig, saturated: float) -> dict:
    """Statistics of one frame; ``star_xy``/``star_v``: the known stars in it (px, V)."""
    bg = float(np.median(img))
    ext = js.extract_centroids(img[None].astype(np.float32), centroid, capacity=256)
    valid = np.asarray(ext.valid[0])
    xy, mag = np.asarray(ext.xy[0])[valid], np.asarray(ext.mag[0])[valid]
    d = np.linalg.norm(xy[:, None, :] - star_xy[None, :, :], axis=-1)
    j = np.argmin(d, axis=1)
    hit = d[np.arange(len(xy)), j] < MATCH_PX
    zp = star_v[j[hit]] - mag[hit]
    peaks = []
    for (x, y), v in zip(star_xy, star_v, strict=True):
        xi, yi = int(round(x)), int(round(y))
        if 6.0 <= v < 6.5 and 2 <= xi < img.shape[1] - 2 and 2 <= yi < img.shape[0] - 2:
            peaks.append(img[yi - 1:yi + 2, xi - 1:xi + 2].max() - bg)
    return {"background": bg, "corner_ratio": corner_ratio(img), "noise": local_noise(img),
            "psf_sigma_px": float(np.median(psf_sigma(img, star_xy, bg, saturated) or [np.nan])),
            "zero_point": float(np.median(zp)) if zp.size else math.nan,
            "peak_v6": float(np.median(peaks)) if peaks else math.nan,
            "detections": int(valid.sum()),
            "overflow": bool(ext.overflow[0])}


def scene_at(catalog, camera, c, capacity=512):
    """A one-scene batch of every catalog star in the frame at attitude ``c`` (no noise)."""
    proj, front = (np.asarray(a) for a in camera.project(catalog.unit_vectors @ np.asarray(c).T))
    rows = np.nonzero(front & np.asarray(camera.contains(proj)))[0]
    rows = rows[np.argsort(catalog.mag[rows])][:capacity]
    n = rows.size
    xy = np.zeros((1, capacity, 2), np.float32)
    mag = np.full((1, capacity), np.inf, np.float32)
    truth = np.full((1, capacity), -1, np.int32)
    valid = np.zeros((1, capacity), bool)
    xy[0, :n], mag[0, :n], truth[0, :n], valid[0, :n] = proj[rows], catalog.mag[rows], rows, True
    return js.Scene(xy=jnp.asarray(xy), mag=jnp.asarray(mag), truth=jnp.asarray(truth),
                    valid=jnp.asarray(valid), attitude=jnp.asarray(np.asarray(c, np.float32)[None]),
                    overflow=jnp.asarray([False]))


def sky_scale(real, sensor, camera) -> float:
    """Factor on the sensor's sky rate that gives the real frame's median background."""
    noiseless = np.asarray(js.mean_electrons(scene_at(js.load_catalog(0.0), camera, np.eye(3), 1),
                                             camera, sensor)[0])
    dark = sensor.dark_e_per_s * sensor.exposure_s
    want = (np.median(real) / sensor.counts_per_e - sensor.bias_adu * sensor.gain_e_per_adu) - dark
    return float(want / (np.median(noiseless) - dark))


def real_section(args) -> dict:
    """Real frames against frames rendered at their attitudes (``real`` in the module docstring)."""
    camera = js.camera_preset("tetra3_test")
    sensor = js.sensor_for_camera(camera)
    catalog = js.load_catalog(mag_limit=DEEP_MAG, epoch=IMAGE_EPOCH)
    ref = json.loads((args.data / "reference.json").read_text())
    centroid = js.CentroidConfig()
    saturated = 0.95 * 2 ** 16
    rows = {}
    for i, (name, r) in enumerate(sorted(ref.items())):
        real = js.read_image(args.data / name).astype(np.float32)
        c, _, _ = ex.reference_attitude(r["matches"], catalog, camera)
        scene = scene_at(catalog, camera, c)
        # the sky differs between pointings (×2 at Azi −45°): the preset's sky rate scaled to this
        # frame's median background (bias and dark current taken off both)
        sky = sensor.sky_e_per_s * sky_scale(real, sensor, camera)
        frame = np.asarray(js.render(jax.random.key(args.seed + i), scene, camera,
                                     sensor.replace(sky_e_per_s=sky))[0])
        valid = np.asarray(scene.valid[0])
        star_xy, star_v = np.asarray(scene.xy[0])[valid], np.asarray(scene.mag[0])[valid]
        rows[name] = {"real": frame_stats(real, star_xy, star_v, centroid, saturated),
                      "rendered": frame_stats(frame, star_xy, star_v, centroid, saturated),
                      "stars_to_v9": int(valid.sum()), "sky_e_per_s": sky}
        print(name, json.dumps(rows[name]))
    return {"sensor": dataclasses.asdict(sensor), "frames": rows}


# --- centroid error against the Cramér–Rao bound -----------------------------------------------------

CRB_CAMERA = js.Camera(48, 48, 300.0, mag_limit=6.0, name="crb")  # one star per small frame
CRB_SENSOR = js.SensorConfig(sky_e_per_s=200.0)  # 20 e⁻ sky + 5 e⁻ dark per pixel, 10 e⁻ read noise
CRB_MAGS = np.arange(2.0, 8.01, 0.5)


def noise_per_pixel_e2(sensor) -> float:
    """Background variance per pixel (e⁻²): sky and dark shot noise, read noise, the ADC's step²/12."""
    return ((sensor.sky_e_per_s + sensor.dark_e_per_s) * sensor.exposure_s + sensor.read_noise_e ** 2
            + sensor.gain_e_per_adu ** 2 / 12)


def star_snr(electrons, sensor) -> np.ndarray:
    """SNR of a star: F / √(F + n·(background variance)), n = 4π(σ² + 1/12) pixels (the footprint
    of a pixel-integrated Gaussian PSF)."""
    n = 4 * math.pi * (sensor.psf_sigma_px ** 2 + 1 / 12)
    return electrons / np.sqrt(electrons + n * noise_per_pixel_e2(sensor))


def centroid_crb_px(electrons, sensor, offsets) -> float:
    """Cramér–Rao bound on the x centroid (px, RMS over the sub-pixel ``offsets``) for the renderer's
    pixel model: pixel k ~ N(μ_k, v_k), μ_k = F·P_k(x, y) + b, v_k = μ_k + read² + step²/12, P_k the
    Gaussian integrated over the pixel; x, y, F and b unknown (the 4 × 4 Fisher matrix, whose terms
    are Σ ∂μ∂μ/v + ½ Σ ∂v∂v/v²)."""
    from scipy import special

    s = sensor.psf_sigma_px
    b = (sensor.sky_e_per_s + sensor.dark_e_per_s) * sensor.exposure_s
    extra = sensor.read_noise_e ** 2 + sensor.gain_e_per_adu ** 2 / 12
    k = np.arange(-12, 13, dtype=np.float64)
    crb = []
    for dx, dy in offsets:
        def frac(c):
            lo, hi = (k - 0.5 - c) / s, (k + 0.5 - c) / s
            f = 0.5 * (special.erf(hi / math.sqrt(2)) - special.erf(lo / math.sqrt(2)))
            df = -(np.exp(-hi ** 2 / 2) - np.exp(-lo ** 2 / 2)) / (s * math.sqrt(2 * math.pi))
            return f, df

        fx, dfx = frac(dx)
        fy, dfy = frac(dy)
        p = np.outer(fy, fx)
        grads = np.stack([electrons * np.outer(fy, dfx), electrons * np.outer(dfy, fx), p,
                          np.ones_like(p)]).reshape(4, -1)  # ∂μ/∂(x, y, F, b)
        v = (electrons * p + b + extra).ravel()
        fisher = (grads / v) @ grads.T + 0.5 * (grads / v ** 2) @ grads.T
        crb.append(np.linalg.inv(fisher)[0, 0])
    return float(np.sqrt(np.mean(crb)))


def crb_section(args) -> dict:
    """Centroid error of the extractor against the bound (``crb`` in the module docstring)."""
    cam, sensor = CRB_CAMERA, CRB_SENSOR
    rng = np.random.default_rng(args.seed)
    configs = {"default": js.CentroidConfig(), "no pixel threshold": js.CentroidConfig(pixel_sigma=0.0),
               "window 2": js.CentroidConfig(window_px=2)}
    rows = []
    for i, m in enumerate(CRB_MAGS):
        offsets = rng.uniform(-0.5, 0.5, (args.stars, 2))
        xy = np.array([cam.cx, cam.cy]) + offsets
        scenes = js.scenes_from_centroids(xy[:, None, :], np.full((args.stars, 1), m), capacity=1)
        frames = js.render(jax.random.key(1000 * args.seed + i), scenes, cam, sensor)
        e = float(sensor.star_electrons(m))
        row = {"mag": float(m), "electrons": e, "snr": float(star_snr(e, sensor)),
               "crb_px": centroid_crb_px(e, sensor, offsets[:200])}
        for name, cfg in configs.items():
            ext = js.extract_centroids(frames, cfg, capacity=4)
            valid = np.asarray(ext.valid)
            d = np.asarray(ext.xy)[:, :, 0] - xy[:, None, 0]
            d = np.where(valid & (np.abs(d) < 3), np.abs(d), np.inf).min(axis=1)
            found = np.isfinite(d)
            row[f"{name}: found"] = float(found.mean())
            row[f"{name}: rms_px"] = float(np.sqrt(np.mean(d[found] ** 2))) if found.any() else None
        rows.append(row)
        print(f"V {m:.1f}  {e:8.0f} e  SNR {row['snr']:6.1f}  CRB {row['crb_px']:.4f} px  "
              + "  ".join(f"{n}: {row[f'{n}: rms_px'] or math.nan:.4f} ({row[f'{n}: found']:.0%})"
                          for n in configs))
    return {"sensor": dataclasses.asdict(sensor), "camera": dataclasses.asdict(cam),
            "configs": {n: dataclasses.asdict(c) for n, c in configs.items()}, "rows": rows}


def draw_crb(results, path):
    rows = results["crb"]["rows"]
    snr = [r["snr"] for r in rows]
    series = [js.plotting.Series(snr, [r["crb_px"] for r in rows], "Cramér–Rao bound", "k-")]
    for name in results["crb"]["configs"]:
        pts = [(r["snr"], r[f"{name}: rms_px"]) for r in rows if r[f"{name}: rms_px"]]
        series.append(js.plotting.Series(*zip(*pts, strict=True), f"extract_centroids ({name})"))
    js.plotting.save_panels([js.plotting.Panel(
        series, xlabel="star SNR", ylabel="x centroid error, RMS (px)", xscale="log", yscale="log",
        title="Centroid error vs the bound (PSF σ 0.8 px, read noise 10 e⁻)")], path, size=(6.0, 4.0))


# --- detection completeness and false detections -----------------------------------------------------

COMPLETENESS_BINS = np.arange(3.0, 9.01, 0.5)


def completeness_section(args) -> dict:
    """Completeness, false detections and centroid error on tetra3_test (``completeness``)."""
    camera = js.camera_preset("tetra3_test")
    deep = dataclasses.replace(camera, mag_limit=DEEP_MAG)
    catalog = js.load_catalog(mag_limit=DEEP_MAG)
    sensor = js.sensor_for_camera(camera)
    scenes = js.simulate(jax.random.key(args.seed), catalog, deep, batch_size=args.frames, capacity=512)
    frames = js.render(jax.random.key(args.seed + 1), scenes, deep, sensor)
    valid = np.asarray(scenes.valid)
    truth_xy, truth_v = np.asarray(scenes.xy), np.asarray(scenes.mag)
    configs = {"default (5σ, window 4)": js.CentroidConfig(),
               "threshold 3σ": js.CentroidConfig(threshold_sigma=3.0),
               "threshold 8σ": js.CentroidConfig(threshold_sigma=8.0),
               "window 2": js.CentroidConfig(window_px=2),
               "no pixel threshold": js.CentroidConfig(pixel_sigma=0.0)}
    out = {}
    for name, cfg in configs.items():
        t = time.perf_counter()
        ext = js.extract_centroids(frames, dataclasses.replace(cfg, zero_point=sensor.zero_point()),
                                   capacity=256)
        seconds = time.perf_counter() - t
        ev, exy = np.asarray(ext.valid), np.asarray(ext.xy)
        found = np.zeros(valid.shape, bool)
        false, err = 0, []
        for b in range(args.frames):
            tx, got = truth_xy[b][valid[b]], exy[b][ev[b]]
            d = np.linalg.norm(got[:, None] - tx[None], axis=-1)
            j = np.argmin(d, axis=1) if tx.size else np.zeros(len(got), int)
            hit = d[np.arange(len(got)), j] < MATCH_PX if tx.size else np.zeros(len(got), bool)
            found[b, np.nonzero(valid[b])[0][j[hit]]] = True
            false += int((~hit).sum())
            bright = hit & (truth_v[b][valid[b]][j] < 6.5) if tx.size else hit
            err += list(d[np.arange(len(got)), j][bright]) if tx.size else []
        per_bin = []
        for lo in COMPLETENESS_BINS[:-1]:
            sel = valid & (truth_v >= lo) & (truth_v < lo + 0.5)
            per_bin.append(float(found[sel].mean()) if sel.any() else None)
        out[name] = {"completeness": per_bin, "false_per_frame": false / args.frames,
                     "rms_err_px_v_lt_6_5": float(np.sqrt(np.mean(np.square(err)))),
                     "overflow_frames": int(np.asarray(ext.overflow).sum()),
                     "frames_per_s": args.frames / seconds}
        print(f"{name:24s} false/frame {out[name]['false_per_frame']:.2f}  "
              f"RMS {out[name]['rms_err_px_v_lt_6_5']:.3f} px  completeness "
              + " ".join("–" if c is None else f"{c:.2f}" for c in per_bin))
    return {"bins_v": COMPLETENESS_BINS.tolist(), "sensor": dataclasses.asdict(sensor),
            "stars_per_frame": float(valid.sum(1).mean()), "configs": out}


def draw_completeness(results, path):
    r = results["completeness"]
    centres = np.asarray(r["bins_v"][:-1]) + 0.25
    series = [js.plotting.Series(centres, row["completeness"],
                                 f"{name}: {row['false_per_frame']:.1f} false/frame")
              for name, row in r["configs"].items()]
    js.plotting.save_panels([js.plotting.Panel(
        series, xlabel="V (mag)", ylabel="fraction of the stars detected",
        title="tetra3_test sensor: detection completeness")], path, size=(6.0, 4.0))


# --- speed ------------------------------------------------------------------------------------------

def speed_section(args) -> dict:
    """Rendered frames per second (``speed``): best of 3 after a first (compiling) call."""
    out = {}
    for name, mag_limit in (("sgm2022", None), ("tetra3_test", DEEP_MAG)):
        camera = js.camera_preset(name)
        deep = camera if mag_limit is None else dataclasses.replace(camera, mag_limit=mag_limit)
        catalog = js.load_catalog(mag_limit=deep.mag_limit)
        scenes = js.simulate(jax.random.key(0), catalog, deep, batch_size=128, capacity=256)
        sensor = js.sensor_for_camera(camera)
        def run(scenes=scenes, deep=deep, sensor=sensor):
            js.render(jax.random.key(1), scenes, deep, sensor).block_until_ready()

        run()
        best = min(_timed(run) for _ in range(3))
        out[name] = {"size": f"{camera.width}x{camera.height}", "frames_per_s": 128 / best,
                     "stars_per_frame": float(np.asarray(scenes.valid).sum(1).mean()),
                     "devices": jax.local_device_count()}
        print(name, json.dumps(out[name]))
    return out


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main(argv=None):
    args = parse_args(argv)
    js.use_cpu_cores()
    results = {}
    for name, run in (("real", real_section), ("crb", crb_section),
                      ("completeness", completeness_section), ("speed", speed_section)):
        if name in args.sections:
            results[name] = run(args)
    figures = {"crb.png": draw_crb} if "crb" in results else {}
    if "completeness" in results:
        figures["completeness.png"] = draw_completeness
    ex.write(args.out, config=vars(args), results=results, table=format_table(results), figures=figures)


def format_table(results) -> str:
    """table.md: the real-frame comparison, the CRB rows, completeness and speed."""
    parts = []
    if "real" in results:
        cols = [("frame", "frame", "{}"), ("what", "", "{}"), ("background", "background", "{:.0f}"),
                ("corner_ratio", "corner/median", "{:.2f}"), ("noise", "noise σ", "{:.0f}"),
                ("psf_sigma_px", "PSF σ fit (px)", "{:.2f}"), ("peak_v6", "peak V 6–6.5", "{:.0f}"),
                ("zero_point", "zero point", "{:.2f}"), ("detections", "detections", "{}")]
        rows = []
        for name, r in results["real"]["frames"].items():
            for what in ("real", "rendered"):
                rows.append({"frame": name.split("_")[1] + " " + name.split("_")[2], "what": what, **r[what]})
        parts.append(ex.markdown_table(rows, cols,
                                       title="Real frames and rendered frames at the same attitudes",
                                       note="Counts of the 16-bit frames. Rendered: tetra3_test sensor, the "
                                            "sky rate scaled to each frame's median, Hipparcos to V 9."))
    if "crb" in results:
        names = list(results["crb"]["configs"])
        cols = [("mag", "V", "{:.1f}"), ("electrons", "e⁻", "{:.0f}"), ("snr", "SNR", "{:.1f}"),
                ("crb_px", "CRB (px)", "{:.4f}")]
        cols += [(f"{n}: rms_px", f"{n} (px)", "{:.4f}") for n in names]
        cols += [(f"{n}: found", f"{n} found", "{:.0%}") for n in names]
        parts.append(ex.markdown_table(results["crb"]["rows"], cols,
                                       title="Centroid error (x, RMS) against the bound"))
    if "completeness" in results:
        r = results["completeness"]
        bins = r["bins_v"]
        cols = [("name", "CentroidConfig", "{}"), ("false_per_frame", "false/frame", "{:.2f}"),
                ("rms_err_px_v_lt_6_5", "RMS err V<6.5 (px)", "{:.3f}")]
        cols += [(f"c{i}", f"V {lo:.1f}", "{:.2f}") for i, lo in enumerate(bins[:-1]) if lo >= 5.0]
        rows = [{"name": n, **c, **{f"c{i}": v for i, v in enumerate(c["completeness"])}}
                for n, c in r["configs"].items()]
        parts.append(ex.markdown_table(rows, cols, title="Detection completeness on tetra3_test "
                                                         "(fraction found per 0.5-mag bin)"))
    if "speed" in results:
        rows = [{"camera": n, **v} for n, v in results["speed"].items()]
        parts.append(ex.markdown_table(rows, [("camera", "camera", "{}"), ("size", "frame", "{}"),
                                              ("stars_per_frame", "stars/frame", "{:.0f}"),
                                              ("frames_per_s", "frames/s", "{:.0f}"),
                                              ("devices", "devices", "{}")], title="Rendering speed"))
    return "\n".join(parts)


if __name__ == "__main__":
    main()
