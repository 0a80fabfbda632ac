"""Centroid extraction (jstarid.centroid) against a NumPy/SciPy reference, the truth of synthetic
images, and the real test images of shared/data/real."""

import json
from pathlib import Path

import jax
import numpy as np
import pytest
from scipy import interpolate, ndimage, special

import jstarid as js
from jstarid.centroid import CentroidConfig, background, extract_centroids
from jstarid.image_files import read_image

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
H, W = 192, 256


def gaussian_star(h, w, x, y, flux, psf_sigma=0.8):
    """A Gaussian PSF integrated over each pixel (pixel (0, 0) centred on (0, 0))."""
    def axis(n, c):
        edges = (np.arange(n + 1) - 0.5 - c) / (np.sqrt(2.0) * psf_sigma)
        return 0.5 * np.diff(special.erf(edges))
    return flux * np.outer(axis(h, y), axis(w, x))


def synthetic_image(seed=0, n_stars=12, noise=10.0, saturate=None, hot_pixel=True):
    """Stars at random sub-pixel positions on a sloped background with Gaussian read noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W]
    img = 1000.0 + 0.8 * xx + 0.5 * yy  # sky gradient
    xy = np.stack([rng.uniform(8, W - 9, n_stars), rng.uniform(8, H - 9, n_stars)], -1)
    # keep stars apart (the duplicate radius merges closer ones by design) and off the hot pixel
    for i in range(n_stars):
        while np.min(np.max(np.abs(np.vstack([xy[:i], [60, 50]]) - xy[i]), axis=1)) < 12:
            xy[i] = [rng.uniform(8, W - 9), rng.uniform(8, H - 9)]
    flux = np.geomspace(40_000, 2_000, n_stars)
    for (x, y), f in zip(xy, flux, strict=True):
        img += gaussian_star(H, W, x, y, f)
    img += rng.normal(0.0, noise, img.shape)
    if hot_pixel:
        img[50, 60] += 5_000.0  # a single hot pixel, far from every star
    if saturate is not None:
        img = np.minimum(img, saturate)
    return img.astype(np.float32), xy, flux


def reference_centroids(img, cfg: CentroidConfig):
    """The module's steps written independently with NumPy / SciPy (float64 after the median)."""
    img = img.astype(np.float32)
    h, w = img.shape
    t = cfg.tile_px
    th, tw = -(-h // t), -(-w // t)
    padded = np.pad(img, ((0, th * t - h), (0, tw * t - w)), mode="reflect")
    k = cfg.sample_stride
    tiles = padded.reshape(th, t, tw, t).swapaxes(1, 2)[:, :, ::k, ::k]
    med = np.median(tiles.reshape(th, tw, -1), axis=-1)
    centre = np.mean(np.arange(t)[::k])  # of the sampled pixels of a tile
    ys = (np.arange(h) - centre) / t
    xs = (np.arange(w) - centre) / t
    gy, gx = np.meshgrid(ys, xs, indexing="ij")
    interp = interpolate.RegularGridInterpolator((np.arange(th), np.arange(tw)), med.astype(np.float64),
                                                 method="linear", bounds_error=False, fill_value=None)
    bg = interp(np.stack([gy, gx], -1))  # linear extrapolation beyond the outer tile centres
    r = img.astype(np.float64) - bg
    s = ndimage.uniform_filter(r, size=3, mode="constant")
    sigma = 1.4826 * np.median(np.abs(s[::2 * k, ::2 * k]))
    sigma_pix = 1.4826 * np.median(np.abs(r[::2 * k, ::2 * k]))
    size = 2 * cfg.peak_radius_px + 1
    lmax = ndimage.maximum_filter(s, size=size, mode="constant", cval=-np.inf)
    peak = (s > cfg.threshold_sigma * sigma) & (s >= lmax)
    flat = np.nonzero(peak.ravel())[0]
    flat = flat[np.argsort(-s.ravel()[flat], kind="stable")][: cfg.max_peaks]
    hw = cfg.window_px
    rp = np.pad(r, hw)
    stars = []  # (x, y, flux, peak y, peak x)
    for f in flat:
        py, px = divmod(int(f), w)
        win = rp[py:py + 2 * hw + 1, px:px + 2 * hw + 1]
        wt = np.where(win > cfg.pixel_sigma * sigma_pix, win, 0.0)
        if (wt > 0).sum() < cfg.min_pixels or wt.sum() <= 0:
            continue
        core = win[hw - 1:hw + 2, hw - 1:hw + 2]
        if core.max() > cfg.max_sharpness * core.sum():
            continue  # a hot pixel
        oy, ox = np.mgrid[-hw:hw + 1, -hw:hw + 1]
        stars.append((px + (wt * ox).sum() / wt.sum(), py + (wt * oy).sum() / wt.sum(), wt.sum(), py, px))
    kept = [a for i, a in enumerate(stars)
            if not any(abs(a[3] - b[3]) <= hw and abs(a[4] - b[4]) <= hw for b in stars[:i])]
    kept.sort(key=lambda a: -a[2])
    return np.array([[a[0], a[1]] for a in kept]), np.array([a[2] for a in kept])


def detections(scene, i=0):
    v = np.asarray(scene.valid[i])
    return np.asarray(scene.xy[i])[v], np.asarray(scene.mag[i])[v]


@pytest.mark.parametrize("seed, crop, stride", [(0, None, 2), (1, None, 2), (2, None, 2),
                                                (1, (150, 229), 2), (0, (150, 229), 1)])
def test_matches_numpy_scipy_reference(seed, crop, stride):
    img, _, _ = synthetic_image(seed, saturate=30_000.0 if seed == 2 else None)
    if crop is not None:  # not a whole number of tiles: the last ones are padded by reflection
        img = img[:crop[0], :crop[1]]
    cfg = CentroidConfig(sample_stride=stride)
    xy, mag = detections(extract_centroids(img, cfg, capacity=64))
    ref_xy, ref_flux = reference_centroids(img, cfg)
    assert xy.shape == ref_xy.shape
    np.testing.assert_allclose(xy, ref_xy, atol=1e-3)
    np.testing.assert_allclose(mag, -2.5 * np.log10(ref_flux), atol=1e-3)


def test_background_matches_tile_medians_interpolated():
    img, _, _ = synthetic_image(0, n_stars=0, hot_pixel=False, noise=0.0)
    bg = np.asarray(background(img, 32, 2))
    # a plane is reproduced everywhere (bilinear inside, linear extrapolation at the border)
    np.testing.assert_allclose(bg, img, atol=0.05)


def test_finds_every_star_at_its_true_position():
    img, xy_true, flux = synthetic_image(3)
    xy, mag = detections(extract_centroids(img, capacity=64))
    assert len(xy) == len(xy_true)  # every star; the hot pixel is rejected
    d = np.linalg.norm(xy[:, None] - xy_true[None], axis=-1)
    assert np.all(d.min(axis=1) < 0.1)  # thresholded CoG of a 0.8 px PSF: pixel-phase bias < 0.1 px
    assert np.all(np.diff(mag) >= 0)  # brightest first
    # brightness order follows the true fluxes (they differ by ≥ 30 % from star to star)
    np.testing.assert_array_equal(d.argmin(axis=1), np.arange(len(xy_true)))


def test_saturated_star_gives_one_detection_and_hot_pixel_none():
    img, xy_true, _ = synthetic_image(4, saturate=2_500.0)
    assert (img >= 2_500.0).sum() > 20  # plateaus exist
    xy, _ = detections(extract_centroids(img, capacity=64))
    d = np.linalg.norm(xy[:, None] - xy_true[None], axis=-1)
    assert len(xy) == len(xy_true)
    assert np.all(d.min(axis=1) < 0.3)
    assert not np.any(np.all(np.abs(xy - [60, 50]) < 3, axis=1))  # the hot pixel


def test_overflow_and_capacity_prefix():
    img, _, _ = synthetic_image(5)
    full = extract_centroids(img, capacity=64)
    small = extract_centroids(img, capacity=5)
    assert not bool(full.overflow[0]) and bool(small.overflow[0])
    np.testing.assert_array_equal(np.asarray(small.xy[0]), np.asarray(full.xy[0, :5]))
    assert int(small.valid.sum()) == 5
    # max_peaks below the number of peaks is reported too, never silently dropped
    few = extract_centroids(img, CentroidConfig(max_peaks=4), capacity=64)
    assert bool(few.overflow[0]) and int(few.valid.sum()) <= 4


def test_batch_jit_and_per_image_agree():
    imgs = np.stack([synthetic_image(s)[0] for s in (6, 7, 8)])
    batch = extract_centroids(imgs, capacity=32)
    for i in range(3):
        one = extract_centroids(imgs[i], capacity=32)
        for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(batch[i:i + 1]), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    again = extract_centroids(imgs, capacity=32)
    np.testing.assert_array_equal(np.asarray(again.xy), np.asarray(batch.xy))
    sharded = extract_centroids(imgs, capacity=32, shard=True)  # 3 images over 4 CPU devices (1 GPU)
    for a, b in zip(jax.tree.leaves(sharded), jax.tree.leaves(batch), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.all(np.asarray(batch.truth) == -1) and np.all(np.isnan(np.asarray(batch.attitude)))


def test_flat_and_noise_only_images_have_no_detection():
    flat = np.full((H, W), 1234.0, np.float32)
    noise = np.random.default_rng(0).normal(1000.0, 10.0, (H, W)).astype(np.float32)
    out = extract_centroids(np.stack([flat, noise]), capacity=16)
    assert int(out.valid.sum()) == 0 and not np.any(np.asarray(out.overflow))


def test_bad_input_raises():
    img, _, _ = synthetic_image(0)
    bad = img.copy()
    bad[3, 4] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        extract_centroids(bad)
    with pytest.raises(ValueError, match="shape"):
        extract_centroids(img[0])
    with pytest.raises(ValueError, match="smaller"):
        extract_centroids(img[:16, :16])
    with pytest.raises(ValueError, match="real"):
        extract_centroids(img.astype(np.complex64))
    with pytest.raises(ValueError, match="capacity"):
        extract_centroids(img, capacity=0)
    for field, value in [("tile_px", 2), ("threshold_sigma", 0.0), ("window_px", 0),
                         ("min_pixels", 0), ("max_peaks", 0), ("max_sharpness", 0.0),
                         ("sample_stride", 0), ("zero_point", np.nan)]:
        with pytest.raises(ValueError, match=field):
            CentroidConfig(**{field: value})


needs_real = pytest.mark.skipif(not (REAL / "reference.json").exists(),
                                reason="shared/data/real not present")


@pytest.fixture(scope="module")
def real_images():
    ref = json.loads((REAL / "reference.json").read_text())
    names = sorted(ref)
    return ref, names, np.stack([read_image(REAL / n) for n in names])


@needs_real
def test_real_images_find_the_reference_stars(real_images):
    ref, names, imgs = real_images
    scenes = extract_centroids(imgs, capacity=256)
    for i, name in enumerate(names):
        xy, _ = detections(scenes, i)
        # the reference's pixel origin is a pixel corner, ours the first pixel's centre
        ref_xy = np.array([[m["x"], m["y"]] for m in ref[name]["matches"]]) - 0.5
        dist = np.linalg.norm(ref_xy[:, None] - xy[None], axis=-1)
        d = dist.min(axis=1)
        assert np.mean(d < 1.0) >= 0.95, name
        assert np.median(d) < 0.25, name  # two centroiders agree to a fraction of a pixel
        offset = np.median((xy[dist.argmin(axis=1)] - ref_xy)[d < 1.0], axis=0)
        assert np.all(np.abs(offset) < 0.1), (name, offset)  # and no half-pixel convention slip


@needs_real
def test_real_images_identified_by_mlv(real_images):
    """Raw pixels → centroids → MLV → attitude, against the independent reference solve."""
    ref, names, imgs = real_images
    cam = js.camera_preset("tetra3_test")
    cat = js.load_catalog(mag_limit=7.0)
    algo = js.algorithms.get("mlv")
    cfg = algo.Config()
    scenes = extract_centroids(imgs, capacity=24)
    result = algo.identify(algo.build_database(cat, cam, cfg), scenes, cfg)
    att, _, have = js.estimate_attitude(cat, cam, scenes, result)
    for i, name in enumerate(names):
        assert bool(result.ok[i]) and bool(have[i]), name
        ra, dec = np.radians([ref[name]["boresight_ra_deg"], ref[name]["boresight_dec_deg"]])
        bore = np.array([np.cos(ra) * np.cos(dec), np.sin(ra) * np.cos(dec), np.sin(dec)])
        c2 = np.asarray(att[i, 2], np.float64)
        sep = np.arctan2(np.linalg.norm(np.cross(c2, bore)), c2 @ bore)
        assert np.degrees(sep) * 3600 < 60, name
        # every name the reference also gives agrees with it
        ids = np.asarray(result.ids[i])
        xy = np.asarray(scenes.xy[i])
        ref_hip = {m["hip"]: np.array([m["x"], m["y"]]) - 0.5 for m in ref[name]["matches"]}
        named = np.nonzero(ids >= 0)[0]
        assert len(named) >= 5, name
        for j in named:
            hip = int(cat.hip[ids[j]])
            at_ref = [h for h, p in ref_hip.items() if np.linalg.norm(p - xy[j]) < 1.5]
            assert not at_ref or at_ref == [hip], (name, j)


def test_plot_image_draws_detections_and_labels(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    img, _, _ = synthetic_image(0)
    xy, _ = detections(extract_centroids(img, capacity=8))
    labels = [f"HIP {k}" for k in range(len(xy) - 1)] + [""]
    correct = [True] * (len(xy) - 2) + [False, None]
    ax = js.plotting.plot_image(img, xy, labels=labels, correct=correct)
    assert len(ax.patches) == len(xy) and len(ax.texts) == len(xy) - 1
    assert [p.get_edgecolor()[:3] for p in ax.patches[-2:]] == [(1.0, 0.0, 0.0), (1.0, 1.0, 1.0)]
    ax.figure.savefig(tmp_path / "frame.png")
    assert (tmp_path / "frame.png").stat().st_size > 5_000
