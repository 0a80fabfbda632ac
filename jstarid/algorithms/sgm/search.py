"""Rough search (eq. 1, k-vector) and the dynamic Δw search of Algorithm 1, batched.

Algorithm 1 (You et al. 2022) for one image graph with MST weight w_I visits Δw_l = Δw₀ + l·h_Δw,
l = 0, 1, … while Δw_l ≤ Δw_max; at each level it matches every database graph J with
``|w_J − w_I| ≤ Δw_l`` that was not matched at an earlier level, takes J* = argmin δ (eq. 6) over
everything matched so far, and stops at the first level where δ_{I,J*} ≤ ε_δ; if no level succeeds,
the scene fails.

Batched form used here. Sort the candidates of a scene by d_J = |w_J − w_I| (rank 0, 1, …); the
level at which J is first searched is ``l(J) = ⌈(d_J − Δw₀)/h⌉⁺``, non-decreasing in rank, so the
set searched up to level l is a prefix of this order. Candidates are matched in fixed-size chunks
of ranks (all scenes of the batch in lock-step, each with its own ``done`` flag). Let t be the first
rank with δ ≤ ε_δ and l* = l(t): Algorithm 1 stops at level l* and returns the argmin of δ over the
prefix ``{J : l(J) ≤ l*}``; the chunked loop keeps matching until it has covered that prefix (and
ignores ranks beyond it inside the last chunk), then returns the argmin over the same prefix. Ranks
before t all have δ > ε_δ, so every earlier level fails in both. With no success the whole window
``d_J ≤ Δw_last`` is covered and the scene fails in both. Hence the outcome equals the sequential
loop (up to ties in δ); only the order of work differs. Scenes that are done leave the batch, so a
batch costs about as much as its hardest scenes.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.sgm.config import Config
from jstarid.algorithms.sgm.matching import spectral_match
from jstarid.geometry import range_search

__all__ = ["candidate_windows", "order_candidates", "dynamic_search"]


def _bucket(x: int, m: int) -> int:
    return max(m, int(math.ceil(x / m) * m))


def _pow2(x: int) -> int:
    return 1 << max(0, int(math.ceil(math.log2(max(x, 1)))))


@jax.jit
def candidate_windows(kvector, w_i, dw_last_deg):
    """Rough search (eq. 1) at the widest Δw: ``(start, stop)`` (B,) int32 rows of the database."""
    return jax.vmap(range_search, in_axes=(None, 0, 0))(kvector, w_i - dw_last_deg,
                                                         w_i + dw_last_deg)


@functools.partial(jax.jit, static_argnames=("width", "dw0", "step", "n_levels"))
def order_candidates(w_db, start, stop, w_i, *, width: int, dw0: float, step: float, n_levels: int):
    """Candidates of each scene ordered by |w_J − w_I|, with the Δw level where each enters.

    Args:
        w_db: (D,) ascending database w (deg).
        start, stop: (B,) int32 window of each scene (from :func:`candidate_windows`).
        w_i: (B,) image MST weights (deg).
        width: static window capacity W ≥ max(stop − start).
        dw0, step, n_levels: Δw₀, h_Δw (deg) and the number of levels (Config).

    Returns:
        ``(cand, level)``: (B, W) int32 database rows by rank (−1 past the window), (B, W) int32
        level l(J) of each (n_levels past the window).
    """
    idx = start[:, None] + jnp.arange(width)[None, :]
    inwin = idx < stop[:, None]
    d = jnp.abs(w_db[jnp.clip(idx, 0, w_db.shape[0] - 1)] - w_i[:, None])
    key = jnp.where(inwin, d, jnp.inf)
    perm = jnp.argsort(key, axis=1, stable=True)
    d_sorted = jnp.take_along_axis(key, perm, axis=1)
    cand = jnp.where(jnp.isfinite(d_sorted), jnp.take_along_axis(idx, perm, axis=1), -1)
    level = jnp.ceil((d_sorted - dw0) / step - 1e-4)
    level = jnp.where(jnp.isfinite(d_sorted), jnp.clip(level, 0, n_levels - 1), n_levels)
    return cand.astype(jnp.int32), level.astype(jnp.int32)


@functools.partial(jax.jit, static_argnames=("p", "q", "c", "n_iter", "min_matched"))
def _match_chunk(a_i, mask_i, cand, db_adj, db_n, *, p, q, c, n_iter, min_matched):
    """Spectral matching of S image graphs against C candidates each → (S, C, p) match, (S, C) δ."""
    safe = jnp.clip(cand, 0, db_adj.shape[0] - 1)
    a_j = db_adj[safe][:, :, :q, :q]
    mask_j = (jnp.arange(q)[None, None, :] < db_n[safe][:, :, None]) & (cand >= 0)[:, :, None]
    match_one = functools.partial(spectral_match, c=c, n_iter=n_iter, min_matched=min_matched)
    over_cand = jax.vmap(match_one, in_axes=(None, None, 0, 0))
    match, err = jax.vmap(over_cand)(a_i[:, :p, :p], mask_i[:, :p], a_j, mask_j)
    return match, jnp.where(cand >= 0, err, jnp.inf)


def _groups(order, n_i, n_j_max, config: Config, chunk: int):
    """Split scenes (sorted by n_I) into sub-batches whose affinity matrices fit the budget."""
    budget = config.memory_budget_mb * 2**20
    groups, cur, p, q = [], [], 0, 0
    for s in order:
        p2 = max(p, _bucket(int(n_i[s]), config.size_bucket))
        q2 = max(q, _bucket(int(n_j_max[s]), config.size_bucket))
        need = _pow2(len(cur) + 1) * chunk * (p2 * q2) ** 2 * 4 * 3  # K, |ΔA| and exp temporaries
        if cur and need > budget:
            groups.append((cur, p, q))
            cur, p2, q2 = [], _bucket(int(n_i[s]), config.size_bucket), _bucket(
                int(n_j_max[s]), config.size_bucket)
        cur.append(s)
        p, q = p2, q2
    if cur:
        groups.append((cur, p, q))
    return groups


def dynamic_search(db, graphs: dict, usable: np.ndarray, config: Config) -> dict:
    """Algorithm 1 for a batch of image graphs (host loop over candidate chunks).

    Args:
        db: :class:`~jstarid.algorithms.sgm.database.Database`.
        graphs: per-scene image graphs as NumPy arrays: ``adj`` (B, K, K) deg, ``mask`` (B, K),
            ``n`` (B,), ``w`` (B,) deg.
        usable: (B,) bool scenes to search (the others fail).
        config: :class:`Config`.

    Returns:
        dict of NumPy arrays: ``ok`` (B,) bool, ``best`` (B,) int32 database row of J* (−1),
        ``match`` (B, K) int32 database vertex of each image vertex (−1), ``error`` (B,) δ_{I,J*}
        (deg, inf when nothing was matched), ``n_matched_graphs`` (B,) candidates matched,
        ``level`` (B,) index of the Δw level that succeeded (−1).
    """
    b, k = graphs["mask"].shape
    chunk = int(config.chunk_size)
    n_levels = config.n_levels
    w_i = jnp.asarray(graphs["w"], jnp.float32)
    start, stop = candidate_windows(db.kvector, w_i, jnp.float32(config.dw_last_deg))
    count = np.where(usable, np.asarray(stop) - np.asarray(start), 0)
    width = _pow2(max(int(count.max(initial=0)), chunk))
    cand_all, level_all = order_candidates(
        jnp.asarray(db.w), start, stop, w_i, width=width, dw0=float(config.dw0_deg),
        step=float(config.dw_step_deg), n_levels=n_levels)
    cand_all, level_all = np.asarray(cand_all), np.asarray(level_all)
    n_j_all = np.where(cand_all >= 0, db.n[np.clip(cand_all, 0, len(db) - 1)], 0)

    best_err = np.full(b, np.inf, np.float32)
    best = np.full(b, -1, np.int32)
    best_match = np.full((b, k), -1, np.int32)
    lstar = np.full(b, n_levels, np.int32)  # level of the first success; n_levels = none yet
    n_done = np.zeros(b, np.int32)
    done = ~usable | (count == 0)
    adj_i, mask_i = graphs["adj"], graphs["mask"]
    db_adj, db_n = db.device_adj, jnp.asarray(db.n)
    r0 = 0
    while not np.all(done) and r0 < width:
        act = np.nonzero(~done)[0]
        cand = cand_all[act, r0:r0 + chunk]
        lev = level_all[act, r0:r0 + chunk]
        cand = np.where(lev <= lstar[act, None], cand, -1)
        nj = np.where(cand >= 0, n_j_all[act, r0:r0 + chunk], 0).max(axis=1)
        err = np.full(cand.shape, np.inf, np.float32)
        match = np.full(cand.shape + (k,), -1, np.int32)
        order = np.argsort(graphs["n"][act], kind="stable")
        for members, p, q in _groups(order, graphs["n"][act], nj, config, cand.shape[1]):
            sel = np.asarray(members)
            pad = _pow2(sel.size) - sel.size
            rows = act[np.concatenate([sel, np.repeat(sel[:1], pad)])]
            c_in = np.concatenate([cand[sel], np.full((pad, cand.shape[1]), -1, np.int32)])
            m, e = _match_chunk(jnp.asarray(adj_i[rows]), jnp.asarray(mask_i[rows]),
                                jnp.asarray(c_in), db_adj, db_n, p=p, q=q, c=float(config.c),
                                n_iter=int(config.power_iterations),
                                min_matched=int(config.min_matched))
            err[sel] = np.asarray(e)[:sel.size]
            match[sel, :, :p] = np.asarray(m)[:sel.size]
        n_done[act] += np.sum(cand >= 0, axis=1)
        # first success fixes l*; ranks beyond the l* prefix do not take part (Algorithm 1, line 10)
        succ = err <= config.max_error_deg
        first = np.where(succ.any(axis=1), lev[np.arange(act.size), np.argmax(succ, axis=1)],
                         n_levels)
        lstar[act] = np.minimum(lstar[act], first)
        err = np.where(lev <= lstar[act, None], err, np.inf)
        j = np.argmin(err, axis=1)
        e_best = err[np.arange(act.size), j]
        better = e_best < best_err[act]
        upd = act[better]
        best_err[upd] = e_best[better]
        best[upd] = cand[better, j[better]]
        best_match[upd] = match[better, j[better]]
        r0 += chunk
        nxt = level_all[act, r0] if r0 < width else np.full(act.size, n_levels)
        done[act] = (r0 >= count[act]) | (nxt > lstar[act])
    ok = usable & (best_err <= config.max_error_deg)
    return {"ok": ok, "best": np.where(ok, best, -1), "match": np.where(ok[:, None], best_match, -1),
            "error": best_err, "n_matched_graphs": n_done,
            "level": np.where(ok, lstar, -1).astype(np.int32)}
