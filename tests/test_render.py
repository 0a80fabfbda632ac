"""The renderer (js.render): pixel model against SciPy, recovery by the extractor, noise, detector."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import special

import jstarid as js
from jstarid.render import psf_offsets

CAM = js.Camera(96, 64, 300.0, mag_limit=6.0)  # small frame: cheap to compile and render


def _scenes(xy, mag):
    """A batch of scenes (B, N) from (B, N, 2) positions and (B, N) magnitudes (NaN: padding)."""
    xy, mag = np.asarray(xy, np.float32), np.asarray(mag, np.float32)
    valid = np.isfinite(mag)
    return js.Scene(xy=jnp.asarray(np.where(valid[..., None], xy, 0)),
                    mag=jnp.asarray(np.where(valid, mag, np.inf)),
                    truth=jnp.asarray(np.where(valid, 0, -1).astype(np.int32)), valid=jnp.asarray(valid),
                    attitude=jnp.asarray(np.tile(np.eye(3, dtype=np.float32), (len(mag), 1, 1))),
                    overflow=jnp.zeros(len(mag), bool))


def _reference_mean(xy, mag, sensor, camera):
    """Expected electrons of one frame, written out in NumPy/SciPy (no vignetting, no hot pixels)."""
    ys, xs = np.mgrid[:camera.height, :camera.width]
    img = np.full((camera.height, camera.width), sensor.dark_e_per_s * sensor.exposure_s + sensor.sky_e_per_s
                  * sensor.exposure_s)
    s = sensor.psf_sigma_px * math.sqrt(2)
    pts = psf_offsets(sensor)
    for (x, y), m in zip(xy, mag, strict=True):
        flux = sensor.star_electrons(m)
        for dx, dy in pts:
            fx = 0.5 * (special.erf((xs + 0.5 - x - dx) / s) - special.erf((xs - 0.5 - x - dx) / s))
            fy = 0.5 * (special.erf((ys + 0.5 - y - dy) / s) - special.erf((ys - 0.5 - y - dy) / s))
            img += flux / len(pts) * fx * fy
    return img


@pytest.mark.parametrize("shape", [dict(), dict(defocus_px=2.5), dict(smear_px=6.0, smear_angle_rad=0.6)])
def test_mean_frame_equals_the_scipy_pixel_integrals(shape):
    sensor = js.SensorConfig(sky_e_per_s=300.0, **shape)
    xy = np.array([[20.3, 30.7], [60.5, 12.2], [94.8, 62.9]])  # the last one at the frame's corner
    mag = np.array([3.0, 4.5, 4.0])
    got = np.asarray(js.mean_electrons(_scenes(xy[None], mag[None]), CAM, sensor)[0])
    want = _reference_mean(xy, mag, sensor, CAM)
    # the window holds all but < 1e-6 of each star; the corner star loses what falls off the frame
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6 * sensor.star_electrons(3.0))
    # the two stars inside the frame deliver all their electrons
    background = (sensor.sky_e_per_s + sensor.dark_e_per_s) * sensor.exposure_s
    inner = got[:, :80] - background
    assert inner.sum() == pytest.approx(sensor.star_electrons(mag[:2]).sum(), rel=1e-5)


def test_smear_spreads_the_star_along_its_direction():
    sensor = js.SensorConfig(smear_px=8.0, smear_angle_rad=0.0, sky_e_per_s=0.0, dark_e_per_s=0.0)
    img = np.asarray(js.mean_electrons(_scenes([[[40.0, 30.0]]], [[3.0]]), CAM, sensor)[0])
    ys, xs = np.mgrid[:CAM.height, :CAM.width]
    w = img / img.sum()
    var_x = np.sum(w * (xs - np.sum(w * xs)) ** 2)
    var_y = np.sum(w * (ys - np.sum(w * ys)) ** 2)
    # a segment of L along x: σ² + 1/12 (pixel) + L²/12 (to the midpoint rule's 1 − 1/n²)
    n = len(psf_offsets(sensor))
    assert var_y == pytest.approx(0.8 ** 2 + 1 / 12, rel=1e-3)
    assert var_x == pytest.approx(0.8 ** 2 + 1 / 12 + 8.0 ** 2 / 12 * (1 - 1 / n ** 2), rel=1e-3)
    assert np.sum(w * xs) == pytest.approx(40.0, abs=1e-3)  # centred on the mid-exposure position


def test_defocus_spreads_the_star_into_a_ring():
    sensor = js.SensorConfig(defocus_px=5.0, sky_e_per_s=0.0, dark_e_per_s=0.0)
    img = np.asarray(js.mean_electrons(_scenes([[[40.0, 30.0]]], [[3.0]]), CAM, sensor)[0])
    ys, xs = np.mgrid[:CAM.height, :CAM.width]
    w = img / img.sum()
    r2 = (xs - 40.0) ** 2 + (ys - 30.0) ** 2
    # a ring of radius R blurred by σ and the pixel: E r² = R² + 2 (σ² + 1/12)
    assert np.sum(w * r2) == pytest.approx(5.0 ** 2 + 2 * (0.8 ** 2 + 1 / 12), rel=1e-3)
    assert img[30, 40] < 0.05 * img.max()  # a dark centre
    assert np.sum(w * xs) == pytest.approx(40.0, abs=1e-3) and np.sum(w * ys) == pytest.approx(30.0, abs=1e-3)


def test_extractor_recovers_rendered_positions_and_magnitudes():
    rng = np.random.default_rng(0)
    gx, gy = np.meshgrid(np.arange(12, 90, 16.0), np.arange(12, 60, 16.0))
    xy = np.stack([gx.ravel(), gy.ravel()], 1) + rng.uniform(-0.5, 0.5, (gx.size, 2))  # 15 stars
    mag = rng.uniform(3.0, 4.0, gx.size)
    sensor = js.sensor_for_camera(CAM)
    frames = js.render(jax.random.key(1), _scenes(np.tile(xy, (4, 1, 1)), np.tile(mag, (4, 1))), CAM, sensor)
    ext = js.extract_centroids(frames, js.CentroidConfig(zero_point=sensor.zero_point()), capacity=32)
    assert np.asarray(ext.valid).sum(1).tolist() == [xy.shape[0]] * 4  # every star, nothing else
    for b in range(4):
        got = np.asarray(ext.xy[b])[np.asarray(ext.valid[b])]
        d = np.linalg.norm(got[:, None] - xy[None], axis=-1)
        j = np.argmin(d, axis=1)
        assert sorted(j.tolist()) == list(range(xy.shape[0]))
        # ≈ 5,000 e⁻ per star against 10 e⁻ read noise: σ/SNR ≈ 0.01 px, plus the windowing bias
        assert np.sqrt(np.mean(np.min(d, axis=1) ** 2)) < 0.06
        # the thresholded window keeps ≈ 98 % of the flux; flux noise ≈ 0.015 mag
        dm = np.asarray(ext.mag[b])[np.asarray(ext.valid[b])] - mag[j]
        assert np.all(np.abs(dm) < 0.1) and abs(np.median(dm)) < 0.04


def test_deterministic_per_frame_and_sharding_invariant():
    sc = _scenes(np.tile([[30.2, 20.7], [70.0, 40.1]], (5, 1, 1)), np.tile([4.0, np.nan], (5, 1)))
    keys = jax.random.split(jax.random.key(3), 5)
    a = np.asarray(js.render(keys, sc, CAM))
    np.testing.assert_array_equal(a, np.asarray(js.render(keys, sc, CAM)))
    np.testing.assert_array_equal(a, np.asarray(js.render(keys, sc, CAM, shard=False)))
    one = jax.tree.map(lambda x: x[2:3], sc)
    np.testing.assert_array_equal(a[2], np.asarray(js.render(keys[2:3], one, CAM))[0])
    assert not np.array_equal(a[0], a[1])  # each frame its own noise
    b = np.asarray(js.render(jax.random.key(3), sc, CAM))
    np.testing.assert_array_equal(a, b)  # one key is split into the same frame keys
    assert np.all(a == np.round(a))


@pytest.mark.parametrize("mode", ["gaussian", "poisson"])
def test_background_noise_has_the_shot_and_read_variance(mode):
    sensor = js.SensorConfig(sky_e_per_s=4000.0, dark_e_per_s=0.0, read_noise_e=5.0, gain_e_per_adu=1.0,
                             bit_depth=16, bias_adu=100.0, shot_noise=mode)
    frames = np.asarray(js.render(jax.random.key(0), _scenes(np.zeros((4, 1, 2)), np.full((4, 1), np.nan)),
                                  CAM, sensor))
    mean = 4000.0 * 0.1
    assert frames.mean() - 100.0 == pytest.approx(mean, rel=2e-3)
    # variance: shot (mean) + read² + rounding (1/12)
    assert frames.var() == pytest.approx(mean + 25.0 + 1 / 12, rel=0.03)


def test_saturation_quantization_and_stored_bits():
    sensor = js.SensorConfig(full_well_e=5000.0, gain_e_per_adu=2.0, bias_adu=50.0, bit_depth=12,
                             stored_bits=16, read_noise_e=2.0)
    frame = np.asarray(js.render(jax.random.key(0), _scenes([[[40.0, 30.0]]], [[-2.0]]), CAM, sensor)[0])
    top = round(5000.0 / 2.0 + 50.0) * 16
    assert frame.max() == top and np.sum(frame == top) >= 9  # a clipped plateau
    assert np.all(frame % 16 == 0)
    clipped = js.SensorConfig(full_well_e=1e6, gain_e_per_adu=1.0, bit_depth=12)
    frame = np.asarray(js.render(jax.random.key(0), _scenes([[[40.0, 30.0]]], [[-2.0]]), CAM, clipped)[0])
    assert frame.max() == 4095  # the ADC's range


def test_hot_pixels_are_fixed_and_rejected_by_the_extractor():
    sensor = js.SensorConfig(hot_pixels=6, hot_pixel_seed=4)
    empty = _scenes(np.zeros((3, 1, 2)), np.full((3, 1), np.nan))
    frames = np.asarray(js.render(jax.random.key(0), empty, CAM, sensor))
    hot = frames > frames.mean() + 200
    assert hot[0].sum() == 6 and np.array_equal(hot[0], hot[1]) and np.array_equal(hot[0], hot[2])
    other = np.asarray(js.render(jax.random.key(0), empty, CAM, sensor.replace(hot_pixel_seed=5)))
    assert not np.array_equal(hot[0], other[0] > frames.mean() + 200)
    ext = js.extract_centroids(frames, capacity=16)
    assert not np.asarray(ext.valid).any()  # a single hot pixel is no star


def test_default_sensors_follow_the_camera():
    for name in ("sgm2022", "narrow_twin"):
        cam = js.camera_preset(name)
        s = js.sensor_for_camera(cam)
        assert s.star_electrons(cam.mag_limit) == pytest.approx(500.0)
    t = js.sensor_for_camera(js.camera_preset("tetra3_test"))
    assert t.stored_bits == 16 and t.zero_point() == pytest.approx(16.9, abs=0.2)
    assert js.sensor_for_camera(CAM, exposure_s=0.5).exposure_s == 0.5


@pytest.mark.parametrize("bad, words", [
    (dict(exposure_s=0.0), "exposure_s must be a positive"),
    (dict(read_noise_e=-1.0), "read_noise_e must be ≥ 0"),
    (dict(vignetting=1.0), "vignetting must be in [0, 1)"),
    (dict(quantum_efficiency=1.5), "quantum_efficiency is a fraction"),
    (dict(shot_noise="exact"), "shot_noise must be"),
    (dict(bit_depth=12, stored_bits=8), "stored_bits must be"),
    (dict(hot_pixels=2.5), "hot_pixels must be a count"),
    (dict(defocus_px=80.0), "PSF window would be"),
    (dict(psf_sigma_px=0.01), "psf_sigma_px must be ≥ 0.1"),
])
def test_bad_sensor_settings_are_refused(bad, words):
    with pytest.raises(ValueError, match=words.replace("[", r"\[").replace("(", r"\(").replace(")", r"\)")):
        js.SensorConfig(**bad)


def test_bad_batches_are_refused():
    sc = _scenes(np.zeros((2, 1, 2)), np.full((2, 1), 4.0))
    with pytest.raises(ValueError, match="3 frame keys for 2 scenes"):
        js.render(jax.random.split(jax.random.key(0), 3), sc, CAM)
    with pytest.raises(ValueError, match="batch of scenes"):
        js.render(jax.random.key(0), jax.tree.map(lambda x: x[0], sc), CAM)
    with pytest.raises(ValueError, match="hot pixels do not fit"):
        js.render(jax.random.key(0), sc, js.Camera(4, 4, 10.0), js.SensorConfig(hot_pixels=17))
