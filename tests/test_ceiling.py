import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js
from jstarid.ceiling import accuracy_bound, naming_ceiling


def _star_field(cam, pixels):
    """Unit vectors (n, 3) that project (identity attitude) onto ``pixels`` (n, 2)."""
    pixels = np.asarray(pixels, np.float64)
    ray = np.stack([(pixels[:, 0] - cam.cx) / cam.f_px, (pixels[:, 1] - cam.cy) / cam.f_px,
                    np.ones(len(pixels))], -1)
    return ray / np.linalg.norm(ray, axis=-1, keepdims=True)


def _scene(xy):
    """One scene whose detection i is star i, at the given (noisy) centroids."""
    xy = np.asarray(xy, np.float32)[None]
    n = xy.shape[1]
    return js.Scene(xy=jnp.asarray(xy), mag=jnp.zeros((1, n)), truth=jnp.arange(n)[None],
                    valid=jnp.ones((1, n), bool), attitude=jnp.eye(3)[None],
                    overflow=jnp.zeros(1, bool))


def test_swapped_close_pair_is_beyond_any_identifier():
    cam = js.camera_preset("sgm2022")
    stars = np.array([[cam.cx, cam.cy], [cam.cx + 3.0, cam.cy], [cam.cx + 200.0, cam.cy + 50.0]])
    vec = _star_field(cam, stars)
    small = stars + np.array([[0.4, -0.3], [-0.5, 0.2], [1.0, 1.0]])
    assert naming_ceiling(_scene(small), vec, cam, region="all")[0]
    crossed = stars + np.array([[2.6, 0.0], [-2.4, 0.0], [0.0, 0.0]])  # each nearer the other star
    assert not naming_ceiling(_scene(crossed), vec, cam, region="all")[0]


def test_sgm_region_ignores_stars_outside_the_circle():
    cam = js.camera_preset("sgm2022")
    px_per_deg = cam.f_px * np.tan(np.radians(1.0))
    far = cam.cx + 9.0 * px_per_deg  # beyond r = 6° from the main star at the centre
    stars = np.array([[cam.cx, cam.cy], [far, cam.cy], [far + 3.0, cam.cy]])
    vec = _star_field(cam, stars)
    crossed = stars + np.array([[0.0, 0.0], [2.6, 0.0], [-2.4, 0.0]])
    assert naming_ceiling(_scene(crossed), vec, cam, region="sgm")[0]
    assert not naming_ceiling(_scene(crossed), vec, cam, region="all")[0]
    assert not naming_ceiling(_scene(crossed), vec, cam, region="sgm", radius_deg=10.0)[0]


def test_matches_brute_force_over_permutations():
    """The identity is a least-cost assignment exactly when no permutation of the stars is cheaper."""
    cam = js.camera_preset("sgm2022")
    rng = np.random.default_rng(3)
    n, trials, disagree_cases, clear_cases = 6, 60, 0, 0
    for _ in range(trials):
        stars = np.array([cam.cx, cam.cy]) + rng.uniform(-15.0, 15.0, (n, 2))
        xy = stars + rng.normal(0.0, 6.0, (n, 2))
        cost = np.sum((xy[:, None] - stars[None]) ** 2, -1)
        best = min(sum(cost[i, p[i]] for i in range(n)) for p in itertools.permutations(range(n)))
        expect = np.trace(cost) <= best + 1e-9 * max(best, 1.0)
        disagree_cases += not expect
        got = naming_ceiling(_scene(xy), _star_field(cam, stars), cam, region="all")[0]
        assert got == expect
        # with a margin: every detection's best other name must cost ≥ margin · 2σ² more
        sigma, margin = 6.0, 2.0
        gaps = [min(sum(cost[k, p[k]] for k in range(n)) for p in itertools.permutations(range(n))
                    if p[i] != i) - np.trace(cost) for i in range(n)]
        confident = expect and min(gaps) >= margin * 2 * sigma ** 2
        clear_cases += confident
        got = naming_ceiling(_scene(xy), _star_field(cam, stars), cam, region="all",
                             margin_nats=margin, sigma_px=sigma)[0]
        assert got == confident
    assert 0 < disagree_cases < trials  # both outcomes were exercised
    assert 0 < clear_cases < trials - disagree_cases


def test_simulated_scenes(catalog6, sgm_camera):
    rows = np.arange(0, len(catalog6), len(catalog6) // 48)[:48]
    clean = js.simulate(jax.random.key(0), catalog6, sgm_camera, js.NoiseConfig(),
                        boresight_ids=rows, capacity=128)
    assert naming_ceiling(clean, catalog6, sgm_camera).all()
    noisy = js.simulate(jax.random.key(0), catalog6, sgm_camera,
                        js.NoiseConfig(position_sigma_px=40.0), boresight_ids=rows, capacity=128)
    rate = naming_ceiling(noisy, catalog6, sgm_camera).mean()
    assert rate < 1.0  # 40 px ≈ 0.8°: neighbours get crossed


def test_bad_input_and_accuracy_bound():
    cam = js.camera_preset("sgm2022")
    scene = _scene([[cam.cx, cam.cy], [cam.cx + 5.0, cam.cy]])
    with pytest.raises(ValueError, match="region"):
        naming_ceiling(scene, np.eye(3), cam, region="circle")
    with pytest.raises(ValueError, match="star vectors"):
        naming_ceiling(scene, np.eye(3)[:1], cam)
    with pytest.raises(ValueError, match="sigma_px"):
        naming_ceiling(scene, np.eye(3), cam, margin_nats=6.25)
    np.testing.assert_allclose(accuracy_bound([0.9, 0.99], 0.02), [0.9 / 0.98, 1.0])
    with pytest.raises(ValueError, match="max_failure_rate"):
        accuracy_bound(0.9, 1.0)
