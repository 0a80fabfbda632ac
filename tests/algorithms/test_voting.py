"""Tests of the geometric-voting baseline (jstarid.algorithms.voting) against brute-force NumPy."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js
from jstarid.algorithms import voting
from jstarid.algorithms.voting.database import window_size
from jstarid.algorithms.voting.identify import cast_votes

CAM = js.camera_preset("sgm2022")


@pytest.fixture(scope="module")
def bright():
    """V ≤ 4.5: a table small enough for brute force."""
    catalog = js.load_catalog(4.5)
    return catalog, voting.build_database(catalog, CAM, progress=False)


def _angles64(u, v):
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.sum(u * v, axis=-1))


def test_pair_table_is_every_pair_within_the_diagonal(bright):
    catalog, db = bright
    vec = np.asarray(catalog.unit_vectors, np.float64)
    i, j = np.triu_indices(len(catalog), 1)
    ang = _angles64(vec[i], vec[j])
    keep = ang <= db.max_angle_rad
    want = {(int(a), int(b)) for a, b in zip(i[keep], j[keep], strict=True)}
    pairs = np.asarray(db.pairs)
    assert {tuple(map(int, p)) for p in pairs} == want and len(pairs) == len(want)
    values = np.asarray(db.kvector.values)
    assert np.all(np.diff(values) >= 0)
    np.testing.assert_allclose(values, _angles64(vec[pairs[:, 0]], vec[pairs[:, 1]]), atol=1e-6)


def test_votes_equal_a_brute_force_tally(bright):
    catalog, db = bright
    vec = np.asarray(catalog.unit_vectors, np.float64)
    rng = np.random.default_rng(3)
    n, eps = 6, 2.0 / CAM.f_px
    body = rng.normal(size=(n, 3)) * [0.08, 0.08, 1.0]
    body /= np.linalg.norm(body, axis=1, keepdims=True)
    first, second = np.triu_indices(n, 1)
    asked = np.ones(first.size, bool)
    asked[2] = False
    theta = _angles64(body[first], body[second]).astype(np.float32)
    window = window_size(db, eps)
    votes, count = jax.jit(cast_votes, static_argnames=("n", "n_cat", "window"))(
        jnp.asarray(theta), jnp.asarray(asked), jnp.asarray(first, jnp.int32), jnp.asarray(second, jnp.int32),
        db.kvector, db.pairs, jnp.float32(eps), n=n, n_cat=len(catalog), window=window)
    # the reference: every catalog pair (i < j, within the diagonal) whose angle lies in the window
    ci, cj = np.triu_indices(len(catalog), 1)
    cang = _angles64(vec[ci], vec[cj]).astype(np.float32)
    inside = cang <= db.max_angle_rad
    ci, cj, cang = ci[inside], cj[inside], cang[inside]
    want = np.zeros((n, len(catalog)), np.int64)
    want_count = np.zeros(first.size, np.int64)
    for p, (a, b) in enumerate(zip(first, second, strict=True)):
        if not asked[p]:
            continue
        hit = (cang >= theta[p] - np.float32(eps)) & (cang <= theta[p] + np.float32(eps))
        want_count[p] = hit.sum()
        for det in (a, b):
            np.add.at(want[det], ci[hit], 1)
            np.add.at(want[det], cj[hit], 1)
    assert want_count.max() > 0 and want_count.max() <= window
    np.testing.assert_array_equal(np.asarray(count), want_count)
    np.testing.assert_array_equal(np.asarray(votes), want)


def test_window_size_bounds_every_window(bright):
    _, db = bright
    eps = 1.5 / CAM.f_px
    s = np.asarray(db.kvector.values, np.float64)
    w = window_size(db, eps)
    counts = np.searchsorted(s, s + 2 * eps, side="right") - np.arange(s.size)
    assert w >= counts.max() and w <= counts.max() + 2


def test_noise_free_scenes_are_named_and_noisy_ones_never_wrongly(catalog6, key):
    """Config(): every noise-free scene identified; at 1 px the scenes it names carry no wrong id."""
    db = voting.build_database(catalog6, CAM, progress=False)
    noise = js.noise_grid(24, position_sigma_px=[0.0, 1.0])
    scenes = js.simulate(key, catalog6, CAM, noise, batch_size=48, capacity=48)
    result, diag = voting.identify(db, scenes, diagnostics=True)
    clean = js.evaluate(scenes[:24], result[:24], "strict")
    noisy = js.evaluate(scenes[24:], result[24:], "strict")
    assert clean["identification_rate"] == 1.0
    assert noisy["misid_rate"] == 0.0
    np.testing.assert_array_equal(np.asarray(diag.overflow), np.asarray(scenes.overflow))  # no window cut
    # the attitude of a claimed scene is the truth's within a few pixels' angle
    have = np.asarray(result.ok[:24])
    err, _ = js.attitude.attitude_errors_arcsec(result.attitude[:24][have], scenes.attitude[:24][have])
    assert float(jnp.max(err)) < 3600 * math.degrees(0.5 / CAM.f_px) * 4


def test_camera_problem_refuses_a_table_too_large():
    deep = js.load_catalog(8.0)
    assert voting.camera_problem(CAM, voting.Config(), deep) is not None
    with pytest.raises(ValueError, match="pairs"):
        voting.build_database(deep, CAM, progress=False)
    assert voting.camera_problem(CAM, voting.Config(), None) is None


@pytest.mark.parametrize("bad", [dict(n_stars=2), dict(eps_px=0.0), dict(eps_px=math.nan),
                                 dict(min_verified=2), dict(min_verified=30)])
def test_bad_config_is_refused(bad):
    with pytest.raises(ValueError):
        voting.Config(**bad)
