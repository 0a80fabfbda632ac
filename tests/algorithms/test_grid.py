"""Tests of the grid baseline (jstarid.algorithms.grid) against a NumPy reference."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js
from jstarid.algorithms import grid
from jstarid.algorithms.grid.pattern import grid_pattern, overlap

CAM = js.camera_preset("sgm2022")


def _reference_bits(u, neighbours, real, f_px, pattern_px, buffer_px, g):
    """The paper's pattern in float64 NumPy: tangent-plane pixels, nearest neighbour on +x, g × g cells."""
    helper = np.array([1.0, 0, 0]) if abs(u[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = helper - helper.dot(u) * u
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    along = neighbours @ u
    x, y = f_px * (neighbours @ e1) / along, f_px * (neighbours @ e2) / along
    r = np.hypot(x, y)
    near = real & (along > 0) & (r <= pattern_px) & (r > buffer_px)
    bits = np.zeros(g * g, bool)
    if not near.any():
        return bits
    k = np.flatnonzero(near)[np.argmin(r[near])]
    phi = np.arctan2(y[k], x[k])
    xr = np.cos(phi) * x + np.sin(phi) * y
    yr = -np.sin(phi) * x + np.cos(phi) * y
    ix = np.floor((xr / pattern_px + 1) * 0.5 * g).astype(int)
    iy = np.floor((yr / pattern_px + 1) * 0.5 * g + 0.5).astype(int)  # rows centred on the +x axis
    inside = near & (ix >= 0) & (ix < g) & (iy >= 0) & (iy < g)
    bits[ix[inside] * g + iy[inside]] = True
    return bits


def _unpack(words):
    words = np.asarray(words, np.uint32)
    return ((words[:, None] >> np.arange(32, dtype=np.uint32)[None, :]) & 1).astype(bool).reshape(-1)


def test_pattern_equals_the_numpy_reference():
    rng = np.random.default_rng(0)
    f, pattern_px, buffer_px, g = float(CAM.f_px), 300.0, 20.0, 32
    fn = jax.jit(lambda u, v, m: grid_pattern(u, v, m, f_px=f, pattern_px=pattern_px, buffer_px=buffer_px,
                                              grid=g))
    differing = 0
    for _ in range(40):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        v = u[None, :] + rng.normal(size=(30, 3)) * 0.06
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        real = rng.random(30) < 0.8
        u32, v32 = u.astype(np.float32), v.astype(np.float32)
        words, oriented = fn(jnp.asarray(u32), jnp.asarray(v32), jnp.asarray(real))
        want = _reference_bits(u32.astype(np.float64), v32.astype(np.float64), real, f, pattern_px,
                               buffer_px, g)
        got = _unpack(words)
        assert bool(oriented) == want.any() and want.sum() >= 5
        differing += int(np.sum(got != want))
    assert differing <= 2  # a star within float32 rounding of a cell border, at most


def test_overlap_counts_common_bits():
    rng = np.random.default_rng(1)
    table = rng.integers(0, 2**32, (50, 32), dtype=np.uint64).astype(np.uint32)
    pattern = table[7] & rng.integers(0, 2**32, 32, dtype=np.uint64).astype(np.uint32)
    want = np.array([np.sum(_unpack(row) & _unpack(pattern)) for row in table])
    np.testing.assert_array_equal(np.asarray(overlap(jnp.asarray(pattern), jnp.asarray(table))), want)


def test_noise_free_scenes_are_named(catalog6, key):
    db = grid.build_database(catalog6, CAM, progress=False)
    scenes = js.simulate(key, catalog6, CAM, js.noise_grid(30, position_sigma_px=[0.0]), batch_size=30,
                         capacity=48)
    result, diag = grid.identify(db, scenes, diagnostics=True)
    report = js.evaluate(scenes, result, "strict")
    assert report["identification_rate"] == 1.0 and report["misid_rate"] == 0.0
    assert np.all(np.asarray(diag.n_candidates) == grid.Config().n_refs)


def test_a_database_of_other_radii_is_refused(catalog6, key):
    db = grid.build_database(js.load_catalog(4.0), CAM, grid.Config(pattern_radius=0.4), progress=False)
    scenes = js.simulate(key, catalog6, CAM, js.noise_grid(2), batch_size=2, capacity=16)
    with pytest.raises(ValueError, match="radii"):
        grid.identify(db, scenes, grid.Config())


@pytest.mark.parametrize("bad", [dict(grid=10), dict(pattern_radius=0.01), dict(buffer_radius=0.0),
                                 dict(n_refs=1), dict(min_verified=1), dict(min_overlap=0), dict(eps_px=0.0)])
def test_bad_config_is_refused(bad):
    with pytest.raises(ValueError):
        grid.Config(**bad)
