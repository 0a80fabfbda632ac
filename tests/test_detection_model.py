"""The detection model (jstarid.detection_model): the papers' special case, its curves against the
simulator, blends against brute force, the sensor-derived model and bad settings."""

from __future__ import annotations

import dataclasses
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import ndtr

import jstarid as js
from jstarid.detection_model import merge_close

# m50 = 5.0 on a V ≤ 6 catalog: the whole completeness curve lies inside the identification catalog
STATS_MODEL = js.DetectionModel(zero_point_e=1e4, background_e2=900.0, threshold_e=100.0,
                                detection_background_e2=400.0, position_scale_px=1.0,
                                position_background_e2=2000.0)


def _fields(scenes):
    return {f: np.asarray(getattr(scenes, f)) for f in ("xy", "mag", "truth", "valid", "overflow")}


@pytest.mark.parametrize("model", [None, js.DetectionModel.ideal(),
                                   js.DetectionModel(zero_point_e=np.full(12, np.inf))])
def test_the_ideal_model_is_the_papers_noise(catalog6, sgm_camera, model):
    """No photometric noise: the same scenes as the four knobs alone — bit for bit where the model is
    one scalar setting (the papers' own program runs), to float32 rounding where it is a per-scene
    array (the model's program: XLA may fuse the same sums differently)."""
    noise = js.NoiseConfig(position_sigma_px=np.linspace(0, 2, 12), magnitude_sigma=0.2, n_missing=1,
                           n_false=2)
    key = jax.random.key(5)
    plain = _fields(js.simulate(key, catalog6, sgm_camera, noise, batch_size=12))
    with_model = _fields(js.simulate(key, catalog6, sgm_camera, noise, batch_size=12, detection=model))
    exact = model is None or np.ndim(model.zero_point_e) == 0
    for name, value in plain.items():
        if exact or value.dtype != np.float32:
            np.testing.assert_array_equal(value, with_model[name], err_msg=name)
        else:
            np.testing.assert_allclose(value, with_model[name], rtol=1e-6, atol=1e-6, err_msg=name)


@pytest.fixture(scope="module")
def stats_scenes(catalog6, sgm_camera):
    """400 scenes drawn from STATS_MODEL and the same attitudes without noise, to V 7."""
    key = jax.random.key(11)
    drawn = js.simulate(key, catalog6, sgm_camera, batch_size=400, capacity=96, detection=STATS_MODEL)
    deep = dataclasses.replace(sgm_camera, mag_limit=7.0)
    sky = js.simulate(key, catalog6, deep, batch_size=400, capacity=256)
    return drawn, sky


def _per_star(drawn, sky):
    """Every identification-catalog star in the field: V, detected?, Δm, Δxy (px)."""
    sky_truth = np.asarray(sky.truth)
    stars = np.asarray(sky.valid) & (sky_truth >= 0)  # (B, M)
    same = sky_truth[:, :, None] == np.asarray(drawn.truth)[:, None, :]  # (B, M, N)
    same &= stars[:, :, None]
    found = same.any(axis=2)
    j = np.argmax(same, axis=2)  # (B, M) the detection of each star found
    det_mag = np.take_along_axis(np.asarray(drawn.mag), j, axis=1)
    det_xy = np.take_along_axis(np.asarray(drawn.xy), j[..., None], axis=1)
    dmag = np.where(found, det_mag - np.asarray(sky.mag), np.nan)
    dxy = np.where(found[..., None], det_xy - np.asarray(sky.xy), np.nan)
    return np.asarray(sky.mag)[stars], found[stars], dmag[stars], dxy[stars]


def _reference_magnitudes(model, mag, n=200_000, seed=0):
    """Plain NumPy draws of the model at one magnitude: (detected fraction, mean Δm of detections)."""
    rng = np.random.default_rng(seed)
    s = model.zero_point_e * 10 ** (-0.4 * mag)
    z = rng.standard_normal(n)
    rho, rho_d = math.sqrt(s + model.background_e2) / s, math.sqrt(s + model.detection_background_e2) / s
    detected = (s * (1 + rho_d * z) >= model.threshold_e) & (1 + rho * z > 0)
    dm = -2.5 * np.log10(1 + rho * z[detected])
    return detected.mean(), dm.mean()


def test_completeness_bias_and_position_noise_follow_the_model(stats_scenes):
    """Per 0.25-mag bin: the detected fraction against Φ((S − T)/√(S + B_d)), the mean magnitude
    residual against NumPy draws of the model (the bias near the threshold), the position σ against
    c √(S + B_c) / S."""
    v, found, dmag, dxy = _per_star(*stats_scenes)
    checked = 0
    for lo in np.arange(4.0, 6.0, 0.25):
        sel = (v >= lo) & (v < lo + 0.25)
        if sel.sum() < 60:
            continue
        checked += 1
        mid = float(np.mean(v[sel]))
        expect = float(np.mean(STATS_MODEL.completeness(v[sel])))
        assert abs(found[sel].mean() - expect) < 4 * math.sqrt(expect * (1 - expect) / sel.sum()) + 0.02
        hit = sel & found
        if hit.sum() >= 40:
            frac, bias = _reference_magnitudes(STATS_MODEL, mid)
            assert abs(np.mean(dmag[hit]) - bias) < 0.03 + 3 * np.std(dmag[hit]) / math.sqrt(hit.sum())
            sigma = float(STATS_MODEL.position_sigma(mid))
            got = float(np.std(dxy[hit]))
            assert abs(got / sigma - 1) < 0.2, (lo, got, sigma)
    assert checked >= 5
    # the bias is real: detections near the threshold come out brighter than they are
    faint = (v > 5.1) & found
    assert np.mean(dmag[faint]) < -0.05


def test_merge_close_against_brute_force():
    rng = np.random.default_rng(4)
    for _ in range(30):
        k = 60
        xy = rng.uniform(0, 60, (k, 2)).astype(np.float32)
        flux = rng.uniform(0.1, 1.0, k).astype(np.float32)
        live = rng.random(k) < 0.9
        radius = 3.0
        got_xy, got_flux, absorbed, overflow = (np.asarray(a) for a in jax.jit(merge_close)(
            jnp.asarray(xy), jnp.asarray(flux), jnp.asarray(live), radius))
        d = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
        near = (d < radius) & live[:, None] & live[None] & ~np.eye(k, dtype=bool)
        target = np.arange(k)
        for i in range(k):
            j = np.nonzero(near[i])[0]
            if j.size and flux[j].max() > flux[i]:
                target[i] = j[np.argmax(flux[j])]
        np.testing.assert_array_equal(absorbed, target != np.arange(k))
        for r in np.nonzero(~absorbed & live)[0]:
            members = np.nonzero(target == r)[0]
            np.testing.assert_allclose(got_flux[r], flux[members].sum(), rtol=1e-5)
            centroid = (flux[members, None] * xy[members]).sum(0) / flux[members].sum()
            np.testing.assert_allclose(got_xy[r], centroid, atol=1e-4)
        assert not overflow  # 60 stars over 60 px: never 16 within 3 px in x order
    # a column of stars stacked in x beyond the window is flagged, not silently left apart
    xy = np.stack([np.full(40, 10.0), np.arange(40) * 5.0], -1).astype(np.float32)
    *_, overflow = merge_close(jnp.asarray(xy), jnp.ones(40), jnp.ones(40, bool), 3.0)
    assert bool(overflow)


def test_blended_scenes_have_no_two_detections_within_the_radius(catalog6, sgm_camera):
    model = STATS_MODEL.replace(merge_radius_px=40.0, position_scale_px=0.0)
    scenes = js.simulate(jax.random.key(2), catalog6, sgm_camera, batch_size=50, capacity=96,
                         detection=model)
    plain = js.simulate(jax.random.key(2), catalog6, sgm_camera, batch_size=50, capacity=96,
                        detection=model.replace(merge_radius_px=0.0))
    assert not np.asarray(plain.overflow).any()
    assert int(np.asarray(scenes.overflow).sum()) <= 10  # the check below reads ≥ 40 scenes
    # blends carry their members' light: stars too faint alone are detected together
    assert not np.array_equal(np.asarray(scenes.truth), np.asarray(plain.truth))
    # no two detections' stars lie within the radius (their blends' centroids may: a star between two
    # joins the brighter and pulls its centroid towards the other)
    sky = js.simulate(jax.random.key(2), catalog6, dataclasses.replace(sgm_camera, mag_limit=7.0),
                      batch_size=50, capacity=256)
    for b in range(50):
        where = {int(r): xy for r, xy in zip(np.asarray(sky.truth[b]), np.asarray(sky.xy[b]), strict=True)
                 if r >= 0}
        rows = [int(r) for r in np.asarray(scenes.truth[b]) if r >= 0]
        xy = np.array([where[r] for r in rows]).reshape(-1, 2)
        if len(xy) > 1 and not bool(scenes.overflow[b]):
            d = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + 1e9 * np.eye(len(xy))
            assert d.min() >= 40.0 - 1e-3


def test_from_sensor_detects_the_generic_sensor_to_the_camera_limit(sgm_camera):
    """The generic sensor puts 500 e⁻ in a star at the camera's limit: comfortably detected."""
    model = js.DetectionModel.from_sensor(sgm_camera)
    sensor = js.sensor_for_camera(sgm_camera)
    np.testing.assert_allclose(model.zero_point_e * 10 ** (-0.4 * sgm_camera.mag_limit), 500.0, rtol=1e-6)
    assert model.completeness(sgm_camera.mag_limit) > 0.99
    assert model.completeness(sgm_camera.mag_limit + 2.0) < 0.01
    per_pixel = sensor.dark_e_per_s * sensor.exposure_s + sensor.read_noise_e ** 2
    box = model.threshold_e / (3 * 5.0 * math.sqrt(per_pixel))  # T = 3 · 5σ · √b / f₉
    assert 0.5 < 1 / box < 1.0
    np.testing.assert_allclose(model.completeness(np.array([5.0, 7.0])),
                               ndtr((model._electrons(np.array([5.0, 7.0])) - model.threshold_e)
                                    / np.sqrt(model._electrons(np.array([5.0, 7.0]))
                                              + model.detection_background_e2)))
    # the centroid curve: a star at the limit (SNR ≈ 12) wanders a few tenths of a pixel
    assert 0.05 < float(model.position_sigma(sgm_camera.mag_limit)) < 0.5


def test_a_model_deeper_than_the_simulation_list_warns(catalog6, sgm_camera):
    deep = js.DetectionModel(zero_point_e=1e7, threshold_e=100.0, detection_background_e2=100.0)
    with pytest.warns(UserWarning, match="simulation list"):
        js.simulate(jax.random.key(0), catalog6, sgm_camera, batch_size=4, detection=deep)
    # a model of a few electrons (a fit to a shallow frame): its noise alone clears the threshold
    few = js.DetectionModel(zero_point_e=1390.0, background_e2=4.7, threshold_e=2.84,
                            detection_background_e2=0.89)
    assert few.faintest_detectable(odds=1e-3) > 30.0
    with pytest.warns(UserWarning, match="at any depth"):
        js.simulate(jax.random.key(0), catalog6, sgm_camera, batch_size=4, detection=few)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        js.simulate(jax.random.key(0), catalog6, sgm_camera, batch_size=4, detection=STATS_MODEL)


@pytest.mark.parametrize("changes", [{"background_e2": -1.0}, {"zero_point_e": 0.0},
                                     {"vignetting": 1.0}, {"merge_radius_px": np.nan},
                                     {"threshold_e": np.inf}])
def test_bad_settings_are_refused(catalog6, sgm_camera, changes):
    with pytest.raises(ValueError, match="DetectionModel"):
        js.simulate(jax.random.key(0), catalog6, sgm_camera, batch_size=2,
                    detection=STATS_MODEL.replace(**changes))


def test_a_model_per_scene_and_a_wrong_type(catalog6, sgm_camera):
    """Fields are per-scene arrays (an exposure sweep is one batch); anything else is refused."""
    zero = np.array([1e4, 1e4, 2e4, 2e4])
    scenes = js.simulate(jax.random.key(3), catalog6, sgm_camera, batch_size=4, capacity=128,
                         detection=STATS_MODEL.replace(zero_point_e=zero))
    n = np.asarray(scenes.n_stars)
    assert n[2:].sum() > n[:2].sum()
    with pytest.raises(ValueError, match="shape"):
        js.simulate(jax.random.key(3), catalog6, sgm_camera, batch_size=3,
                    detection=STATS_MODEL.replace(zero_point_e=zero))
    with pytest.raises(ValueError, match="DetectionModel"):
        js.simulate(jax.random.key(3), catalog6, sgm_camera, batch_size=4, detection={"zero_point_e": 1})


def test_a_fit_recovers_the_model_that_drew_the_scenes(catalog6, sgm_camera):
    """Records from scenes drawn with a known model and floors: the fitted curves match the true ones
    (completeness to 0.06, magnitude and position σ to 25 %) and the offset is found."""
    truth = STATS_MODEL.replace(zero_point_e=1.8e4)  # m50 ≈ 5.6: stars past it are in the V ≤ 6 catalog
    noise = js.NoiseConfig(magnitude_sigma=0.05, position_sigma_px=0.05)
    key = jax.random.key(21)
    drawn = js.simulate(key, catalog6, sgm_camera, noise, batch_size=600, capacity=128, detection=truth)
    sky = js.simulate(key, catalog6, dataclasses.replace(sgm_camera, mag_limit=7.0), batch_size=600,
                      capacity=256)
    v, found, dmag, dxy = _per_star(drawn, sky)
    fit = js.DetectionModel.fit(v, found, v + dmag + 1.3, dxy)
    assert abs(fit.magnitude_offset - 1.3) < 0.03
    assert fit.stars == v.size and fit.detected == int(found.sum())
    mags = np.arange(4.0, 6.01, 0.25)
    np.testing.assert_allclose(fit.model.completeness(mags, fit.magnitude_sigma),
                               truth.completeness(mags, 0.05), atol=0.06)
    bright = mags[mags <= 5.5]
    np.testing.assert_allclose(fit.model.magnitude_sigma(bright, fit.magnitude_sigma),
                               truth.magnitude_sigma(bright, 0.05), rtol=0.25)
    np.testing.assert_allclose(fit.model.position_sigma(bright, fit.position_sigma_px),
                               truth.position_sigma(bright, 0.05), rtol=0.25)
    assert fit.noise().magnitude_sigma == fit.magnitude_sigma
    with pytest.raises(ValueError, match="past the detection limit"):
        js.DetectionModel.fit(v[found], found[found])
    with pytest.raises(ValueError, match="finite"):
        js.DetectionModel.fit(np.where(np.arange(v.size) == 3, np.nan, v), found)
    # positions without scatter: no photon term, not a made-up one
    exact = js.DetectionModel.fit(v, found, position_error_px=np.zeros((v.size, 2)))
    assert exact.model.position_scale_px == 0.0 and exact.position_sigma_px == 0.0


def test_unmatched_detections_become_clutter():
    """Detections that are no catalog star: a Poisson mean per frame and the slope of their magnitudes
    (drawn here from the simulator's own false-star distribution) come back as NoiseConfig clutter."""
    from jstarid.simulator import _false_magnitudes

    noise = js.NoiseConfig(false_mag_min=5.0, false_mag_max=9.0, false_mag_slope=js.CATALOG_MAG_SLOPE)
    loose = np.asarray(_false_magnitudes(jax.random.uniform(jax.random.key(0), (3000,)), noise))
    rng = np.random.default_rng(0)
    v = rng.uniform(3, 9, 500)
    found = v < 7.5
    fit = js.DetectionModel.fit(v, found, v + 0.4, unmatched_mag=loose + 0.4, frames=150)
    assert fit.clutter["false_mean"] == 20.0
    assert abs(fit.clutter["false_mag_slope"] - js.CATALOG_MAG_SLOPE) < 0.05
    assert 5.0 <= fit.clutter["false_mag_min"] < 5.05 and 8.95 < fit.clutter["false_mag_max"] <= 9.0
    assert fit.noise().false_mean == 20.0
    with pytest.raises(ValueError, match="frames"):
        js.DetectionModel.fit(v, found, unmatched_mag=loose)
    assert "false_mag_knee" not in fit.clutter  # one slope drew them: no knee gains enough


def test_clutter_piling_up_at_the_threshold_gets_a_knee():
    """A sparse bright tail over noise peaks just above the threshold (as OreSat's extractor finds):
    the fitted knee and slopes, drawn back through the simulator, put as many clutter detections
    brighter than each magnitude as the sample has."""
    from jstarid.simulator import _false_magnitudes

    truth = js.NoiseConfig(false_mag_min=2.0, false_mag_max=7.3, false_mag_slope=2.0, false_mag_knee=6.5,
                           false_mag_slope_faint=-0.3)
    loose = np.asarray(_false_magnitudes(jax.random.uniform(jax.random.key(1), (6000,)), truth))
    rng = np.random.default_rng(1)
    v = rng.uniform(3, 9, 500)
    fit = js.DetectionModel.fit(v, v < 7.0, v, unmatched_mag=loose, frames=20)
    clutter = fit.clutter
    assert abs(clutter["false_mag_knee"] - 6.5) < 0.1
    assert abs(clutter["false_mag_slope"] - 2.0) < 0.2 and abs(clutter["false_mag_slope_faint"] + 0.3) < 0.2
    redrawn = np.asarray(_false_magnitudes(jax.random.uniform(jax.random.key(2), (6000,)), fit.noise()))
    for m in (5.5, 6.0, 6.5):
        assert abs(np.mean(redrawn < m) - np.mean(loose < m)) < 0.02


@pytest.mark.production_numerics
def test_sharded_draws_equal_one_device(catalog6, sgm_camera, several_devices):
    """A physical model with blends: the same scenes whether the batch is split over devices or not."""
    model = STATS_MODEL.replace(merge_radius_px=5.0, vignetting=0.3, sky_fraction=0.5)
    noise = js.NoiseConfig(position_sigma_px=0.2, magnitude_sigma=0.1, n_false=2)
    one = js.simulate(jax.random.key(8), catalog6, sgm_camera, noise, batch_size=10, capacity=96,
                      detection=model)
    many = js.simulate(jax.random.key(8), catalog6, sgm_camera, noise, batch_size=10, capacity=96,
                       detection=model, shard=True)
    np.testing.assert_array_equal(np.asarray(one.truth), np.asarray(many.truth))
    np.testing.assert_allclose(np.asarray(one.xy), np.asarray(many.xy), atol=1e-4)
    np.testing.assert_allclose(np.asarray(one.mag), np.asarray(many.mag), atol=1e-5)
