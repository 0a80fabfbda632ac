import math

import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js


@pytest.mark.parametrize("name", js.preset_names())
def test_project_matches_numpy_pinhole(name):
    cam = js.camera_preset(name)
    rng = np.random.default_rng(1)
    v = rng.normal(size=(500, 3))
    v[:, 2] = np.abs(v[:, 2]) + 2.0  # in front of the camera
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    xy, inside = cam.project(jnp.asarray(v))
    ref_x = cam.cx + cam.f_px * v[:, 0] / v[:, 2]
    ref_y = cam.cy + cam.f_px * v[:, 1] / v[:, 2]
    np.testing.assert_allclose(np.asarray(xy[:, 0]), ref_x, atol=1e-3)
    np.testing.assert_allclose(np.asarray(xy[:, 1]), ref_y, atol=1e-3)
    ref_in = (ref_x >= 0) & (ref_x <= cam.width - 1) & (ref_y >= 0) & (ref_y <= cam.height - 1)
    np.testing.assert_array_equal(np.asarray(inside), ref_in)


@pytest.mark.parametrize("name", js.preset_names())
def test_unproject_inverts_project(name):
    cam = js.camera_preset(name)
    rng = np.random.default_rng(2)
    xy = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], size=(300, 2))
    v = cam.unproject(jnp.asarray(xy, jnp.float32))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(v), axis=1), 1.0, atol=1e-6)
    back, inside = cam.project(v)
    np.testing.assert_allclose(np.asarray(back), xy, atol=1e-3)
    assert bool(np.all(np.asarray(inside)))


def test_behind_camera_is_not_in_field():
    cam = js.camera_preset("sgm2022")
    xy, inside = cam.project(jnp.array([[0.0, 0.0, -1.0], [0.01, 0.0, 0.0]]))
    assert not bool(inside.any())
    assert bool(jnp.all(jnp.isfinite(xy)))


def test_preset_fields_of_view():
    assert js.camera_preset("sgm2022").fov_x_deg == pytest.approx(20.0, abs=1e-9)
    assert js.camera_preset("mlv2021").fov_x_deg == pytest.approx(25.0, abs=1e-9)
    rp = js.camera_preset("rpnet2019")
    assert rp.fov_diagonal_deg == pytest.approx(20.0, abs=0.05)  # conventions §6 note: diagonal, not side
    assert rp.fov_x_deg == pytest.approx(14.2, abs=0.05)
    zy3 = js.camera_preset("zy3")
    assert (zy3.cx, zy3.cy) == (515.247, 513.320)
    t3 = js.camera_preset("tetra3_test")
    assert (t3.width, t3.height) == (1024, 768)
    assert t3.fov_x_deg == pytest.approx(11.42, abs=0.01)
    # principal point defaults to the image centre with the pixel-centre origin
    assert js.camera_preset("sgm2022").cx == 511.5


def test_bad_camera_input():
    with pytest.raises(ValueError, match="unknown camera preset"):
        js.camera_preset("hubble")
    with pytest.raises(ValueError):
        js.Camera(1024, 1024, -5.0)
    with pytest.raises(ValueError):
        js.Camera(0, 1024, 500.0)
    with pytest.raises(ValueError):
        js.Camera(1024, 1024, math.nan)


def test_camera_is_hashable_static():
    a = js.camera_preset("sgm2022")
    b = js.camera_preset("sgm2022")
    assert hash(a) == hash(b) and a == b
    assert js.camera_preset("sgm2022", mag_limit=6.5) != a


def test_contains_with_inset():
    cam = js.camera_preset("sgm2022")
    xy = jnp.array([[0.0, 0.0], [4.9, 500.0], [5.0, 500.0], [cam.width - 6.0, 5.0],
                    [cam.width - 5.9, 500.0], [500.0, cam.height]])
    np.testing.assert_array_equal(cam.contains(xy), [True, True, True, True, True, False])
    np.testing.assert_array_equal(cam.contains(xy, 5.0), [False, False, True, True, False, False])


def test_inscribed_half_field_and_the_radius_that_fits():
    from jstarid.camera import radius_that_fits

    cam = js.camera_preset("tetra3_test")  # 1024 × 768: the nearest edge is 383.5 px above the centre
    assert cam.inscribed_half_field_deg == pytest.approx(math.degrees(math.atan(383.5 / cam.f_px)))
    assert radius_that_fits(cam, 6.0) == 3.8 and radius_that_fits(cam, 4.0) == 4.0
    off = js.Camera(1024, 1024, 2000.0, cx=100.0)  # principal point 100 px from the left edge
    assert off.inscribed_half_field_deg == pytest.approx(math.degrees(math.atan(100.0 / 2000.0)))
    assert radius_that_fits(js.camera_preset("rpnet2019"), 6.0) == 6.0


def test_tolerance_scales_keep_the_papers_cameras_and_follow_others():
    from jstarid.camera import PAPER_CAMERAS, tolerance_scales

    for name in PAPER_CAMERAS:
        assert tolerance_scales(js.camera_preset(name)) == (1.0, 1.0)
    twin = js.camera_preset("narrow_twin")
    pixel, field = tolerance_scales(twin)
    finest = min(js.camera_preset(n).pixel_scale_arcsec for n in PAPER_CAMERAS)
    assert pixel == pytest.approx(twin.pixel_scale_arcsec / finest) and 0.3 < pixel < 0.33
    assert 0.37 < field < 0.39
    coarse = js.Camera.from_fov(512, 512, 40.0)  # 290″/px, 55° diagonal: both grow
    assert all(s > 1.5 for s in tolerance_scales(coarse))
