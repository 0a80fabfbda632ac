"""SGM building blocks (eqs. 2–5, MST) against hand-checked values and plain NumPy references."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.sparse.csgraph import minimum_spanning_tree

from jstarid.algorithms.sgm.bound import edge_lower_bound, error_lower_bound, sorted_edges, sorted_rows
from jstarid.algorithms.sgm.config import Config
from jstarid.algorithms.sgm.graph import mst_weight
from jstarid.algorithms.sgm.matching import (
    affinity,
    affinity_eigenvector,
    greedy_binarize,
    matching_error,
    principal_eigenvector,
    spectral_match,
)
from jstarid.config_tree import with_fields

C = 1.74


def _random_graph(rng, n, pad):
    """A padded adjacency (deg) of n random points on a 12° patch, and its mask."""
    pts = rng.uniform(-6, 6, (n, 2))
    a = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    out = np.zeros((pad, pad), np.float32)
    out[:n, :n] = a
    return out, np.arange(pad) < n


def _np_affinity(a_i, n_i, a_j, n_j, c):
    """Eq. 2 written with loops over the valid vertices, index i·Q + j."""
    p, q = a_i.shape[0], a_j.shape[0]
    k = np.zeros((p * q, p * q))
    for i, j, kk, m in itertools.product(range(n_i), range(n_j), range(n_i), range(n_j)):
        if i != kk and j != m:
            k[i * q + j, kk * q + m] = np.exp(-c * abs(a_i[i, kk] - a_j[j, m]))
    return k


def _np_greedy(conf, n_i, n_j):
    conf = conf[:n_i, :n_j].astype(np.float64).copy()
    match = -np.ones(n_i, int)
    for _ in range(min(n_i, n_j)):
        i, j = np.unravel_index(np.argmax(conf), conf.shape)
        match[i] = j
        conf[i, :] = -np.inf
        conf[:, j] = -np.inf
    return match


def test_greedy_binarize_equals_the_one_pair_at_a_time_loop():
    """The round-based binarization gives the sequential greedy assignment, ties included (values
    drawn from a few levels so that rows and columns share maxima), for every shape and mask."""
    rng = np.random.default_rng(3)
    binarize = jax.jit(greedy_binarize)
    for trial in range(200):
        p, q = rng.choice([4, 8, 16], 2)
        n_i, n_j = rng.integers(1, p + 1), rng.integers(1, q + 1)
        levels = 3 if trial % 2 else 1000
        conf = rng.integers(0, levels, (p, q)).astype(np.float32) / levels
        match = np.asarray(binarize(jnp.asarray(conf), jnp.arange(p) < n_i, jnp.arange(q) < n_j))
        np.testing.assert_array_equal(match[:n_i], _np_greedy(conf, n_i, n_j))
        assert np.all(match[n_i:] == -1)


def test_tiny_graph_by_hand():
    # triangle with sides 1, 2, 1.5 (deg); G_J is the same triangle with vertices permuted (2, 0, 1)
    a_i = np.array([[0, 1, 2], [1, 0, 1.5], [2, 1.5, 0]], np.float32)
    perm = np.array([2, 0, 1])  # image vertex i ↔ database vertex perm[i]
    a_j = np.zeros_like(a_i)
    a_j[np.ix_(perm, perm)] = a_i
    m3 = np.ones(3, bool)
    k = np.asarray(affinity(jnp.asarray(a_i), m3, jnp.asarray(a_j), m3, C))
    assert k.shape == (9, 9)
    np.testing.assert_allclose(k, k.T)
    assert np.all(np.diag(k) == 0)
    # conflicting pairs: same image vertex, different database vertices (i = k, j ≠ m) and vice versa
    assert k[0 * 3 + 0, 0 * 3 + 1] == 0 and k[0 * 3 + 0, 1 * 3 + 0] == 0
    # edge (0,1) of G_I (1°) vs edge (2,0) of G_J (= image edge (0,1), 1°) → e^0 = 1
    np.testing.assert_allclose(k[0 * 3 + 2, 1 * 3 + 0], 1.0, rtol=1e-6)
    # edge (0,1) (1°) vs G_J edge (2,1) (= image edge (0,2), 2°) → e^{−1.74}
    np.testing.assert_allclose(k[0 * 3 + 2, 1 * 3 + 1], np.exp(-C), rtol=1e-6)
    match, err = spectral_match(jnp.asarray(a_i), m3, jnp.asarray(a_j), m3, c=C, n_iter=100)
    np.testing.assert_array_equal(np.asarray(match), perm)
    assert float(err) < 1e-6
    # lengthen one image side by 0.3°: eq. 5 gives sqrt(2·0.3²)/3 for the same correspondence
    a_n = a_i.copy()
    a_n[0, 1] = a_n[1, 0] = 1.3
    match, err = spectral_match(jnp.asarray(a_n), m3, jnp.asarray(a_j), m3, c=C, n_iter=100)
    np.testing.assert_array_equal(np.asarray(match), perm)
    np.testing.assert_allclose(float(err), np.sqrt(2 * 0.3**2) / 3, rtol=1e-5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_against_numpy_on_random_graphs(seed):
    rng = np.random.default_rng(seed)
    n_i, n_j, p, q = 5, 6, 8, 8
    a_i, m_i = _random_graph(rng, n_i, p)
    a_j, m_j = _random_graph(rng, n_j, q)
    k = np.asarray(affinity(jnp.asarray(a_i), m_i, jnp.asarray(a_j), m_j, C))
    k_ref = _np_affinity(a_i, n_i, a_j, n_j, C)
    np.testing.assert_allclose(k, k_ref, rtol=1e-5, atol=1e-7)
    # principal eigenvector: power iteration vs eigh (NumPy float64 and jnp.linalg.eigh)
    x = np.asarray(principal_eigenvector(jnp.asarray(k), 300))
    vals, vecs = np.linalg.eigh(k_ref)
    v = np.abs(vecs[:, -1])
    np.testing.assert_allclose(x, v, atol=2e-4)
    _, jvecs = jnp.linalg.eigh(jnp.asarray(k))
    np.testing.assert_allclose(x, np.abs(np.asarray(jvecs[:, -1])), atol=2e-4)
    # greedy binarization and eq. 5 against loops
    conf = v.reshape(p, q)
    match = np.asarray(greedy_binarize(jnp.asarray(conf, jnp.float32), m_i, m_j))
    ref = _np_greedy(conf, n_i, n_j)
    np.testing.assert_array_equal(match[:n_i], ref)
    assert np.all(match[n_i:] == -1)
    assert np.sum(match >= 0) == min(n_i, n_j)
    err = float(matching_error(jnp.asarray(a_i), jnp.asarray(a_j), jnp.asarray(match)))
    sel = np.nonzero(ref >= 0)[0]
    d = a_i[np.ix_(sel, sel)] - a_j[np.ix_(ref[sel], ref[sel])]
    np.testing.assert_allclose(err, np.sqrt(np.sum(d**2)) / min(n_i, n_j), rtol=1e-5)


@pytest.mark.parametrize("case", ["lost", "false"])
def test_noisy_subgraph_and_false_vertex(case):
    """G_I = a noisy, shuffled G_J with 3 stars lost, or with 1 false vertex added (n_I > n_J)."""
    rng = np.random.default_rng(7)
    pts = rng.uniform(-5, 5, (12, 2))
    keep = rng.permutation(12)[:9] if case == "lost" else rng.permutation(12)
    img = pts[keep] + rng.normal(0, 0.02, (keep.size, 2))
    if case == "false":
        img = np.concatenate([img, [[0.3, -4.1]]])
    n_i = img.shape[0]
    a_i = np.zeros((16, 16), np.float32)
    a_i[:n_i, :n_i] = np.linalg.norm(img[:, None] - img[None], axis=-1)
    a_j = np.zeros((16, 16), np.float32)
    a_j[:12, :12] = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    m_i, m_j = np.arange(16) < n_i, np.arange(16) < 12
    match, err = jax.jit(spectral_match, static_argnames=("c", "n_iter", "min_matched"))(
        jnp.asarray(a_i), m_i, jnp.asarray(a_j), m_j, c=C, n_iter=60, min_matched=3)
    match = np.asarray(match)
    np.testing.assert_array_equal(match[:keep.size], keep)
    assert np.all(match[keep.size:] == -1)  # the false vertex (and the padding) stay unmatched
    assert float(err) < 0.1


def test_power_iteration_converges_like_eigh_with_default_steps():
    """The default steps agree with eigh closely enough that greedy binarization is unchanged."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(-6, 6, (14, 2))
    a = np.linalg.norm(pts[:, None] - pts[None], axis=-1).astype(np.float32)
    a_n = a + rng.normal(0, 0.05, a.shape).astype(np.float32)
    a_n = (a_n + a_n.T) / 2
    np.fill_diagonal(a_n, 0)
    m = np.ones(14, bool)
    k = affinity(jnp.asarray(a_n), m, jnp.asarray(a), m, C)
    x = principal_eigenvector(k, Config().matching.power_iterations)
    _, vecs = jnp.linalg.eigh(k)
    v = jnp.abs(vecs[:, -1])
    np.testing.assert_allclose(np.asarray(x), np.asarray(v), atol=1e-3)
    b1 = greedy_binarize(x.reshape(14, 14), m, m)
    b2 = greedy_binarize(v.reshape(14, 14), m, m)
    np.testing.assert_array_equal(np.asarray(b1), np.asarray(b2))
    np.testing.assert_array_equal(np.asarray(b1), np.arange(14))


def test_min_matched_and_degenerate_graphs():
    a = jnp.zeros((4, 4))
    one = np.arange(4) < 1
    match, err = spectral_match(a, one, a, one, c=C, n_iter=5, min_matched=3)
    assert np.isinf(float(err))
    assert int(np.sum(np.asarray(match) >= 0)) == 1


@pytest.mark.parametrize("n", [1, 2, 5, 13])
def test_mst_weight_matches_scipy(n):
    rng = np.random.default_rng(n)
    a, m = _random_graph(rng, n, 16)
    w = float(jax.jit(mst_weight)(jnp.asarray(a), jnp.asarray(m)))
    ref = minimum_spanning_tree(a[:n, :n].astype(np.float64)).sum() if n > 1 else 0.0
    np.testing.assert_allclose(w, ref, rtol=1e-5)


def test_vertex_check_unnames_the_inconsistent_vertex():
    """A vertex paired with the wrong database vertex has large residuals and loses its name."""
    import dataclasses

    from jstarid.algorithms.sgm import Config
    from jstarid.algorithms.sgm.naming import check_vertices
    from jstarid.algorithms.sgm.search import SearchOutcome

    rng = np.random.default_rng(4)
    pts = rng.uniform(-5, 5, (10, 2))
    img = pts + rng.normal(0, 0.02, pts.shape)
    img[3] = [4.5, -4.5]  # vertex 3: a star that is not the database's vertex 3
    k = 16
    a_j = np.zeros((1, k, k), np.float32)
    a_j[0, :10, :10] = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    a_i = np.zeros((1, k, k), np.float32)
    a_i[0, :10, :10] = np.linalg.norm(img[:, None] - img[None], axis=-1)
    match = np.full((1, k), -1, np.int32)
    match[0, :10] = np.arange(10)
    one = np.zeros(1, np.int32)
    res = SearchOutcome(ok=np.array([True]), best=one, rank=one, match=match, error=np.zeros(1),
                        n_matched=one, n_pruned=one, n_rejected=one, level=one)
    cfg = dataclasses.replace(Config(), vertex_check_deg=0.2)
    m, ok = check_vertices(a_i, a_j, res, cfg)
    assert bool(ok[0])
    expect = match[0].copy()
    expect[3] = -1
    np.testing.assert_array_equal(m[0], expect)
    # too few consistent vertices left → the scene fails
    m, ok = check_vertices(a_i, a_j, res, dataclasses.replace(cfg, min_matched=10))
    assert not bool(ok[0]) and np.all(m == -1)
    # … and through the naming: the unnamed vertex's detection gets no name, the others theirs
    import types

    from jstarid.algorithms.sgm.graph import ImageGraph
    from jstarid.algorithms.sgm.naming import names_from_match
    # the detection of each vertex: 13, 12, …, 4 (a scene of 14 detections)
    members = np.where(np.arange(k) < 10, np.arange(k)[::-1] - 2, -1).astype(np.int32)[None]
    db = types.SimpleNamespace(adj=a_j, members=(100 + np.arange(k, dtype=np.int32))[None])
    g = ImageGraph(members=members, mask=members >= 0, adj=a_i, n=np.array([10]), w=None, overflow=None,
                   main=members[:, 0])
    scenes = types.SimpleNamespace(valid=np.ones((1, 14), bool))
    plain = with_fields(cfg, {"leftover_tol_deg": None, "verify": False})
    result, _ = names_from_match(db, scenes, g, res, plain)
    want = np.full(14, -1)
    want[members[0, :10]] = 100 + np.arange(10)
    want[members[0, 3]] = -1
    np.testing.assert_array_equal(np.asarray(result.ids)[0], want)
    assert bool(np.asarray(result.ok)[0])


def test_power_iteration_early_stop_agrees_with_fixed_steps():
    rng = np.random.default_rng(4)
    a, m = _random_graph(rng, 9, 12)
    b = a + np.where(a > 0, rng.normal(0, 0.03, a.shape), 0).astype(np.float32)
    b = (b + b.T) / 2
    k = affinity(jnp.asarray(a), m, jnp.asarray(b), m, C)
    x_fixed = principal_eigenvector(k, 300)
    x_tol = jax.jit(principal_eigenvector, static_argnums=1)(k, 300, 1e-7)
    np.testing.assert_allclose(np.asarray(x_tol), np.asarray(x_fixed), atol=1e-5)


@pytest.mark.parametrize("n_i, p, n_j, q, tol", [(9, 12, 9, 12, 0.0), (11, 16, 7, 8, 1e-4),
                                                 (14, 16, 20, 24, 1e-4), (3, 8, 12, 16, 0.0)])
def test_matrix_free_eigenvector_equals_the_written_out_one(n_i, p, n_j, q, tol):
    """spectral_match's power steps (entries recomputed in each step) against principal_eigenvector
    of the stored affinity matrix and against eigh's Perron vector."""
    rng = np.random.default_rng(n_i * 100 + q)
    a, ma = _random_graph(rng, n_i, p)
    b, mb = _random_graph(rng, n_j, q)
    if n_i == n_j:  # a noisy copy: a clear leading eigenvalue
        b = a + np.where(a > 0, rng.normal(0, 0.03, a.shape), 0).astype(np.float32)
        b = (b + b.T) / 2
    k = affinity(jnp.asarray(a), ma, jnp.asarray(b), mb, C)
    stored = principal_eigenvector(k, 300, tol).reshape(p, q)
    free = jax.jit(affinity_eigenvector, static_argnums=(5, 6))(jnp.asarray(a), ma, jnp.asarray(b), mb,
                                                                 C, 300, tol)
    np.testing.assert_allclose(np.asarray(free), np.asarray(stored), atol=2e-6)
    np.testing.assert_array_equal(np.asarray(free)[~ma], 0.0)  # padding rows stay zero
    vals, vecs = np.linalg.eigh(np.asarray(k, np.float64))
    gap = vals[-1] - max(vals[-2], -vals[0])  # power steps converge at the rate of the next |λ|
    if tol == 0 and gap > 0.05 * vals[-1]:
        np.testing.assert_allclose(np.asarray(free).reshape(-1), np.abs(vecs[:, -1]), atol=1e-4)


def _brute_force_min_error(a_i, n_i, a_j, n_j):
    """min over every one-to-one correspondence of min(n_I, n_J) pairs of eq. 5 (deg)."""
    small, large = (a_i[:n_i, :n_i], a_j[:n_j, :n_j]) if n_i <= n_j else (a_j[:n_j, :n_j], a_i[:n_i, :n_i])
    m = small.shape[0]
    best = np.inf
    for perm in itertools.permutations(range(large.shape[0]), m):
        p = np.array(perm)
        d = small - large[np.ix_(p, p)]
        best = min(best, np.sqrt(np.sum(d * d)) / m)
    return best


def test_error_lower_bound_never_exceeds_the_best_correspondence():
    """Both pruning bounds are below eq. 5 for every correspondence (brute force); the exact one is
    tight for a copy, the first-stage edge bound looser but not vacuous."""
    rng = np.random.default_rng(11)
    bound = jax.jit(error_lower_bound, static_argnames="max_skip")
    edge_bound = jax.jit(edge_lower_bound)
    ratios, edge_ratios = [], []
    for trial in range(60):
        n_i, n_j = (int(x) for x in rng.integers(2, 7, 2))
        a_i, m_i = _random_graph(rng, n_i, 8)
        if trial % 2:  # unrelated graph
            a_j, m_j = _random_graph(rng, n_j, 8)
        else:  # the same points (plus others, or fewer) with noise
            pts = rng.uniform(-6, 6, (8, 2))
            a_i = np.zeros((8, 8), np.float32)
            a_i[:n_i, :n_i] = np.linalg.norm(pts[:n_i, None] - pts[None, :n_i], axis=-1)
            q = pts[:n_j] + rng.normal(0, 0.05, (n_j, 2))
            a_j = np.zeros((8, 8), np.float32)
            a_j[:n_j, :n_j] = np.linalg.norm(q[:, None] - q[None], axis=-1)
            m_j = np.arange(8) < n_j
        lb = float(bound(sorted_rows(jnp.asarray(a_i), m_i), n_i, sorted_rows(jnp.asarray(a_j), m_j),
                         n_j, max_skip=6))
        elb = float(edge_bound(sorted_edges(jnp.asarray(a_i), m_i), n_i,
                               sorted_edges(jnp.asarray(a_j), m_j), n_j))
        best = _brute_force_min_error(a_i, n_i, a_j, n_j)
        assert lb <= best * (1 + 1e-5) + 1e-6, (trial, lb, best)
        assert elb <= best * (1 + 1e-5) + 1e-6, (trial, elb, best)
        ratios.append(lb / best if best > 0 else 1.0)
        edge_ratios.append(elb / best if best > 0 else 1.0)
    assert max(ratios) > 0.99  # not a vacuous bound: tight for some pairs
    assert np.median(edge_ratios[1::2]) > 0.5  # unrelated graphs: looser, but not vacuous
    # identical graphs → 0; more vertex difference than max_skip → 0 (no pruning)
    a, m = _random_graph(rng, 6, 8)
    r = sorted_rows(jnp.asarray(a), m)
    assert float(bound(r, 6, r, 6, max_skip=2)) < 1e-6
    b, mb = _random_graph(rng, 2, 8)
    assert float(bound(r, 6, sorted_rows(jnp.asarray(b), mb), 2, max_skip=2)) == 0.0


def test_row_cost_is_the_cheapest_monotone_assignment():
    """The row bound's programme (``bound._row_cost``) against brute force: every short row of
    ``n_short`` entries (fewer than the table's R columns, +inf padded) placed in order into each long
    row, skipping at most ``max_skip`` long entries before each one."""
    from jstarid.algorithms.sgm.bound import _row_cost
    rng = np.random.default_rng(12)
    for n_short, s, max_skip in [(3, 2, 2), (4, 1, 3), (2, 3, 3), (5, 0, 2), (3, 3, 2)]:
        r = 7  # table width: entries past n_short (short) / n_short + s (long) are +inf padding
        short = np.full((3, r), np.inf, np.float32)
        long = np.full((4, r), np.inf, np.float32)
        short[:, :n_short] = np.sort(rng.uniform(0, 5, (3, n_short)), axis=1)
        long[:, :n_short + s] = np.sort(rng.uniform(0, 5, (4, n_short + s)), axis=1)
        got = np.asarray(_row_cost(jnp.asarray(short), jnp.asarray(long), n_short, max_skip))
        want = np.full((3, 4), np.inf)
        for i, j in itertools.product(range(3), range(4)):
            for pos in itertools.combinations(range(n_short + s), n_short):
                if all(p - t <= max_skip for t, p in enumerate(pos)):
                    cost = np.sum((short[i, :n_short] - long[j, list(pos)]) ** 2)
                    want[i, j] = min(want[i, j], cost)
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
