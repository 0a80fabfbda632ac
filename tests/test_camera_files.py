"""Cameras from files and from size + field of view; lens distortion undone at the edge."""

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

import jstarid as js
from jstarid.algorithms.base import cache_key
from jstarid.camera_files import camera_from_dict, camera_to_dict

LENS = (0.12, -0.04, 1e-3, -2e-3, 0.02)


def _opencv_distort(camera, xy, k):
    """OpenCV's distortion model written out in NumPy (the reference for Camera.distort)."""
    k1, k2, p1, p2, k3 = (*k, 0, 0, 0, 0, 0)[:5]
    x = (xy[:, 0] - camera.cx) / camera.f_px
    y = (xy[:, 1] - camera.cy) / camera.f_px
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([camera.cx + camera.f_px * xd, camera.cy + camera.f_px * yd], axis=1)


def test_focal_length_given_four_ways():
    ref = js.Camera.from_fov(1280, 960, 15.0)
    assert camera_from_dict({"width": 1280, "height": 960, "fov_deg": 15.0}).f_px == pytest.approx(ref.f_px)
    diag = camera_from_dict({"size": [1280, 960], "fov_diagonal_deg": ref.fov_diagonal_deg})
    assert diag.f_px == pytest.approx(ref.f_px)
    optics = camera_from_dict({"width": 1024, "height": 1024, "focal_length_mm": 49.277,
                               "pixel_size_um": 12.0})
    assert optics.f_px == pytest.approx(js.camera_preset("rpnet2019").f_px)
    assert camera_from_dict({"width": 64, "height": 48, "f_px": 100.0, "cx": 30, "cy": 20}).cx == 30.0


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_camera_file_round_trip(tmp_path, suffix):
    cam = js.Camera(1392, 1040, 13000.0, cx=700.2, cy=515.9, mag_limit=9.5, name="narrow",
                    distortion=LENS)
    path = js.save_camera(cam, tmp_path / f"narrow{suffix}")
    assert js.load_camera(path) == cam
    assert js.load_camera(str(path)) == cam


def test_hand_written_toml(tmp_path):
    path = tmp_path / "tracker.toml"
    path.write_text('width = 1280\nheight = 960\nfov_deg = 15  # horizontal\nmag_limit = 6.5\n'
                    'k1 = -0.05\n')
    cam = js.load_camera(path)
    assert (cam.name, cam.width, cam.mag_limit, cam.distortion) == ("tracker", 1280, 6.5, (-0.05,))
    assert cam.fov_x_deg == pytest.approx(15.0)


@pytest.mark.parametrize("fields, message", [
    ({"width": 10, "height": 10, "fov_deg": 10, "focus": 1}, "unknown camera key(s) focus"),
    ({"width": 10, "height": 10}, "exactly one way"),
    ({"width": 10, "height": 10, "fov_deg": 10, "f_px": 100}, "exactly one way"),
    ({"width": 10, "fov_deg": 10}, "needs width and height"),
    ({"width": 10.5, "height": 10, "fov_deg": 10}, "whole number"),
    ({"width": 10, "height": 10, "fov_deg": 200}, "below 180"),
    ({"width": 10, "height": 10, "f_px": -1}, "positive"),
    ({"width": 10, "height": 10, "focal_length_mm": 35}, "go together"),
    ({"width": 10, "height": 10, "f_px": 10, "distortion": [1, 2, 3, 4, 5, 6]}, "at most 5"),
    ({"width": 10, "height": 10, "f_px": 10, "distortion": [0.1], "k1": 0.1}, "not both"),
])
def test_bad_camera_fields(fields, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        camera_from_dict(fields)


def test_bad_camera_specs(tmp_path):
    with pytest.raises(ValueError, match="neither a preset"):
        js.load_camera("no_such_camera")
    broken = tmp_path / "broken.toml"
    broken.write_text("width = = 3")
    with pytest.raises(ValueError, match="broken.toml: cannot read"):
        js.load_camera(broken)
    listed = tmp_path / "list.json"
    listed.write_text("[1, 2]")
    with pytest.raises(ValueError, match="expected a table"):
        js.load_camera(listed)
    with pytest.raises(ValueError, match="field of view"):
        js.load_camera("sgm2022", fov_deg=0.0)


def test_size_and_field_of_view_replace_the_presets():
    cam = js.load_camera("sgm2022", size=(1280, 960), fov_deg=15.0)
    assert (cam.width, cam.height, cam.cx, cam.cy) == (1280, 960, 639.5, 479.5)
    assert cam.fov_x_deg == pytest.approx(15.0)
    resized = js.load_camera("sgm2022", size=(2048, 2048))
    assert resized.fov_x_deg == pytest.approx(js.camera_preset("sgm2022").fov_x_deg)
    assert js.load_camera("tetra3_test", fov_deg=10.0).cx == js.camera_preset("tetra3_test").cx


def test_distortion_matches_opencv_model_and_inverts():
    cam = js.Camera.from_fov(1280, 960, 20.0, distortion=LENS)
    rng = np.random.default_rng(0)
    ideal = rng.uniform([0, 0], [1279, 959], size=(200, 2))
    measured = np.asarray(cam.distort(ideal), np.float64)
    np.testing.assert_allclose(measured, _opencv_distort(cam, ideal, LENS), atol=2e-3)
    back = np.asarray(cam.undistort(measured), np.float64)
    # the reference inverse: SciPy's least squares on the OpenCV model, point by point
    for m, b in zip(measured[:20], back[:20], strict=True):
        ref = least_squares(lambda p, m=m: _opencv_distort(cam, p[None], LENS)[0] - m, m).x
        np.testing.assert_allclose(b, ref, atol=2e-3)
    np.testing.assert_allclose(back, ideal, atol=2e-3)
    assert js.Camera(64, 48, 50.0, distortion=(0.1, 0.0)).distortion == (0.1,)
    plain = js.Camera(64, 48, 50.0)
    np.testing.assert_array_equal(np.asarray(plain.undistort(ideal)), np.asarray(ideal, np.float32))
    assert plain.pinhole() is plain


def test_distortion_leaves_database_keys_alone():
    cam = js.camera_preset("mlv2021")
    lens = js.Camera(**{**camera_to_dict(cam), "distortion": LENS})
    assert cache_key("mlv", 1, None, cam, {}) == cache_key("mlv", 1, None, lens, {})
    assert lens.pinhole() == cam


def test_scenes_from_distorted_centroids_are_pinhole_again():
    cam = js.Camera.from_fov(1024, 768, 12.0, distortion=LENS)
    ideal = np.array([[10.0, 20.0], [1000.0, 700.0], [511.5, 383.5]])
    measured = np.asarray(cam.distort(ideal))
    scenes = js.scenes_from_centroids([measured], [np.arange(3.0)], capacity=4, camera=cam)
    np.testing.assert_allclose(np.asarray(scenes.xy[0, :3]), ideal, atol=2e-3)
    assert float(np.abs(np.asarray(scenes.xy[0, 3])).max()) == 0.0  # padding stays zero
    plain = js.scenes_from_centroids([measured], [np.arange(3.0)], capacity=4)
    assert math.dist(plain.xy[0, 0].tolist(), ideal[0]) > 1.0  # the lens moved the corner star
    with pytest.raises(ValueError, match="camera"):
        js.extract_centroids(np.zeros((64, 64)), capacity=4, camera=cam)
