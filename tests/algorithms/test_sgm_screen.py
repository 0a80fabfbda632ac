"""SGM's triangle screen (``Config.screen``): its kernel against a plain-loop reference, the plane
coordinates it reads, and the search it filters (Algorithm 1 over the candidates that pass)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

import jstarid as js
from jstarid import Finishing
from jstarid.algorithms import sgm
from jstarid.algorithms.sgm.graph import plane_coords, separation_deg
from jstarid.algorithms.sgm.screen import nearest_partners, screen_pairs, screen_pass, triangle_support

_support = jax.jit(triangle_support, static_argnames=("partners", "hypotheses"))


def _reference_support(xi, n_i, xj, n_j, tol, partners, hypotheses):
    """The screen's definition, one hypothesis and one star at a time."""
    r_i = [float(np.hypot(*xi[k])) for k in range(n_i)]
    r_j = [float(np.hypot(*xj[v])) for v in range(n_j)]

    def partners_of(k):
        gaps = sorted((abs(r_i[k] - r_j[v]), v) for v in range(1, n_j))[:partners]
        return [v for gap, v in gaps if gap <= tol]

    def rotation(k, v):  # the turn about the main star that takes image star k onto database star v
        return np.arctan2(xj[v][1], xj[v][0]) - np.arctan2(xi[k][1], xi[k][0])

    best = None
    for i in [k for k in range(1, n_i) if r_i[k] >= 4 * tol][:hypotheses]:
        for j in partners_of(i):
            count = 0
            for k in range(1, n_i):
                turns = [rotation(k, v) - rotation(i, j) for v in partners_of(k) if v != j and k != i]
                if any(abs(np.angle(np.exp(1j * t))) <= tol / r_i[i] + tol / r_i[k] for t in turns):
                    count += 1
            best = count if best is None else max(best, count)
    return 0 if best is None else best + 2


def _random_graph(rng, n, radius=6.0):
    r = radius * np.sqrt(rng.uniform(0.02, 1, n - 1))
    az = rng.uniform(-np.pi, np.pi, n - 1)
    return np.concatenate([[[0.0, 0.0]], np.stack([r * np.cos(az), r * np.sin(az)], 1)])


def _padded(x, size):
    out = np.zeros((size, 2), np.float32)
    out[:len(x)] = x
    return out


def test_triangle_support_equals_a_plain_loop_reference():
    """Rotated noisy copies (with a star lost and a fake one added) and unrelated graphs, of
    different sizes: the kernel's count equals the reference's, and separates the two kinds."""
    rng = np.random.default_rng(0)
    tol, size = 0.25, 24
    same, other = [], []
    for trial in range(12):
        a = _random_graph(rng, int(rng.integers(8, 20)))
        t = rng.uniform(-np.pi, np.pi)
        rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
        b = np.matmul(a, rot.T) + np.concatenate([[[0, 0]], rng.normal(0, 0.03, (len(a) - 1, 2))])
        b = np.concatenate([b[:-1], _random_graph(rng, 2)[1:]])  # the last star lost, a fake one in
        c = _random_graph(rng, int(rng.integers(8, 20)))
        for x, y, bucket in ((a, b, same), (a, c, other)):
            got = int(_support(jnp.asarray(_padded(x, size)), len(x), jnp.asarray(_padded(y, size)),
                               len(y), tol=jnp.float32(tol), partners=4, hypotheses=6))
            assert got == _reference_support(x, len(x), y, len(y), tol, 4, 6), trial
            bucket.append(got / min(len(x), len(y)))
    assert min(same) >= 0.8 and max(other) < 0.6, (same, other)


def test_plane_coords_keep_radii_and_turn_with_the_sky():
    """Radius = angle to the main star; a rotation of the sky (SciPy) moves the plane coordinates by
    a rotation about the origin (det + 1: no mirror), up to the projection's r²/6 scale error."""
    rng = np.random.default_rng(1)
    main = np.array([0.3, -0.5, 0.8])
    main /= np.linalg.norm(main)
    vecs = main + rng.normal(0, 0.05, (10, 3))
    vecs[0] = main
    vecs /= np.linalg.norm(vecs, axis=1, keepdims=True)
    mask = jnp.ones(10, bool)
    xy = np.asarray(plane_coords(jnp.asarray(vecs, jnp.float32), mask))
    sep = np.asarray(separation_deg(jnp.asarray(vecs), jnp.asarray(main)[None]))
    np.testing.assert_allclose(np.hypot(xy[:, 0], xy[:, 1]), sep, atol=2e-4)
    turned = Rotation.random(random_state=3).apply(vecs)
    xy2 = np.asarray(plane_coords(jnp.asarray(turned, jnp.float32), mask))
    # best 2-D rotation (Kabsch) from xy to xy2 is proper and explains it
    u, _, vt = np.linalg.svd(np.matmul(xy[1:].T, xy2[1:]))
    r = np.matmul(vt.T, u.T)
    assert np.linalg.det(r) > 0
    np.testing.assert_allclose(np.matmul(xy[1:], r.T), xy2[1:], atol=0.02 * np.max(sep) ** 3 / 6 + 2e-3)


def test_true_graphs_pass_and_most_others_fail_at_three_pixels(setup5):
    from jstarid.algorithms.sgm.graph import searchable_graphs
    cat, cam, db = setup5
    cfg = sgm.Config()
    rows = np.random.default_rng(4).choice(len(cat), 48, replace=False)
    scenes = js.simulate(jax.random.key(8), cat, cam, js.NoiseConfig(position_sigma_px=3.0),
                         capacity=64, boresight_ids=rows)
    g, usable = searchable_graphs(db, scenes, cfg)
    truth = np.asarray(scenes.truth)[np.arange(rows.size), g.main]
    row_of = np.argsort(db.main)  # catalog row → database row
    scene = np.nonzero(usable & (truth >= 0))[0]
    assert scene.size > 30
    n_i = g.n.astype(np.int32)
    keep_true = screen_pairs(db, g.plane, n_i, scene, row_of[truth[scene]], cfg)
    assert keep_true.all()
    other = np.random.default_rng(5).integers(0, len(db), scene.size * 20)
    scenes_rep = np.repeat(scene, 20)
    wrong = db.main[other] != truth[scenes_rep]
    keep = screen_pairs(db, g.plane, n_i, scenes_rep[wrong], other[wrong], cfg)
    assert keep.mean() < 0.1, keep.mean()


def test_search_with_the_screen_is_algorithm1_over_the_candidates_that_pass(setup5):
    """The screened search returns what the sequential Algorithm 1 returns when every candidate the
    screen rejects is struck out (test_sgm's replay)."""
    from test_sgm import _noisy_graphs, _sequential_algorithm1

    from jstarid.algorithms.sgm import search
    cat, cam, db = setup5
    cfg = sgm.Config(max_error_deg=0.1, matching=sgm.Matching(chunk_size=8), dw_max_deg=0.5,
                     finishing=Finishing.off())
    rows, _, g, usable = _noisy_graphs(setup5, cfg, n=5, seed=2, key=6)
    state = search.advance_search(db, g, search.start_search(db, g, usable, cfg), cfg)
    out = search.search_outcome(state, cfg, g.mask.shape[1])
    n_i = g.n.astype(np.int32)
    # nothing that fails the screen was matched
    s_idx, rank = np.nonzero(np.isfinite(state.err))
    assert s_idx.size and screen_pairs(db, g.plane, n_i, s_idx, state.cand[s_idx, rank], cfg).all()
    everything = np.arange(len(db))
    screened = 0
    for s in range(rows.size):
        keep = screen_pairs(db, g.plane, n_i, np.full(len(db), s), everything, cfg)
        screened += int(np.sum(~keep))
        best, err, level, _ = _sequential_algorithm1(db, g.adj[s], g.mask[s], float(g.w[s]), cfg,
                                                     exclude=set(np.nonzero(~keep)[0].tolist()))
        assert out.best[s] == best and out.level[s] == level, s
        if best >= 0:
            np.testing.assert_allclose(out.error[s], err, rtol=1e-4, atol=1e-6)
    assert screened > 0


def _image_graphs(setup5, *, sigma, key, seed, n):
    """``(db, config, scenes, graphs, usable)`` of n random main stars at position noise σ (px)."""
    from jstarid.algorithms.sgm.graph import searchable_graphs
    cat, cam, db = setup5
    cfg = sgm.Config()
    scenes = js.simulate(jax.random.key(key), cat, cam, js.NoiseConfig(position_sigma_px=sigma),
                         capacity=64, boresight_ids=np.random.default_rng(seed).choice(len(cat), n))
    return db, cfg, scenes, *searchable_graphs(db, scenes, cfg)


def test_screen_answers_do_not_depend_on_how_the_pairs_are_cut_into_calls(setup5):
    """Calls are cut by size (power-of-two chunks of each graph-size group): the pairs screened all
    at once, or in slices that cut differently, get the same answers."""
    db, cfg, _, g, usable = _image_graphs(setup5, sigma=2.0, key=9, seed=6, n=12)
    rng = np.random.default_rng(7)
    scene = rng.choice(np.nonzero(usable)[0], 900)
    rows = rng.integers(0, len(db), scene.size)
    n_i = g.n.astype(np.int32)
    whole = screen_pairs(db, g.plane, n_i, scene, rows, cfg)
    sliced = np.concatenate([screen_pairs(db, g.plane, n_i, scene[k:k + 137], rows[k:k + 137], cfg)
                             for k in range(0, scene.size, 137)])
    np.testing.assert_array_equal(whole, sliced)


def test_screen_pairs_equal_the_screen_of_each_pair_at_full_size(setup5):
    """The search's screen (neighbor coordinates and hypotheses computed once per graph, pairs cut
    to their padded size) answers as :func:`triangle_support` + :func:`screen_pass` on each pair's
    two whole graphs."""
    db, cfg, scenes, g, usable = _image_graphs(setup5, sigma=3.0, key=11, seed=8, n=16)
    rng = np.random.default_rng(9)
    scene = rng.choice(np.nonzero(usable)[0], 400)
    row_of = np.argsort(db.main)
    truth = np.asarray(scenes.truth)[scene, g.main[scene]]
    # a third of the pairs are the true graphs (they pass), the rest random (most fail)
    rows = np.where(np.arange(scene.size) % 3 == 0, row_of[np.maximum(truth, 0)],
                    rng.integers(0, len(db), scene.size))
    n_i = g.n.astype(np.int32)
    got = screen_pairs(db, g.plane, n_i, scene, rows, cfg)
    k = max(g.plane.shape[1], db.plane.shape[1])
    pad = lambda x: np.pad(x, ((0, 0), (0, k - x.shape[1]), (0, 0)))  # noqa: E731
    support = jax.vmap(lambda a, na, b, nb: _support(a, na, b, nb, tol=jnp.float32(cfg.screen.tol_deg),
                                                     partners=cfg.screen.partners,
                                                     hypotheses=cfg.screen.hypotheses))(
        jnp.asarray(pad(g.plane[scene])), jnp.asarray(n_i[scene]), jnp.asarray(pad(db.plane[rows])),
        jnp.asarray(db.n[rows]))
    want = screen_pass(support, n_i[scene], db.n[rows], fraction=cfg.screen.fraction,
                       min_matched=cfg.min_matched)
    np.testing.assert_array_equal(got, np.asarray(want))
    assert 0.2 < got.mean() < 0.6


def test_nearest_partners_are_the_m_smallest_gaps():
    """The window about the insertion point holds the m nearest radii of a brute-force ranking by
    (gap, radius), for lists with ties, absent neighbors (+inf) and fewer than m present; slots past
    the list come back at +inf."""
    rng = np.random.default_rng(10)
    m = 4
    for trial in range(300):
        q1 = int(rng.integers(4, 24))
        n_present = int(rng.integers(0, q1 + 1)) if trial % 3 else q1
        r = np.round(rng.uniform(0, 6, q1), 1 if trial % 2 else 6).astype(np.float32)  # ties when rounded
        r_sorted = np.sort(np.where(np.arange(q1) < n_present, r, np.inf)).astype(np.float32)
        r_i = np.round(rng.uniform(-0.5, 6.5, 23), 1 if trial % 2 else 6).astype(np.float32)
        gap, part = jax.jit(nearest_partners, static_argnums=2)(jnp.asarray(r_i), jnp.asarray(r_sorted), m)
        gap, part = np.asarray(gap), np.asarray(part)
        for k in range(r_i.size):
            brute = sorted((float(np.abs(r_i[k] - r_sorted[v])), float(r_sorted[v]))  # float32 gaps
                           for v in range(n_present))[:m]
            got = sorted((float(gap[k, s]), float(r_sorted[part[k, s]])) for s in range(m)
                         if np.isfinite(gap[k, s]))
            assert got == brute, (trial, k)  # of equal gaps, the smaller radius
            np.testing.assert_array_equal(gap[k][np.isfinite(gap[k])],
                                          np.abs(r_i[k] - r_sorted[part[k]])[np.isfinite(gap[k])])
