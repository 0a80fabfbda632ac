"""Magnitude-robust SGM (``Config.subgraph``): subgraph matching against a brute-force reference,
the radius votes against a plain loop, and identification when the scenes hold stars the database
lacks and lack stars it holds."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jstarid as js
from jstarid import Finishing
from jstarid.algorithms import sgm
from jstarid.algorithms.sgm.graph import adjacency_deg, searchable_graphs
from jstarid.algorithms.sgm.subgraph import drop_outliers, partial_match, radial_votes, radii_table

TOL = 0.05  # edge residual tolerance of these tests (deg); star noise 0.004° ≪ TOL


def _disc_stars(rng, n, radius_deg):
    """(n, 3) unit vectors uniform in a cap of ``radius_deg`` about +z (the main star first, at +z)."""
    r = np.radians(radius_deg) * np.sqrt(rng.uniform(0.05, 1.0, n))
    az = rng.uniform(0, 2 * np.pi, n)
    v = np.stack([np.sin(r) * np.cos(az), np.sin(r) * np.sin(az), np.cos(r)], axis=-1)
    v[0] = [0.0, 0.0, 1.0]
    return v


def _planted(seed, n_common, extra_i, extra_j, sigma_deg=0.004):
    """Image and database graphs sharing ``n_common`` stars (main included), each with extras.

    Returns ``(a_i, a_j, truth)``: adjacencies (deg) and the planted correspondence (P,) (−1 for
    image extras). Image vertices are a shuffle of the common stars and extras, main first.
    """
    rng = np.random.default_rng(seed)
    sky = _disc_stars(rng, n_common + extra_i + extra_j, 4.0)
    img_rows = np.concatenate([[0], rng.permutation(np.r_[1:n_common, n_common:n_common + extra_i])])
    db_rows = np.concatenate([[0], rng.permutation(np.r_[1:n_common, n_common + extra_i:len(sky)])])
    turn = Rotation.from_rotvec(rng.normal(size=3) * 0.5)
    img = turn.apply(sky[img_rows]) + np.radians(sigma_deg) * rng.normal(size=(len(img_rows), 3))
    img /= np.linalg.norm(img, axis=1, keepdims=True)
    a_i = np.asarray(adjacency_deg(jnp.asarray(img), jnp.ones(len(img), bool)))
    a_j = np.asarray(adjacency_deg(jnp.asarray(sky[db_rows]), jnp.ones(len(db_rows), bool)))
    where = {int(r): k for k, r in enumerate(db_rows)}
    truth = np.array([where[int(r)] if r < n_common else -1 for r in img_rows], np.int32)
    return a_i, a_j, truth


def brute_force_subgraph(a_i, a_j, tol):
    """Reference: the partial one-to-one map with vertex 0 → 0 whose every pair of pairs agrees
    within ``tol`` and that has the most pairs, ties to the smallest ‖A'_I − A_J‖_F (depth-first
    over the image vertices in order, each unmatched or paired with a free database vertex)."""
    p, q = a_i.shape[0], a_j.shape[0]
    best = [None, (-1, 0.0)]

    def extend(i, match, sq):
        if i == p:
            key = (sum(m >= 0 for m in match), -sq)
            if key > best[1]:
                best[0], best[1] = list(match), key
            return
        extend(i + 1, match + [-1], sq)
        used = set(match)
        for j in range(1, q):
            if j in used:
                continue
            prev = [(k, m) for k, m in enumerate(match) if m >= 0]
            d = [a_i[i, k] - a_j[j, m] for k, m in prev]
            if all(abs(x) <= tol for x in d):
                extend(i + 1, match + [j], sq + 2 * sum(x * x for x in d))

    extend(1, [0], 0.0)
    return np.array(best[0], np.int32)


@pytest.mark.parametrize("seed", range(12))
def test_partial_match_equals_brute_force_on_small_graphs(seed):
    n_common, extra_i, extra_j = 4 + seed % 3, 1 + seed % 2, 1 + (seed // 2) % 3
    a_i, a_j, truth = _planted(seed, n_common, extra_i, extra_j)
    ref = brute_force_subgraph(a_i, a_j, TOL)
    np.testing.assert_array_equal(ref, truth)  # the reference finds what was planted
    p, q = a_i.shape[0], a_j.shape[0]
    # padded to 12 slots, as the search pads graphs
    pad_i = np.zeros((12, 12), np.float32)
    pad_i[:p, :p] = a_i
    pad_j = np.zeros((12, 12), np.float32)
    pad_j[:q, :q] = a_j
    match, err = partial_match(jnp.asarray(pad_i), jnp.arange(12) < p, jnp.asarray(pad_j),
                               jnp.arange(12) < q, c=1.74, tol=TOL, n_iter=30, power_tol=1e-4,
                               min_matched=3)
    np.testing.assert_array_equal(np.asarray(match)[:p], ref)
    assert np.all(np.asarray(match)[p:] == -1)
    used = ref >= 0
    d = a_i[np.ix_(used, used)] - a_j[np.ix_(ref[used], ref[used])]
    np.testing.assert_allclose(float(err), np.sqrt(np.sum(d * d)) / used.sum(), rtol=1e-4, atol=1e-6)


def test_drop_outliers_unmatches_a_wrong_pair_and_keeps_the_right_ones():
    a_i, a_j, truth = _planted(3, 6, 0, 0)
    wrong = truth.copy()
    wrong[[2, 4]] = wrong[[4, 2]]  # two swapped pairs: both disagree with the other four
    out = np.asarray(drop_outliers(jnp.asarray(a_i), jnp.asarray(a_j), jnp.asarray(wrong), TOL, 3))
    np.testing.assert_array_equal(out, np.where(np.isin(np.arange(6), [2, 4]), -1, truth))
    right = np.asarray(drop_outliers(jnp.asarray(a_i), jnp.asarray(a_j), jnp.asarray(truth), TOL, 3))
    np.testing.assert_array_equal(right, truth)


def test_radial_votes_match_a_plain_loop(setup5):
    _, _, db = setup5
    radii = radii_table(db)
    rng = np.random.default_rng(0)
    r_i = np.sort(rng.uniform(0.5, 6.0, 8)).astype(np.float32)
    r_i[0] = 0.0
    valid = np.arange(8) > 0
    valid[5] = False
    got = np.asarray(radial_votes(jnp.asarray(r_i), jnp.asarray(valid), jnp.asarray(radii), 0.05))
    want = np.zeros(len(db), np.int32)
    for d in range(len(db)):
        nb = db.adj[d, 0, 1:db.n[d]]
        want[d] = sum(1 for k in range(8) if valid[k] and np.any(np.abs(nb - r_i[k]) <= 0.05))
    np.testing.assert_array_equal(got, want)


def _hip_correct(ids, truth, db_cat, sim_cat):
    """(B, N) bool named, (B, N) bool named right, comparing Hipparcos numbers across catalogs."""
    named = ids >= 0
    right = named & (truth >= 0) & (db_cat.hip[np.maximum(ids, 0)] == sim_cat.hip[np.maximum(truth, 0)])
    return named, right


@pytest.mark.slow
def test_subgraph_identifies_scenes_deeper_than_the_database_and_never_wrongly(setup5):
    """Scenes drawn to V 5.5 with 0.2 mag of magnitude noise, the 20 brightest detections kept, the
    database to V 5.0: the image and database graphs each hold stars the other lacks (the paper's
    search solves 17 of these 32 scenes, measured with the same seed)."""
    cat5, _, db = setup5
    sim_cat = js.load_catalog(5.5)
    cam = js.camera_preset("sgm2022", mag_limit=5.5)
    noise = js.NoiseConfig(position_sigma_px=0.5, magnitude_sigma=0.2)
    scenes = js.simulate(jax.random.key(4), sim_cat, cam, noise, batch_size=32, capacity=20)
    config = sgm.Config(subgraph=sgm.Subgraph(on=True), finishing=Finishing.off())
    res, diag = sgm.identify(db, scenes, config, diagnostics=True)
    named, right = _hip_correct(np.asarray(res.ids), np.asarray(scenes.truth), cat5, sim_cat)
    assert np.array_equal(named, right)  # no wrong name
    ok = np.asarray(res.ok)
    assert ok.sum() >= 26
    assert np.all(named.sum(axis=1)[ok] >= config.min_matched)
    assert np.all(diag.level[diag.match_ok] == 0) and np.all(diag.n_matched[diag.usable] >= 1)
    assert diag.cut.dtype == bool and diag.cut.shape == ok.shape and not np.any(diag.cut & ~diag.match_ok)


def test_later_main_stars_are_the_next_nearest_to_the_principal_point(setup5):
    _, cam, db = setup5
    rng = np.random.default_rng(2)
    xy = [cam.cx + rng.uniform(-300, 300, (n, 2)) for n in (6, 9, 2)]
    scenes = js.scenes_from_centroids(xy, capacity=12)
    d2 = np.where(np.asarray(scenes.valid),
                  np.sum((np.asarray(scenes.xy) - [cam.cx, cam.cy]) ** 2, axis=-1), np.inf)
    order = np.argsort(d2, axis=1, kind="stable")
    for rank in range(3):
        g, _ = searchable_graphs(db, scenes, sgm.Config(subgraph=sgm.Subgraph(on=True)), main_rank=rank)
        np.testing.assert_array_equal(g.main, order[:, rank])
        np.testing.assert_array_equal(g.any, np.asarray(scenes.valid).sum(axis=1) > rank)


def test_subgraph_is_off_in_the_paper_and_checked():
    assert not sgm.Config().subgraph.on
    assert not sgm.Config.paper().subgraph.on
    with pytest.raises(ValueError, match="subgraph"):
        sgm.Subgraph(tol_deg=0.0)
    with pytest.raises(ValueError, match="subgraph"):
        sgm.Subgraph(matchings=0)


def test_subgraph_fails_cleanly_on_empty_and_tiny_scenes(setup5):
    _, cam, db = setup5
    xy = [np.zeros((0, 2)), np.array([[cam.cx, cam.cy], [cam.cx + 40.0, cam.cy]])]
    scenes = js.scenes_from_centroids(xy, capacity=8)
    res, diag = sgm.identify(db, scenes, sgm.Config(subgraph=sgm.Subgraph(on=True)), diagnostics=True)
    assert not np.any(np.asarray(res.ok)) and np.all(np.asarray(res.ids) == -1)
    assert not np.any(diag.usable) and np.all(diag.best == -1)
