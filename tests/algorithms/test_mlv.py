"""Tests of the MLV star identifier (jstarid.algorithms.mlv).

A reduced database (20,000 boresights instead of 100,000) keeps the suite fast; it still holds the
triangles of almost every field, so noise-free scenes must all be identified.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js
from jstarid.algorithms import mlv
from jstarid.algorithms.mlv.database import database_from_triangles, fibonacci_sphere
from jstarid.algorithms.mlv.features import (
    discretize,
    singular_values,
    triangle_combinations,
    triangle_features,
)
from jstarid.algorithms.mlv.identify import _identify_batch, identify_scene
from jstarid.algorithms.mlv.verify import largest_cluster
from jstarid.algorithms.mlv.voting import candidate_ranges, gather_candidates, gather_pool

CAM = js.camera_preset("mlv2021")
CFG = mlv.Config(n_boresights=20_000, batch_chunk=100)


@pytest.fixture(scope="module")
def catalog():
    return js.load_catalog(5.5)


@pytest.fixture(scope="module")
def database(catalog):
    return mlv.build_database(catalog, CAM, CFG, use_cache=False, progress=False)


def _random_triangles(rng, n, spread):
    """(n, 3, 3) float64 unit vectors: three stars within ≈ `spread` rad of a random direction."""
    centre = rng.normal(size=(n, 1, 3))
    p = centre / np.linalg.norm(centre, axis=-1, keepdims=True) + spread * rng.normal(size=(n, 3, 3))
    return p / np.linalg.norm(p, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------- features (eqs. 1–4)
@pytest.mark.parametrize("spread", [0.15, 0.03, 0.003])
def test_singular_values_match_numpy_svd(spread):
    rng = np.random.default_rng(0)
    p = _random_triangles(rng, 2000, spread)
    ref = np.linalg.svd(np.swapaxes(p, -1, -2), compute_uv=False)  # M = [p_i p_j p_k] (eq. 1)
    got64 = singular_values(p[:, 0], p[:, 1], p[:, 2], xp=np)
    np.testing.assert_allclose(got64, ref, rtol=0, atol=1e-12)
    p32 = jnp.asarray(p, jnp.float32)
    got32 = np.asarray(jax.jit(singular_values)(p32[:, 0], p32[:, 1], p32[:, 2]))
    # float32 inputs carry ≈ 6e-8 rounding; the features need ≪ Δv1 = 5e-5, Δv2 = 5e-4
    np.testing.assert_allclose(got32, ref, rtol=0, atol=2e-6)


def test_singular_values_degenerate_triangles_are_finite():
    p = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.1, 0.995]])
    p /= np.linalg.norm(p, axis=-1, keepdims=True)
    sv = np.asarray(singular_values(*jnp.asarray(p, jnp.float32)))
    assert np.all(np.isfinite(sv))
    np.testing.assert_allclose(sv, np.linalg.svd(p.T, compute_uv=False), atol=1e-6)


def test_paper_worked_number():
    # §2.1: v1 = 1.7081, Δv1 = 5e-5 → 34,162 (eq. 4)
    v1h, v2h = discretize(np.float64(1.7081), np.float64(0.1272), 5e-5, 5e-4, xp=np)
    assert int(v1h) == 34162
    # the paper prints 254 for v2 = 0.1272, Δv2 = 5e-4, but eq. 4's ceil gives 255 (see docstring)
    assert int(v2h) == 255
    j1, _ = discretize(jnp.float32(1.7081), jnp.float32(0.1272), 5e-5, 5e-4)
    assert int(j1) == 34162


def test_features_rotation_invariant():
    rng = np.random.default_rng(1)
    p = _random_triangles(rng, 500, 0.1)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rotated = p @ q.T
    a = singular_values(p[:, 0], p[:, 1], p[:, 2], xp=np)
    b = singular_values(rotated[:, 0], rotated[:, 1], rotated[:, 2], xp=np)
    np.testing.assert_allclose(a, b, atol=1e-13)
    # the singular values ignore the order of the three stars as well
    c = singular_values(p[:, 2], p[:, 0], p[:, 1], xp=np)
    np.testing.assert_allclose(a, c, atol=1e-13)
    v1a, v2a, _ = triangle_features(p, 5e-5, 5e-4, xp=np)
    v1b, v2b, _ = triangle_features(rotated, 5e-5, 5e-4, xp=np)
    frac1 = (a[:, 0] / 5e-5) % 1.0
    frac2 = (a[:, 1] / 5e-4) % 1.0
    away = (np.minimum(frac1, 1 - frac1) > 1e-6) & (np.minimum(frac2, 1 - frac2) > 1e-6)
    assert np.all(v1a[away] == v1b[away]) and np.all(v2a[away] == v2b[away])


# ----------------------------------------------------------------------------- database + lookup
def test_fibonacci_sphere_is_even():
    v = fibonacci_sphere(4000)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-12)
    assert abs(v.mean(axis=0)).max() < 1e-3
    # nearest-neighbour distances nearly uniform (≈ 3.6° at n = 4000)
    d = v @ v.T
    np.fill_diagonal(d, -1)
    nn = np.degrees(np.arccos(d.max(axis=1)))
    assert nn.min() > 0.6 * np.median(nn) and nn.max() < 1.4 * np.median(nn)


def test_database_contents(catalog, database):
    info = database.info_dict()
    assert info["n_triangles"] == database.n_triangles > 50_000
    assert np.all(np.diff(np.asarray(database.keys)) >= 0)
    tri = np.asarray(database.star_rows)[np.asarray(database.triangles)]
    # stars ordered by their opposite side, and `sides` are those sides (float64 reference)
    v = catalog.unit_vectors[tri]
    ref_sides = np.degrees(np.arccos(np.clip(np.stack(
        [np.sum(v[:, 1] * v[:, 2], -1), np.sum(v[:, 0] * v[:, 2], -1),
         np.sum(v[:, 0] * v[:, 1], -1)], axis=1), -1, 1)))
    np.testing.assert_allclose(np.degrees(np.asarray(database.sides)), ref_sides, atol=1e-4)
    assert np.all(np.diff(np.asarray(database.sides), axis=1) >= 0)
    tri = np.sort(tri, axis=1)
    assert np.all(np.diff(tri, axis=1) > 0)  # distinct catalog rows
    assert len(np.unique(tri, axis=0)) == len(tri)  # de-duplicated
    # every triangle fits in the field: largest pair angle ≤ the field's diagonal
    v = catalog.unit_vectors[tri]
    cos = np.einsum("tij,tkj->tik", v, v)
    assert np.degrees(np.arccos(cos.min())) <= 2 * math.degrees(CAM.half_diagonal_rad) + 1e-6
    # keys re-computed independently in float64 from the catalog
    sv = np.linalg.svd(np.swapaxes(v, -1, -2), compute_uv=False)
    v1h = np.ceil(sv[:, 0] / CFG.dv1).astype(np.int64)
    v2h = np.ceil(sv[:, 1] / CFG.dv2).astype(np.int64)
    keys = (v1h - database.v1_offset) * database.stride + v2h
    close = np.abs(keys - np.asarray(database.keys)) == 0
    assert close.mean() > 0.999  # a few may sit on a bin edge (SVD vs closed form at 1e-15)
    assert database.nbytes < database.device_nbytes


def test_lookup_matches_brute_force(catalog):
    cfg = mlv.Config(n_boresights=500)
    db = mlv.build_database(catalog, CAM, cfg, use_cache=False, progress=False)
    keys = np.asarray(db.keys)
    v1_db = keys // db.stride + db.v1_offset
    v2_db = keys % db.stride
    rng = np.random.default_rng(3)
    pick = rng.integers(0, len(keys), 200)
    q1 = v1_db[pick] + rng.integers(-3, 4, 200)
    q2 = v2_db[pick] + rng.integers(-3, 4, 200)
    q1 = np.concatenate([q1, [0, 10**6, v1_db.min() - 1]])
    q2 = np.concatenate([q2, [5, 5, -2]])
    for th1, th2 in [(0, 0), (1, 1), (2, 3)]:
        start, count = candidate_ranges(db.keys, jnp.asarray(q1, jnp.int32),
                                        jnp.asarray(q2, jnp.int32), th1=th1, th2=th2,
                                        v1_offset=db.v1_offset, stride=db.stride,
                                        n_rows=db.n_rows)
        idx, valid, overflow, total = jax.vmap(gather_candidates, in_axes=(0, 0, None))(
            start, count, 4096)
        for i in range(len(q1)):
            ref = np.nonzero((np.abs(v1_db - q1[i]) <= th1) & (np.abs(v2_db - q2[i]) <= th2))[0]
            got = np.asarray(idx[i])[np.asarray(valid[i])]
            assert int(total[i]) == len(ref) and not bool(overflow[i])
            np.testing.assert_array_equal(np.sort(got), ref)
        # traced tolerances in a wider static window give the same ranges' contents
        start_t, count_t = jax.jit(candidate_ranges, static_argnames=(
            "v1_offset", "stride", "n_rows", "th1_max"))(
            db.keys, jnp.asarray(q1, jnp.int32), jnp.asarray(q2, jnp.int32),
            th1=jnp.int32(th1), th2=jnp.int32(th2), v1_offset=db.v1_offset, stride=db.stride,
            n_rows=db.n_rows, th1_max=3)
        np.testing.assert_array_equal(np.sum(count_t, 1), np.asarray(total))
        # the shared per-scene buffer holds the same candidates, each tagged with its query
        groups = np.arange(len(q1)) // 8
        for g in range(groups.max() + 1):
            sel = np.nonzero(groups == g)[0]
            index, tri, in_pool, n_all = gather_pool(start_t[sel], count_t[sel], 4096)
            index, tri, in_pool = (np.asarray(a) for a in (index, tri, in_pool))
            assert int(n_all) == int(np.sum(np.asarray(total)[sel])) <= 4096
            for j, i in enumerate(sel):
                ref = np.asarray(idx[i])[np.asarray(valid[i])]
                np.testing.assert_array_equal(np.sort(index[in_pool & (tri == j)]), np.sort(ref))


def test_database_cache_roundtrip(catalog, tmp_path, monkeypatch):
    monkeypatch.setenv("JSTARID_CACHE", str(tmp_path))
    cfg = mlv.Config(n_boresights=300)
    a = mlv.build_database(catalog, CAM, cfg, progress=False)
    assert not a.info_dict()["cached"] and list(tmp_path.glob(f"mlv-{a.cache_key()}.npz"))
    b = mlv.build_database(catalog, CAM, cfg, progress=False)
    assert b.info_dict()["cached"]
    np.testing.assert_array_equal(np.asarray(a.keys), np.asarray(b.keys))
    np.testing.assert_array_equal(np.asarray(a.triangles), np.asarray(b.triangles))
    # Δv1 only shapes the lookup keys: the cached triangle table is shared, the keys are recomputed
    c = mlv.build_database(catalog, CAM, mlv.Config(n_boresights=300, dv1=6e-5), progress=False)
    assert c.info_dict()["cached"] and c.dv1 == 6e-5 and c.n_triangles == a.n_triangles
    assert not np.array_equal(np.asarray(a.keys), np.asarray(c.keys))
    d = mlv.build_database(catalog, CAM, mlv.Config(n_boresights=301), progress=False)
    assert not d.info_dict()["cached"]  # the boresights shape the table: a different entry


def test_database_from_triangles_rejects_empty(catalog):
    with pytest.raises(ValueError):
        database_from_triangles(catalog, CAM, np.zeros((0, 3), int), 5e-5, 5e-4)


# ----------------------------------------------------------------------------- verification
def test_largest_cluster_brute_force():
    rng = np.random.default_rng(4)
    for _ in range(30):
        n = 7
        a = rng.random((n, n)) < 0.6
        a = np.triu(a, 1)
        a = a | a.T
        first, common, size = largest_cluster(jnp.asarray(a))
        best = 0
        cliques = []
        for mask in range(1, 2**n):
            m = [(mask >> i) & 1 for i in range(n)]
            idx = [i for i in range(n) if m[i]]
            if all(a[i, j] for i in idx for j in idx if i < j):
                cliques.append(set(idx))
                best = max(best, len(idx))
        assert int(size) == best
        top = [c for c in cliques if len(c) == best]
        assert set(np.nonzero(np.asarray(first))[0]) in top
        assert set(np.nonzero(np.asarray(common))[0]) == set.intersection(*top)


# ----------------------------------------------------------------------------- identification
@pytest.mark.parametrize("bad", [dict(n_stars=2), dict(n_stars=13), dict(dv1=0.0),
                                 dict(eps_deg=-1.0), dict(th1=-1), dict(ver_min=1)])
def test_config_validation(bad):
    with pytest.raises(ValueError):
        mlv.Config(**bad)


def test_registry():
    algo = js.algorithms.get("mlv")
    assert algo.Config is mlv.Config and callable(algo.build_database) and callable(algo.identify)
    hash(algo.Config())  # static jit argument


def test_noise_free_scenes_all_identified(catalog, database):
    scenes = js.simulate(jax.random.key(10), catalog, CAM, js.NoiseConfig(), batch_size=120,
                         capacity=32)
    result = mlv.identify(database, scenes, CFG)  # two chunks of 100 (one padded): one compile
    assert result.ids.shape == scenes.truth.shape and result.ok.shape == (120,)
    report = js.evaluate(scenes, result, "mlv")
    assert report["identification_rate"] == 1.0, report
    assert report["n_wrong"] == 0
    # the attitude fitted to the named stars (float32 centroids, no noise): arcsecond level
    assert report["boresight_err_arcsec_max"] < 5.0, report
    assert report["roll_err_arcsec_max"] < 30.0, report
    ids = np.asarray(result.ids)
    assert np.all(ids[:, CFG.n_stars:] == -1)  # only the N brightest can be named


def test_noisy_scenes_no_misidentification(catalog, database):
    noise = js.NoiseConfig(position_sigma_px=1.0, magnitude_sigma=0.3, n_false=3)
    scenes = js.simulate(jax.random.key(11), catalog, CAM, noise, batch_size=100, capacity=32)
    report = js.evaluate(scenes, mlv.identify(database, scenes, CFG), "mlv")
    assert report["identification_rate"] > 0.95, report
    assert report["n_wrong"] == 0, report
    # a second call with new scenes of the same shape, and a config differing only in host-side
    # fields, reuse the compilation
    compiled = _identify_batch._cache_size()
    again = js.simulate(jax.random.key(15), catalog, CAM, noise, batch_size=100, capacity=32)
    mlv.identify(database, again, dataclasses.replace(CFG, max_candidate_capacity=2048))
    assert _identify_batch._cache_size() == compiled


def test_false_stars_only_never_identified(database):
    rng = np.random.default_rng(5)
    xy = [rng.uniform(0, 1023, size=(rng.integers(3, 25), 2)) for _ in range(100)]
    scenes = js.scenes_from_centroids(xy, capacity=32)
    result = mlv.identify(database, scenes, CFG)
    assert np.all(np.asarray(result.ids) == -1)  # any id would be wrong
    assert not np.any(np.asarray(result.ok))


def test_candidate_overflow_is_flagged(catalog, database):
    """A bound set in the config is a rule: triangles over it cast no vote, counted in the
    diagnostics (no warning); the host retry doubles K up to it."""
    scenes = js.simulate(jax.random.key(12), catalog, CAM, js.NoiseConfig(), batch_size=4,
                         capacity=64)  # the shapes of the test below: compilations are shared
    tight = mlv.Config(n_boresights=CFG.n_boresights, candidate_capacity=2,
                       max_candidate_capacity=2, batch_chunk=4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, diag = mlv.identify(database, scenes, tight, diagnostics=True)
    counts = np.asarray(diag.triangle_candidates)
    np.testing.assert_array_equal(np.asarray(diag.n_overflow_triangles), np.sum(counts > 2, 1))
    assert np.all(np.asarray(diag.candidate_overflow) == (np.sum(counts > 2, 1) > 0))
    assert np.any(np.asarray(diag.candidate_overflow))
    # the host retry doubles the buffer (2 → 4) up to max_candidate_capacity
    grow = mlv.Config(n_boresights=CFG.n_boresights, candidate_capacity=2,
                      max_candidate_capacity=4, batch_chunk=4)
    _, diag2 = mlv.identify(database, scenes, grow, diagnostics=True)
    assert diag2.capacity == 4
    np.testing.assert_array_equal(np.asarray(diag2.triangle_candidates), counts)
    np.testing.assert_array_equal(np.asarray(diag2.n_overflow_triangles), np.sum(counts > 4, 1))


def test_window_counts_match_brute_force(catalog):
    db = mlv.build_database(catalog, CAM, mlv.Config(n_boresights=500), use_cache=False, progress=False)
    keys = np.asarray(db.keys)
    v1, v2 = keys // db.stride, keys % db.stride
    pick = np.random.default_rng(4).integers(0, len(keys), 300)
    for th1, th2 in [(0, 0), (1, 1), (2, 3)]:
        got = mlv.window_counts(db, th1, th2)
        ref = [np.sum((np.abs(v1 - v1[i]) <= th1) & (np.abs(v2 - v2[i]) <= th2)) for i in pick]
        np.testing.assert_array_equal(got[pick], ref)


def test_buffers_follow_a_dense_database(catalog, database):
    """Coarser bins pack ≈ 36× the triangles into a window (as a narrow field's database does).
    With every triangle voting (the paper), K and its bound follow the database's own windows: no
    triangle is left out and nothing is warned about. The default bound of 1,024 leaves the most
    ambiguous triangles out, counted in the diagnostics. The papers' camera keeps K = 256 and the
    bound 1,024 either way."""
    assert mlv.candidate_buffers(database, CFG)[:2] == (256, 1024)
    assert mlv.candidate_buffers(database, mlv.Config.paper())[:2] == (256, 1024)
    every = dataclasses.replace(CFG, dv1=6 * CFG.dv1, dv2=6 * CFG.dv2, batch_chunk=8,
                                max_candidate_capacity=None)
    dense = mlv.build_database(catalog, CAM, every, use_cache=False, progress=False)
    counts = mlv.window_counts(dense, 1, 1)
    buffers = mlv.candidate_buffers(dense, every)
    assert counts.max() > 1024 and buffers.max_capacity >= counts.max()
    assert buffers.capacity >= np.percentile(counts, 99)
    scenes = js.simulate(jax.random.key(17), catalog, CAM, js.NoiseConfig(), batch_size=8, capacity=32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "more than … candidates" warning
        result, diag = mlv.identify(dense, scenes, every, diagnostics=True)
        capped, diag_capped = mlv.identify(dense, scenes, dataclasses.replace(
            every, max_candidate_capacity=1024), diagnostics=True)
    assert not np.any(np.asarray(diag.candidate_overflow))
    seen = np.asarray(diag.triangle_candidates)
    assert np.max(seen) > 1024  # the scenes do meet such windows …
    np.testing.assert_array_equal(np.asarray(diag_capped.n_overflow_triangles), np.sum(seen > 1024, 1))
    for res in (result, capped):  # … and the answer is right either way
        assert js.evaluate(scenes, res, "mlv")["n_wrong"] == 0


def test_batched_matches_per_scene_and_capacity(catalog, database):
    noise = js.NoiseConfig(position_sigma_px=1.0, magnitude_sigma=0.3, n_false=2)
    scenes = js.simulate(jax.random.key(13), catalog, CAM, noise, batch_size=4, capacity=64)
    batched, diag = mlv.identify(database, scenes, CFG, diagnostics=True)
    n = CFG.n_stars
    one = jax.jit(identify_scene, static_argnames=("config", "capacity"))
    for i in range(4):  # the per-scene core, without vmap
        out = one(scenes.xy[i, :n], scenes.valid[i, :n], database, CFG, diag.capacity,
                  scenes.xy[i], scenes.valid[i])
        np.testing.assert_array_equal(np.asarray(out.ids), np.asarray(batched.ids[i, :n]))
        assert bool(out.ok) == bool(batched.ok[i])
    # capacity 32 vs 64: the same answer
    small = js.Scene(xy=scenes.xy[:, :32], mag=scenes.mag[:, :32], truth=scenes.truth[:, :32],
                     valid=scenes.valid[:, :32], attitude=scenes.attitude,
                     overflow=scenes.overflow)
    res32 = mlv.identify(database, small, CFG)
    np.testing.assert_array_equal(np.asarray(res32.ids), np.asarray(batched.ids[:, :32]))
    np.testing.assert_array_equal(np.asarray(res32.ok), np.asarray(batched.ok))
    assert triangle_combinations(n).shape == (math.comb(n, 3), 3)


def test_tuning_arrays_match_static_configs(catalog, database):
    """Th1/Th2/ε as per-scene arrays (one call, one compilation) equal one static config per value."""
    noise = js.NoiseConfig(position_sigma_px=2.0, magnitude_sigma=0.3, n_false=2)
    base = js.simulate(jax.random.key(16), catalog, CAM, noise, batch_size=4, capacity=64)
    grid = [(0, 0.1), (2, 0.3)]  # the Th = 2 config shares the swept call's compilation
    tiled = jax.tree_util.tree_map(lambda a: jnp.concatenate([a] * len(grid)), base)
    th = np.repeat([g[0] for g in grid], 4)
    eps = np.repeat([g[1] for g in grid], 4)
    eps_rad = np.deg2rad(eps.astype(np.float32))
    tuning = mlv.Tuning(th1=th, th2=th, eps_rad=eps_rad, side_tol_rad=eps_rad)
    swept, sdiag = mlv.identify(database, tiled, CFG, diagnostics=True, tuning=tuning)
    for g, (t, e) in enumerate(grid):
        cfg = dataclasses.replace(CFG, th1=t, th2=t, eps_deg=e, side_tol_deg=e)
        ref, rdiag = mlv.identify(database, tiled, cfg, diagnostics=True)
        part = slice(4 * g, 4 * g + 4)
        np.testing.assert_array_equal(np.asarray(swept.ids[part]), np.asarray(ref.ids[part]))
        np.testing.assert_array_equal(np.asarray(swept.ok[part]), np.asarray(ref.ok[part]))
        np.testing.assert_array_equal(np.asarray(sdiag.triangle_candidates[part]),
                                      np.asarray(rdiag.triangle_candidates[part]))
        np.testing.assert_array_equal(np.asarray(sdiag.votes[part]), np.asarray(rdiag.votes[part]))
    with pytest.raises(ValueError):
        mlv.identify(database, base, CFG, tuning=CFG.tuning()._replace(eps_rad=np.ones(3)))


def test_small_candidate_pool_same_result(catalog, database):
    """Scenes overflowing the shared candidate buffer are recomputed: P never changes the result."""
    noise = js.NoiseConfig(position_sigma_px=1.0, magnitude_sigma=0.3)
    scenes = js.simulate(jax.random.key(17), catalog, CAM, noise, batch_size=4, capacity=64)
    ref, rdiag = mlv.identify(database, scenes, CFG, diagnostics=True)
    totals = np.sum(np.asarray(rdiag.triangle_candidates), 1)
    small = dataclasses.replace(CFG, candidate_pool=int(0.75 * totals.min()))  # every scene retries
    got, gdiag = mlv.identify(database, scenes, small, diagnostics=True)
    np.testing.assert_array_equal(np.asarray(got.ids), np.asarray(ref.ids))
    np.testing.assert_array_equal(np.asarray(gdiag.votes), np.asarray(rdiag.votes))


@pytest.mark.slow
def test_paper_voting_mode_noise_free(catalog, database):
    """The paper's voting and verification alone (no extensions) on noise-free scenes."""
    paper = mlv.Config(n_boresights=CFG.n_boresights, batch_chunk=100, vertex_match=False,
                       attitude_check=False, field_check=False)
    scenes = js.simulate(jax.random.key(14), catalog, CAM, js.NoiseConfig(), batch_size=100,
                         capacity=32)
    report = js.evaluate(scenes, mlv.identify(database, scenes, paper), "mlv")
    assert report["identification_rate"] >= 0.97, report
    assert report["n_wrong"] == 0, report


def test_false_star_near_undetected_star_not_named(catalog, database):
    # The two mis-identifications of the 10,000-scene sweeps (5–6 false stars): a false star a few
    # pixels from a catalog star that was not detected (outside the frame / below the limit) took
    # its id, because its own residual inflated the scene's noise scale. Rebuild that: remove one
    # true star of the N brightest and put a spot 5–8 px from where it was, with its magnitude.
    noise = js.NoiseConfig(position_sigma_px=1.0, magnitude_sigma=0.3)
    scenes = js.simulate(jax.random.key(21), catalog, CAM, noise, batch_size=60, capacity=32)
    rng = np.random.default_rng(21)
    xy, mag, truth = np.asarray(scenes.xy), np.asarray(scenes.mag), np.asarray(scenes.truth)
    xy_list, mag_list, truth_list = [], [], []
    for b in range(scenes.batch_size):
        v = np.asarray(scenes.valid[b])
        j = int(rng.integers(1, 8))  # one of the N brightest, not the brightest
        x, m, t = xy[b, v].copy(), mag[b, v], truth[b, v].copy()
        phi = rng.uniform(0, 2 * np.pi)
        x[j] += rng.uniform(5.0, 8.0) * np.array([np.cos(phi), np.sin(phi)])
        t[j] = -1  # now a false star: its catalog star is not in the image
        xy_list.append(x), mag_list.append(m), truth_list.append(t)
    moved = js.scenes_from_centroids(xy_list, mag_list, capacity=32)
    ids = np.asarray(mlv.identify(database, moved, CFG).ids)
    for b in range(len(xy_list)):
        t = truth_list[b]
        named = ids[b, : len(t)]
        assert np.all((named == -1) | (named == t)), (b, named, t)


def test_checks_on_the_stars_near_the_field_equal_the_whole_catalog(catalog, database):
    """The attitude and field checks search the sky index's stars near the cluster's field
    (``Database.sky_cells``); on noisy clusters with wrong and swapped members they decide as a
    search of the whole catalog does."""
    from jstarid.algorithms.mlv.verify import attitude_check, field_check, fit_attitude
    from jstarid.sky_index import local_stars

    noise = js.NoiseConfig(position_sigma_px=1.5, n_false=2)
    scenes = js.simulate(jax.random.key(31), catalog, CAM, noise, batch_size=64, capacity=12)
    rng = np.random.default_rng(31)
    truth = np.asarray(scenes.truth).copy()
    for b in range(truth.shape[0]):  # a wrong candidate in half the scenes, a swap in a quarter
        if b % 2 == 0:
            truth[b, rng.integers(0, 12)] = rng.integers(0, len(catalog))
        if b % 4 == 1:
            truth[b, [0, 1]] = truth[b, [1, 0]]
    members = jnp.asarray((truth >= 0) & np.asarray(scenes.valid))
    rows = jnp.asarray(np.maximum(truth, 0), jnp.int32)
    vec = CAM.unproject(scenes.xy)
    kw = dict(sigmas=4.0, min_tol_rad=math.radians(0.05), max_tol_rad=math.radians(0.2),
              ambiguity_rad=math.radians(0.2), outlier_sigmas=3.0)

    def both(v, m, r, valid):
        att = fit_attitude(v, m, r, database.catalog_vectors)
        near = local_stars(database.sky_cells, database.catalog_vectors, att[2], database.sky_grid)
        everything = attitude_check(v, m, r, database.catalog_vectors, **kw)
        local = attitude_check(v, m, r, database.catalog_vectors, nearby=near[:2], **kw)
        field_all = field_check(att, v, valid, database.catalog_vectors, CAM, 10, math.radians(0.2))
        field_local = field_check(att, v, valid, near[1], CAM, 10, math.radians(0.2))
        return everything, local, jnp.stack(field_all), jnp.stack(field_local)

    everything, local, field_all, field_local = jax.jit(jax.vmap(both))(vec, members, rows,
                                                                       scenes.valid)
    np.testing.assert_array_equal(np.asarray(local), np.asarray(everything))
    np.testing.assert_array_equal(np.asarray(field_local), np.asarray(field_all))
    assert 0 < int(np.asarray(everything).any(axis=1).sum()) < 64  # some pass, some fail


def test_for_camera_keeps_the_paper_values_on_the_papers_cameras():
    for name in ("sgm2022", "mlv2021", "rpnet2019", "zy3"):
        assert mlv.Config.for_camera(js.camera_preset(name)) == mlv.Config()
    twin = js.camera_preset("narrow_twin")
    pixel, field = js.camera.tolerance_scales(twin)
    cfg = mlv.Config.for_camera(twin, th1=2)
    assert cfg.eps_deg == pytest.approx(0.2 * pixel) and cfg.dv2 == pytest.approx(5e-4 * pixel)
    assert cfg.dv1 == pytest.approx(5e-5 * pixel * field) and cfg.th1 == 2
    assert cfg.residual_max_deg == pytest.approx(0.2 * pixel) and cfg.n_stars == 10


@pytest.mark.slow
def test_narrow_twin_identified_with_the_defaults_for_its_camera():
    """The narrow twin (15.8″/px, V ≤ 10, 0.8 px, 2 false stars): ≥ 95 % identified, none wrong,
    with Config.for_camera."""
    from jstarid.papers import narrow_field as twin

    cam = js.camera_preset(twin.CAMERA)
    cat = js.load_catalog(twin.MAG_LIMIT)
    scenes = js.simulate(jax.random.key(35), cat, cam, js.NoiseConfig(**twin.NOISE), batch_size=200,
                         capacity=twin.CAPACITY)
    cfg = mlv.Config.for_camera(cam)
    result = mlv.identify(mlv.build_database(cat, cam, cfg, progress=False), scenes, cfg)
    report = js.evaluate(scenes, result, "strict")
    assert report["identification_rate"] >= 0.95 and report["misid_rate"] == 0.0


def test_fresh_scenes_of_a_size_met_before_compile_nothing(catalog, database):
    """A sweep meets fresh scenes every call: once MLV has identified a batch of a size, more fresh
    batches of that size and settings compile no XLA program (``CountCompilations``)."""
    from jstarid.runtime import CountCompilations

    batches = [js.simulate(jax.random.key(40 + k), catalog, CAM, js.NoiseConfig(position_sigma_px=1.0),
                           batch_size=4, capacity=64) for k in range(3)]
    jax.block_until_ready(batches)
    jax.block_until_ready(mlv.identify(database, batches[0], CFG).ids)  # this size met once
    with CountCompilations() as count:
        for scenes in batches[1:]:
            result = mlv.identify(database, scenes, CFG)
            jax.block_until_ready(result.ids)
    assert count.programs == 0, f"{count.programs} programs compiled on fresh scenes"
    assert np.any(np.asarray(result.ok))  # the calls did identify
