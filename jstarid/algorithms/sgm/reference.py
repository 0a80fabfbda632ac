"""The independent reference: a straightforward NumPy SGM, as a researcher would first write it.

Not part of the identification (:func:`~jstarid.algorithms.sgm.identify` never calls it): the
paper's Algorithm 1 alone, written apart from the JAX code, so that ``Config.paper()`` can be
checked against it id for id (tests/test_experiments.py) and ``experiments/bench_sgm.py`` can time
it as the baseline. It lives in the package, not under tests/, because that benchmark imports it
(experiment scripts import the package only, never the tests or each other).

One scene at a time, Python loops: main star nearest the image centre, neighbor graph and Prim MST in
NumPy, Algorithm 1's Δw loop over the sorted database weights, and for every candidate the affinity
matrix of eq. 2, its principal eigenvector by ``np.linalg.eig`` (as in the authors' code), greedy
binarization and the error of eq. 5. It reads the same database arrays (``adj``, ``n``, ``w``,
``members``) as :mod:`jstarid.algorithms.sgm` and gives, id for id, the names ``sgm.identify``
gives with ``Config.paper()``; no pruning, no verification. Host NumPy in float64 throughout.
"""

from __future__ import annotations

import numpy as np


def neighbor_graph(xy, valid, camera, radius_deg):
    """(detection indices, adjacency in deg) of the main star's neighbor graph, main star first."""
    idx = np.nonzero(valid)[0]
    d2 = (xy[idx, 0] - camera.cx) ** 2 + (xy[idx, 1] - camera.cy) ** 2
    main = idx[np.argmin(d2)]
    v = np.stack([(xy[:, 0] - camera.cx) / camera.f_px, (xy[:, 1] - camera.cy) / camera.f_px,
                  np.ones(xy.shape[0])], axis=1)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.matmul(v[idx], v[main]), -1, 1)))
    members = np.concatenate([[main], idx[(ang <= radius_deg) & (idx != main)]])
    u = v[members]
    adj = np.degrees(np.arccos(np.clip(np.matmul(u, u.T), -1, 1)))
    np.fill_diagonal(adj, 0.0)
    return members, adj


def mst_weight(adj):
    """Prim's algorithm, O(n²)."""
    n = adj.shape[0]
    if n < 2:
        return 0.0
    in_tree = np.zeros(n, bool)
    in_tree[0] = True
    dist = adj[0].copy()
    total = 0.0
    for _ in range(n - 1):
        cand = np.where(in_tree, np.inf, dist)
        k = int(np.argmin(cand))
        total += cand[k]
        in_tree[k] = True
        dist = np.minimum(dist, adj[k])
    return total


def spectral_match(a_i, a_j, c):
    """(match, error): eq. 2 affinity, eigenvector by np.linalg.eig, greedy binarization, eq. 5."""
    n, m = a_i.shape[0], a_j.shape[0]
    k = np.exp(-c * np.abs(a_i[:, None, :, None] - a_j[None, :, None, :]))
    same_i = np.eye(n, dtype=bool)[:, None, :, None]
    same_j = np.eye(m, dtype=bool)[None, :, None, :]
    k[same_i | same_j] = 0.0  # diagonal and conflicting pairs
    k = k.reshape(n * m, n * m)
    vals, vecs = np.linalg.eig(k)
    x = np.abs(np.real(vecs[:, np.argmax(np.real(vals))])).reshape(n, m)
    match = -np.ones(n, int)
    for _ in range(min(n, m)):
        i, j = np.unravel_index(np.argmax(x), x.shape)
        match[i] = j
        x[i, :] = -np.inf
        x[:, j] = -np.inf
    sel = np.nonzero(match >= 0)[0]
    d = a_i[np.ix_(sel, sel)] - a_j[np.ix_(match[sel], match[sel])]
    return match, np.sqrt(np.sum(d * d)) / len(sel)


def identify_scene(db, xy, valid, config):
    """Algorithm 1 for one scene → (N,) catalog ids (−1 unnamed), ok."""
    ids = -np.ones(xy.shape[0], int)
    if not np.any(valid):
        return ids, False
    members, a_i = neighbor_graph(xy, valid, db.camera, config.radius_deg)
    if members.size < config.min_stars:
        return ids, False
    w_i = mst_weight(a_i)
    tried, best, best_err, best_match = set(), -1, np.inf, None
    for level in range(config.n_levels):
        dw = config.dw0_deg + level * config.dw_step_deg
        lo, hi = np.searchsorted(db.w, w_i - dw), np.searchsorted(db.w, w_i + dw, side="right")
        for row in range(lo, hi):
            if row in tried:
                continue
            tried.add(row)
            n_j = int(db.n[row])
            if min(n_j, members.size) < config.min_matched:
                continue
            match, err = spectral_match(a_i, db.adj[row, :n_j, :n_j], config.c)
            if err < best_err:
                best, best_err, best_match = row, err, match
        if best_err <= config.max_error_deg:
            vert = np.nonzero(best_match >= 0)[0]
            ids[members[vert]] = db.members[best, best_match[vert]]
            return ids, True
    return ids, False
