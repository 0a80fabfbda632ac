"""Tests of the pyramid baseline (jstarid.algorithms.pyramid) against brute-force NumPy."""

from __future__ import annotations

import importlib
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js
from jstarid.algorithms import pyramid
from jstarid.geometry.star_pairs import frame_pair_angle

steps = importlib.import_module("jstarid.algorithms.pyramid.identify")
CAM = js.camera_preset("sgm2022")


@pytest.fixture(scope="module")
def bright():
    """V ≤ 4.5: small enough for brute force."""
    catalog = js.load_catalog(4.5)
    return catalog, pyramid.build_database(catalog, CAM, progress=False)


def _angles64(u, v):
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.sum(u * v, axis=-1))


@pytest.mark.parametrize("n", [4, 5, 8])
def test_pyramid_order_follows_the_paper(n):
    """Mortari et al.'s loops, written 1-based as in the paper; every triple exactly once."""
    want = [(i - 1, i + dj - 1, i + dj + dk - 1) for dj in range(1, n - 1) for dk in range(1, n - dj)
            for i in range(1, n - dj - dk + 1)]
    got = [tuple(t) for t in steps.pyramid_order(n)]
    assert got == want
    assert sorted(got) == list(itertools.combinations(range(n), 3))


def test_partner_table_groups_every_pair_by_star(bright):
    catalog, db = bright
    offsets, partners = np.asarray(db.offsets), np.asarray(db.partners)
    angles = np.asarray(db.partner_angles)
    pairs = np.asarray(db.pairs)
    assert offsets[-1] == 2 * len(pairs)
    for star in (0, 17, len(catalog) // 2, len(catalog) - 1):
        lo, hi = offsets[star], offsets[star + 1]
        assert np.all(np.diff(angles[lo:hi]) >= 0)
        want = set(pairs[pairs[:, 0] == star, 1]) | set(pairs[pairs[:, 1] == star, 0])
        assert set(partners[lo:hi]) == want and hi - lo == len(want)


def _brute_triangles(vec, max_angle, theta, eps, turn):
    """Every catalog triangle (a, b, c) with sides ab, ac, bc within ε of θ_ij, θ_ik, θ_jk, all of
    them within the table's reach, turning as the triple does."""
    ang = _angles64(vec[:, None, :], vec[None, :, :]).astype(np.float32).astype(np.float64)
    ok = (ang <= max_angle) & ~np.eye(len(vec), dtype=bool)
    ab = ok & (np.abs(ang - theta[0]) <= eps)
    ac = ok & (np.abs(ang - theta[1]) <= eps)
    bc = ok & (np.abs(ang - theta[2]) <= eps)
    out = set()
    for a, b in zip(*np.nonzero(ab), strict=True):
        for c in np.flatnonzero(ac[a] & bc[b]):
            if np.sign(np.dot(vec[a], np.cross(vec[b], vec[c]))) == turn:
                out.add((int(a), int(b), int(c)))
    return out


@pytest.mark.parametrize("seed", range(3))
def test_candidate_triangles_equal_a_brute_force_search(bright, seed):
    catalog, db = bright
    vec = np.asarray(catalog.unit_vectors, np.float64)
    rng = np.random.default_rng(seed)
    # a real triangle of the catalog, its sides perturbed by up to half the tolerance
    a = int(rng.integers(len(catalog)))
    near = np.flatnonzero((_angles64(vec[a][None], vec) < 0.15) & (np.arange(len(vec)) != a))
    b, c = rng.choice(near, 2, replace=False)
    eps = 3.0 / CAM.f_px
    theta = np.array([_angles64(vec[a], vec[b]), _angles64(vec[a], vec[c]), _angles64(vec[b], vec[c])])
    theta = (theta + rng.uniform(-0.5, 0.5, 3) * eps).astype(np.float32)
    turn = float(np.sign(np.dot(vec[a], np.cross(vec[b], vec[c]))))
    window = pyramid.database.window_size(db, eps)
    abc, has, count, over = jax.jit(steps.candidate_triangles,
                                    static_argnames=("window", "star_capacity", "capacity"))(
        *map(jnp.float32, theta), jnp.float32(turn), db, jnp.float32(eps), window=window, star_capacity=16,
        capacity=256)
    got = {tuple(map(int, t)) for t in np.asarray(abc)[np.asarray(has)]}
    want = _brute_triangles(vec, frame_pair_angle(CAM), theta.astype(np.float64),
                            np.float64(np.float32(eps)), turn)
    assert not bool(over) and int(count) == len(got)
    assert (int(a), int(b), int(c)) in got
    # float32 windows vs the float64 reference: only triangles within a hair of a bound may differ
    assert len(got ^ want) <= 1, got ^ want


def test_noise_free_scenes_are_named_and_noisy_ones_at_one_pixel_never_wrongly(catalog6, key):
    db = pyramid.build_database(catalog6, CAM, progress=False)
    noise = js.noise_grid(20, position_sigma_px=[0.0, 1.0])
    scenes = js.simulate(key, catalog6, CAM, noise, batch_size=40, capacity=48)
    result, diag = pyramid.identify(db, scenes, diagnostics=True)
    clean = js.evaluate(scenes[:20], result[:20], "strict")
    noisy = js.evaluate(scenes[20:], result[20:], "strict")
    assert clean["identification_rate"] == 1.0 and noisy["misid_rate"] == 0.0
    assert noisy["identification_rate"] >= 0.9
    np.testing.assert_array_equal(np.asarray(diag.overflow), np.asarray(scenes.overflow))
    have = np.asarray(result.ok[:20])
    err, _ = js.attitude.attitude_errors_arcsec(result.attitude[:20][have], scenes.attitude[:20][have])
    assert float(jnp.max(err)) < 3600 * math.degrees(1.0 / CAM.f_px)


@pytest.mark.slow
def test_a_small_buffer_is_flagged_and_grown(catalog6, key):
    """Triples past ``triangle_capacity`` are flagged and run again with 4 × the triangles: 16 slots
    then give what 64 give; 1 slot (4 on the rerun) stays flagged, and its scenes name nothing wrong."""
    db = pyramid.build_database(catalog6, CAM, progress=False)
    scenes = js.simulate(key, catalog6, CAM, js.noise_grid(8, position_sigma_px=[2.0]), batch_size=8,
                         capacity=48)
    runs = {c: pyramid.identify(db, scenes, pyramid.Config(triangle_capacity=c), diagnostics=True)
            for c in (1, 16, 64)}
    np.testing.assert_array_equal(np.asarray(runs[16][0].ids), np.asarray(runs[64][0].ids))
    flagged = np.asarray(runs[1][1].overflow) & ~np.asarray(scenes.overflow)
    assert flagged.any()
    assert js.evaluate(scenes, runs[1][0], "strict")["misid_rate"] == 0.0


def test_camera_problem_refuses_a_table_too_large():
    deep = js.load_catalog(8.0)
    assert pyramid.camera_problem(CAM, pyramid.Config(), deep) is not None
    with pytest.raises(ValueError, match="pairs"):
        pyramid.build_database(deep, CAM, progress=False)


@pytest.mark.parametrize("bad", [dict(n_stars=3), dict(eps_px=-1.0), dict(n_triples=0), dict(n_triples=57),
                                 dict(min_confirm=0), dict(min_confirm=6), dict(star_capacity=0)])
def test_bad_config_is_refused(bad):
    with pytest.raises(ValueError):
        pyramid.Config(**bad)
