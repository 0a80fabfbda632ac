"""The hypothesis search of the finishing stage: the triangle index against brute force, and clutter."""

import dataclasses
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js
from jstarid import hypotheses, triangle_index
from jstarid.finishing import Finishing, finish
from jstarid.geometry.star_pairs import frame_pair_angle
from jstarid.hypotheses import solve_unsolved
from jstarid.scene import Identification
from jstarid.triangle_index import (
    TooManyTriangles,
    build_triangle_index,
    expected_triangles,
    index_problem,
    query,
    stars_that_fit,
)


def _cap_stars(n, radius_deg, seed):
    """n random unit vectors within ``radius_deg`` of +z."""
    rng = np.random.default_rng(seed)
    cos_r = math.cos(math.radians(radius_deg))
    z = rng.uniform(cos_r, 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], 1)


def _angle(u, v):
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.sum(u * v, axis=-1))


def test_index_holds_every_triangle_and_queries_equal_brute_force():
    vectors = _cap_stars(90, 12.0, 0)
    cam = js.Camera(width=640, height=480, f_px=2400.0, name="tiny")  # ≈ 19° diagonal
    eps = 2e-3
    index = build_triangle_index(vectors, cam, eps)
    max_side = 2.0 * cam.half_diagonal_rad * 1.01
    abc = np.asarray(list(itertools.combinations(range(len(vectors)), 3)))
    va, vb, vc = (vectors[abc[:, m]] for m in range(3))
    all_sides = np.sort(np.stack([_angle(vb, vc), _angle(va, vc), _angle(va, vb)], 1), axis=1)
    inside = all_sides[:, 2] <= max_side
    brute = {tuple(t): s for t, s in zip(abc[inside].tolist(), all_sides[inside], strict=True)}
    stars = np.asarray(index.stars)
    assert {tuple(sorted(t)) for t in stars.tolist()} == set(brute) and len(stars) == len(brute)
    # star m is opposite side m
    v = vectors[stars]
    opposite = np.stack([_angle(v[:, 1], v[:, 2]), _angle(v[:, 0], v[:, 2]), _angle(v[:, 0], v[:, 1])], 1)
    np.testing.assert_allclose(opposite, np.asarray(index.sides), atol=1e-6)
    keys = list(brute)
    table = np.stack([brute[k] for k in keys])
    rng = np.random.default_rng(1)
    noise = rng.uniform(-0.9 * eps, 0.9 * eps, (40, 3))
    probes = np.sort(table[np.arange(40) * 7 % len(keys)] + noise, axis=1)
    slots, match = jax.jit(jax.vmap(query, in_axes=(None, 0, None)))(index, jnp.asarray(probes, jnp.float32),
                                                                    jnp.float32(eps))
    for sides, slot, hit in zip(probes.astype(np.float32), np.asarray(slots), np.asarray(match), strict=True):
        found = {tuple(sorted(stars[s].tolist())) for s in slot[hit]}
        gap = np.max(np.abs(table - sides), axis=1)
        expected = {keys[k] for k in np.flatnonzero(gap <= eps - 1e-6)}
        borderline = {keys[k] for k in np.flatnonzero(gap <= eps + 1e-6)}
        assert expected <= found <= borderline


def test_an_index_is_kept_on_disk_and_read_back_whole(tmp_path, monkeypatch):
    """A second process (here: an emptied memo) reads the index from the cache directory instead of
    counting the triangles again, and gets the same index."""
    monkeypatch.setenv("JSTARID_CACHE", str(tmp_path))
    monkeypatch.setattr(triangle_index, "_MEMO", {})
    vectors = _cap_stars(60, 10.0, 3)
    cam = js.Camera(width=640, height=480, f_px=2400.0, name="tiny")
    built = build_triangle_index(vectors, cam, 2e-3)
    files = list((tmp_path / "triangles").glob("*.npz"))
    assert len(files) == 1
    monkeypatch.setattr(triangle_index, "_MEMO", {})
    monkeypatch.setattr(triangle_index, "_build", None)  # counting again would fail
    read = build_triangle_index(vectors, cam, 2e-3)
    for field in ("codes", "stars", "sides"):
        np.testing.assert_array_equal(np.asarray(getattr(read, field)), np.asarray(getattr(built, field)))
    assert (read.cell_rad, read.n_cells, read.run, read.key) == (built.cell_rad, built.n_cells, built.run,
                                                                 built.key)


def test_a_catalog_too_deep_for_the_frame_is_named_and_refused(catalog6):
    cam = js.camera_preset("sgm2022")
    assert "brighter catalog" in index_problem(5070, cam)
    assert index_problem(3000, js.Camera(width=1920, height=1440, f_px=10973.0)) is None
    with pytest.raises(TooManyTriangles, match="brighter catalog"):
        build_triangle_index(catalog6.unit_vectors, cam, 1e-4)
    # the finishing stage then leaves the scenes as the algorithm left them
    scenes = js.simulate(jax.random.key(2), catalog6, cam, js.NoiseConfig(), batch_size=2, capacity=16)
    failed = Identification(ids=np.full((2, 16), -1, np.int32), ok=np.zeros(2, bool), attitude=None)
    finished = finish(failed, scenes, Finishing(focal_search=(), fit_focal=False, max_false_match=1.0),
                      rerun=None, camera=cam, star_vectors=catalog6.unit_vectors)
    assert finished.result is failed and not finished.searched.any()


@pytest.fixture(scope="module")
def clutter_setup(catalog6):
    cam = js.Camera(width=1280, height=960, f_px=1280 / (2 * math.tan(math.radians(4.0))), mag_limit=6.0,
                    name="clutter8")
    return catalog6, cam


def test_a_deep_catalogs_search_stars_cover_every_frame_evenly(clutter_setup):
    """``stars_that_fit``: within the budget, and more frames hold three of them than hold three of a
    magnitude cut as large (counted over random boresights with NumPy)."""
    cat, cam = clutter_setup
    assert np.array_equal(stars_that_fit(cat.unit_vectors, cat.mag, cam, budget=1e12), np.arange(len(cat)))
    budget = 200_000
    kept = stars_that_fit(cat.unit_vectors, cat.mag, cam, budget=budget)
    assert expected_triangles(kept.size, frame_pair_angle(cam)) <= budget < expected_triangles(
        len(cat), frame_pair_angle(cam))
    assert np.all(np.diff(kept) > 0)
    cut = np.argsort(cat.mag, kind="stable")[:kept.size]
    hemisphere = np.where(np.random.default_rng(8).random(3000) < 0.5, 1, -1)[:, None]
    boresights = _cap_stars(3000, 90.0, 7) * hemisphere  # uniform over the sky
    inside = boresights @ np.asarray(cat.unit_vectors).T > math.cos(math.radians(5.0))  # a 10° circle

    def three_or_more(rows):
        return np.mean(inside[:, rows].sum(1) >= 3)

    assert three_or_more(kept) > three_or_more(cut) + 0.08  # 0.94 against 0.82


def test_a_sparse_fields_deep_catalog_is_searched_over_its_brightest_star_per_cell(clutter_setup,
                                                                                   monkeypatch):
    """Where the catalog has too many triangles per frame (here: a lowered cap), the search indexes
    the brightest star of each sky cell and still names every star of the catalog from it."""
    cat, cam = clutter_setup
    monkeypatch.setattr(triangle_index, "_MEMO", {})  # no refusal or index left for the other tests
    monkeypatch.setattr(triangle_index, "MAX_TRIANGLES", 400_000)
    monkeypatch.setattr(triangle_index, "SEARCH_TRIANGLES", 300_000)
    kept = stars_that_fit(cat.unit_vectors, cat.mag, cam)
    assert kept.size < 0.8 * len(cat)
    noise = js.NoiseConfig(position_sigma_px=0.5, n_false=10, false_mag_min=1.0, false_mag_max=6.0)
    scenes = js.simulate(jax.random.key(9), cat, cam, noise, batch_size=8, capacity=48)
    failed = Identification(ids=np.full((8, 48), -1, np.int32), ok=np.zeros(8, bool), attitude=None)
    search = dict(star_vectors=cat.unit_vectors, camera=cam, n_use=32, eps_px=3.0, min_confirm=1,
                  max_false_match=1e-3)
    with pytest.raises(TooManyTriangles):
        solve_unsolved(failed, scenes, **search)
    result, solved, _ = solve_unsolved(failed, scenes, **search, star_mags=cat.mag)
    truth, ids = np.asarray(scenes.truth), np.asarray(result.ids)
    assert solved.sum() >= 5
    assert not np.any((ids >= 0) & (ids != truth))  # no wrong name anywhere
    named = ids[ids >= 0]
    assert not np.isin(named, kept).all()  # stars outside the index named from the attitude


def test_a_claim_the_check_takes_back_is_searched_again(clutter_setup, monkeypatch):
    """Step 4 (``finishing.search_lost``): scenes an algorithm claimed with names the camera check
    cannot fit are searched like the unsolved ones, and named right; without the search they fail.
    The copies that pad its call to 16 scenes are not searched (they were, each of them)."""
    cat, cam = clutter_setup
    searched, real_search = [], hypotheses._search_rows

    def recorded(rows, **kwargs):
        searched.extend(np.asarray(rows).tolist())
        return real_search(rows, **kwargs)

    monkeypatch.setattr(hypotheses, "_search_rows", recorded)
    noise = js.NoiseConfig(position_sigma_px=0.5, n_false=5, false_mag_min=1.0, false_mag_max=6.0)
    scenes = js.simulate(jax.random.key(12), cat, cam, noise, batch_size=6, capacity=32)
    truth = np.asarray(scenes.truth)
    ids = np.full((6, 32), -1, np.int32)
    ids[:, :4] = np.random.default_rng(4).choice(len(cat), (6, 4))  # four names of random stars
    claims = Identification(ids=jnp.asarray(ids), ok=jnp.ones(6, bool), attitude=None)
    stage = dict(rerun=None, camera=cam, star_vectors=cat.unit_vectors, star_mags=cat.mag)
    # triples of the 12 brightest (a small search: the suite's optimisation level); 2b and 3 apart
    config = Finishing(focal_search=(), hypotheses=12, rival_odds=0, max_false_match=1.0)
    lost = finish(claims, scenes, dataclasses.replace(config, hypotheses=0), **stage)
    assert not np.asarray(lost.result.ok).any()  # the check takes every claim back
    found = finish(claims, scenes, config, **stage)
    assert set(searched) == set(range(6))  # the six scenes, not the copies that pad the call to 16
    ok, got = np.asarray(found.result.ok), np.asarray(found.result.ids)
    assert found.claimed.all() and ok.sum() >= 4
    np.testing.assert_array_equal(found.searched, ok)
    assert np.all(got[ok][got[ok] >= 0] == truth[ok][got[ok] >= 0])  # every name right
    assert np.all(np.isfinite(np.asarray(found.result.focal_scale)[ok]))  # checked like any claim


def test_stars_among_many_false_detections_are_found_and_random_points_never_claimed(clutter_setup):
    cat, cam = clutter_setup
    noise = js.NoiseConfig(position_sigma_px=0.5, n_false=30, false_mag_min=1.0, false_mag_max=6.0,
                           false_mag_slope=js.CATALOG_MAG_SLOPE)
    scenes = js.simulate(jax.random.key(5), cat, cam, noise, batch_size=12, capacity=64)
    b = scenes.batch_size
    failed = Identification(ids=np.full((b, 64), -1, np.int32), ok=np.zeros(b, bool), attitude=None)
    result, solved, overflow = solve_unsolved(failed, scenes, star_vectors=cat.unit_vectors, camera=cam,
                                              n_use=40, eps_px=3.0, min_confirm=1, max_false_match=1e-3)
    assert not overflow.any()
    truth, ids, ok = np.asarray(scenes.truth), np.asarray(result.ids), np.asarray(result.ok)
    stars = np.sum(truth >= 0, axis=1)
    assert np.array_equal(ok, solved)
    assert not np.any((ids >= 0) & (ids != truth))  # no wrong name anywhere
    assert np.all(ids[~ok] == -1) and np.all(np.isnan(np.asarray(result.attitude)[~ok]))
    assert np.all(ok[stars >= 7])  # plenty of stars among 30 false ones: solved
    assert np.sum(ok) >= 8
    # a solved scene's boresight is its truth's (within 20″)
    true_z, found_z = np.asarray(scenes.attitude)[ok][:, 2], np.asarray(result.attitude)[ok][:, 2]
    assert np.all(_angle(true_z.astype(np.float64), found_z.astype(np.float64)) < 1e-4)
    # two scenes of random points (each a whole search of 40 detections' triples: slow at the
    # suite's XLA optimisation level; test_contract's random points cover every algorithm)
    rng = np.random.default_rng(3)
    points = js.scenes_from_centroids([rng.uniform(0, 1, (30, 2)) * [1279, 959] for _ in range(2)],
                                      [np.sort(rng.uniform(1, 6, 30)) for _ in range(2)], capacity=64)
    _, claimed, _ = solve_unsolved(failed[:2], points, star_vectors=cat.unit_vectors, camera=cam, n_use=40,
                                   eps_px=3.0, min_confirm=1, max_false_match=1e-3)
    assert not claimed.any()


def test_padding_scenes_are_skipped(clutter_setup):
    """A chunk padded with copies of a scene searches the scene once: the copies (``real`` False)
    come back empty, not solved again (the statics of the test above: its program is reused)."""
    cat, cam = clutter_setup
    noise = js.NoiseConfig(position_sigma_px=0.5, n_false=30, false_mag_min=1.0, false_mag_max=6.0,
                           false_mag_slope=js.CATALOG_MAG_SLOPE)
    scenes = js.simulate(jax.random.key(5), cat, cam, noise, batch_size=12, capacity=64)
    first = int(np.argmax(np.sum(np.asarray(scenes.truth) >= 0, axis=1)))  # the most stars: solved
    vectors = np.asarray(cat.unit_vectors, np.float32)
    eps_rad = 3.0 / cam.f_px
    index = hypotheses._search_index(vectors, None, cam, eps_rad)
    cells, grid = hypotheses._sky_cells(vectors, index, cam, eps_rad)
    part = np.full(16, first)
    found = hypotheses._search_chunk(
        jnp.asarray(scenes.xy)[part], jnp.asarray(scenes.valid)[part], jnp.asarray(scenes.mag)[part],
        jnp.arange(16) < 1, jnp.asarray(hypotheses.padded_triples(40)), index, jnp.asarray(vectors), cells,
        grid=grid, camera=cam, n_use=40, eps_rad=eps_rad, min_confirm=1, capacity=4096, per_triple=16)
    ok, ids = np.asarray(found.ok), np.asarray(found.ids)
    assert ok[0] and np.array_equal(ids[0][ids[0] >= 0], np.asarray(scenes.truth)[first][ids[0] >= 0])
    assert not ok[1:].any() and np.all(ids[1:] == -1) and np.all(np.asarray(found.n_hypotheses)[1:] == 0)


def test_only_the_live_hypotheses_are_verified():
    """``_verify_live`` equals a map over every hypothesis where one is live (chunks of
    ``HYPOTHESIS_CHUNK``), and leaves the chunks past the last live one unverified."""
    chunk = hypotheses.HYPOTHESIS_CHUNK
    h = 3 * chunk + 5
    hyps = (jnp.arange(h, dtype=jnp.int32), jnp.arange(h) % 3 == 0)

    def verify(hyp):
        i, alive = hyp
        att = jnp.full((3, 3), i, jnp.float32)
        return att, jnp.where(alive, i + 1, 0), jnp.full(4, i, jnp.int32)

    every = jax.lax.map(verify, hyps)
    for n_live in (0, 1, chunk, chunk + 1, h):
        got = jax.jit(hypotheses._verify_live, static_argnums=(0, 3))(verify, hyps, n_live, 4)
        done = -(-n_live // chunk) * chunk  # whole chunks up to the last live hypothesis
        for a, b, empty in zip(got, every, (0, 0, -1), strict=True):
            np.testing.assert_array_equal(np.asarray(a)[:done], np.asarray(b)[:done])
            assert np.all(np.asarray(a)[done:] == empty)


def test_a_crowded_scene_is_searched_again_over_more_detections(clutter_setup, monkeypatch):
    """False detections all brighter than the stars: the brightest ``n_use`` hold no star and the
    first pass finds nothing; the crowded pass over ``n_crowded`` finds the stars, none named wrong,
    and a scene with no more than ``n_use`` detections is not searched twice."""
    cat, cam = clutter_setup
    noise = js.NoiseConfig(position_sigma_px=0.5, n_false=16, false_mag_min=0.0, false_mag_max=1.0)
    scenes = js.simulate(jax.random.key(15), cat, cam, noise, batch_size=8, capacity=32)
    truth, valid = np.asarray(scenes.truth), np.asarray(scenes.valid)
    failed = Identification(ids=np.full((8, 32), -1, np.int32), ok=np.zeros(8, bool), attitude=None)
    search = dict(star_vectors=cat.unit_vectors, camera=cam, n_use=12, eps_px=3.0, min_confirm=1,
                  max_false_match=1e-3, capacity=1024)
    passes = []
    search_rows = hypotheses._search_rows
    monkeypatch.setattr(hypotheses, "_search_rows",
                        lambda rows, **kw: passes.append((rows.size, kw["n_use"])) or search_rows(rows, **kw))
    result, solved, overflow = solve_unsolved(failed, scenes, **search, n_crowded=32)
    assert passes == [(8, 12), (8, 32)]  # no scene solved by the first pass
    ids = np.asarray(result.ids)
    assert not np.any((ids >= 0) & (ids != truth))  # no wrong name anywhere
    stars = np.sum((truth >= 0) & valid, axis=1)
    assert np.all(solved[stars >= 6]) and solved.sum() >= 4 and not overflow.any()
    few = js.simulate(jax.random.key(15), cat, cam, noise, batch_size=8, capacity=12)
    passes.clear()
    solve_unsolved(Identification(ids=np.full((8, 12), -1, np.int32), ok=np.zeros(8, bool), attitude=None),
                   few, **search, n_crowded=32)
    assert passes == [(8, 12)]  # 12 detections: the first pass saw them all


def test_solved_scenes_are_left_alone_and_the_setting_is_checked(clutter_setup):
    cat, cam = clutter_setup
    scenes = js.simulate(jax.random.key(6), cat, cam, js.NoiseConfig(), batch_size=3, capacity=32)
    given = Identification(ids=jnp.asarray(scenes.truth), ok=jnp.ones(3, bool), attitude=None)
    same, solved, _ = solve_unsolved(given, scenes, star_vectors=cat.unit_vectors, camera=cam, n_use=32,
                                  eps_px=3.0, min_confirm=1, max_false_match=1e-3)
    assert same is given and not solved.any()
    assert Finishing.off().hypotheses == 0 and Finishing().hypotheses == 48
    for bad in ({"hypotheses": 3}, {"hypotheses": 65}, {"hypothesis_eps_px": 0.0},
                {"hypothesis_false_match": 0.5}, {"crowded_hypotheses": 129}, {"crowded_hypotheses": -1}):
        with pytest.raises(ValueError):
            Finishing(**bad)


def test_hypotheses_past_the_capacity_are_flagged(clutter_setup, monkeypatch):
    """A search that cannot verify every hypothesis searches the scenes it left unsolved again with
    sixteen times the capacity, and says so where that is not enough either; what it claims still
    passes the test."""
    cat, cam = clutter_setup
    noise = js.NoiseConfig(position_sigma_px=0.5, n_false=30, false_mag_min=1.0, false_mag_max=6.0,
                           false_mag_slope=js.CATALOG_MAG_SLOPE)
    scenes = js.simulate(jax.random.key(5), cat, cam, noise, batch_size=12, capacity=64)
    scenes = scenes[:4]  # the test above's first four: the second pass claims the first
    failed = Identification(ids=np.full((4, 64), -1, np.int32), ok=np.zeros(4, bool), attitude=None)
    passes = []
    search_rows = hypotheses._search_rows
    monkeypatch.setattr(hypotheses, "_search_rows", lambda rows, **kw: passes.append(
        (rows.size, kw["n_use"], kw["capacity"])) or search_rows(rows, **kw))
    result, solved, overflow = solve_unsolved(failed, scenes, star_vectors=cat.unit_vectors, camera=cam,
                                              n_use=40, eps_px=3.0, min_confirm=1, max_false_match=1e-3,
                                              capacity=8, per_triple=1)
    assert passes == [(4, 40, 8), (4, 40, 128)]  # the first pass claims none of them
    assert overflow.all()
    ids = np.asarray(result.ids)
    assert not np.any((ids >= 0) & (ids != np.asarray(scenes.truth)))
    assert solved.any()  # a claim from the second pass, held to the false-match test
