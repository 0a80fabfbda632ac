"""A camera fitted on the sky (:func:`jstarid.calibration.calibrate`) against a known lens."""

import dataclasses

import jax
import numpy as np
import pytest

import jstarid as js
from jstarid.calibration import calibrate, project
from jstarid.solution import Solution, Star

TRUE = js.Camera(1392, 1040, 2900.0, cx=701.0, cy=515.0, mag_limit=8.0, name="true lens",
                 distortion=(-0.12, 0.05, 4e-4, -3e-4))


def _frames(n_frames=6, noise_px=0.1):
    """Solutions of frames taken by TRUE, as a rough camera (5 % focal length, no lens) saw them."""
    cat = js.load_catalog(8.0)
    rough = js.Camera(TRUE.width, TRUE.height, TRUE.f_px * 1.05, mag_limit=8.0, name="rough")
    rng = np.random.default_rng(0)
    attitudes = np.asarray(js.random_rotation(jax.random.key(5), (n_frames,)), np.float64)
    out = []
    for c in attitudes:
        v = cat.unit_vectors @ c.T
        ahead = v[:, 2] > 0.9
        xy = np.asarray(TRUE.distort(np.asarray(TRUE.project(v[ahead])[0])), np.float64)
        inside = (xy[:, 0] > 0) & (xy[:, 0] < TRUE.width - 1) & (xy[:, 1] > 0) & (xy[:, 1] < TRUE.height - 1)
        hips = cat.hip[ahead][inside][:40]
        xy = xy[inside][:40] + rng.normal(0, noise_px, (len(hips), 2))
        stars = tuple(Star(int(h), float(x), float(y), 5.0, detection=j)
                      for j, (h, (x, y)) in enumerate(zip(hips, xy, strict=True)))
        out.append(Solution(label="f", solved=True, detections=len(stars), stars=stars, camera=rough,
                            attitude=c, focal_scale=1 / 1.05))
    return out, rough


def test_project_is_the_camera_model():
    v = np.array([[0.01, -0.02, 1.0], [0.1, 0.05, 1.0], [-0.12, 0.09, 1.0]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    lens = js.Camera(TRUE.width, TRUE.height, TRUE.f_px, cx=TRUE.cx, cy=TRUE.cy,
                     distortion=(-0.12, 0.05, 4e-4, -3e-4, 0.3))
    mine = project(dict(f_px=lens.f_px, cx=lens.cx, cy=lens.cy, k1=-0.12, k2=0.05, p1=4e-4, p2=-3e-4,
                        k3=0.3), v)
    np.testing.assert_allclose(mine, np.asarray(lens.distort(lens.project(v)[0])), atol=1e-3)


def test_calibrate_recovers_the_lens():
    solutions, rough = _frames()
    # a blend's centroid is the light of two stars: 30 px off here, and left out of the fit (in it,
    # its residual alone would lift the RMS above 0.2 px)
    first = solutions[0]
    off = dataclasses.replace(first.stars[0], x=first.stars[0].x + 30.0, blend=(first.stars[0].hip, 1))
    solutions[0] = dataclasses.replace(first, stars=(off, *first.stars[1:]))
    result = calibrate(solutions, rough)
    cam = result.camera
    assert result.fitted == ("f_px", "cx", "cy", "k1", "k2", "p1", "p2") and result.frames == 6
    assert result.rms_before_px > 5.0 and result.rms_after_px < 0.2  # 0.1 px noise per axis
    assert result.stars == 6 * 40 - 1 and cam.f_px == pytest.approx(TRUE.f_px, rel=2e-4)
    assert cam.distortion[0] == pytest.approx(-0.12, abs=0.01)
    # the fitted camera puts every star where the true lens does (to the noise), wherever they are
    grid = np.stack(np.meshgrid(np.linspace(0, TRUE.width - 1, 9), np.linspace(0, TRUE.height - 1, 7)),
                    -1).reshape(-1, 2)
    ideal_true = np.asarray(TRUE.undistort(grid))
    rays = np.column_stack([(ideal_true - [TRUE.cx, TRUE.cy]) / TRUE.f_px, np.ones(len(grid))])
    # the same rays through the fitted camera, up to the rotation the principal point trades with
    mine = np.asarray(cam.distort(cam.project(rays)[0]))
    shift = np.median(mine - grid, axis=0)
    assert np.max(np.linalg.norm(mine - grid - shift, axis=1)) < 0.5


def test_calibrate_needs_named_frames():
    solutions, rough = _frames(n_frames=1)
    unsolved = Solution(label="x", solved=False, detections=0, stars=(), camera=rough)
    with pytest.raises(ValueError, match="no solved frame"):
        calibrate([unsolved], rough)
    with pytest.raises(ValueError, match="cannot fit"):
        calibrate(solutions, rough, fit=["k9"])
    few = calibrate(solutions, rough, fit=None)  # 40 stars: focal length and radial terms only
    assert few.fitted == ("f_px", "k1", "k2") and few.camera.cx == rough.cx
