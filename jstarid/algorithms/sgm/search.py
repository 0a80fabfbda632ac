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

from jstarid.algorithms.sgm.bound import error_lower_bound, sorted_rows
from jstarid.algorithms.sgm.config import Config
from jstarid.algorithms.sgm.matching import spectral_match
from jstarid.geometry import range_search
from jstarid.sweep import map_batch, replicate

__all__ = ["candidate_windows", "order_candidates", "prune_mask", "dynamic_search", "run_pairs",
           "database_tables", "bucket_up", "next_pow2"]


def _bucket(x: int, m: int) -> int:
    return max(m, int(math.ceil(x / m) * m))


def next_pow2(x: int) -> int:
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


@functools.partial(jax.jit, static_argnames=("p", "q", "n_iter", "tol", "min_matched"))
def _match_pairs(a_i, n_i, cand, db_adj, db_n, c, *, p, q, n_iter, tol, min_matched):
    """Spectral matching of N (image graph, database graph) pairs → (N, p) match, (N,) δ (deg).

    The pairs run one after the other (``lax.map``), not side by side (``vmap``): each power step
    reads the pair's whole (p·q)² affinity matrix, which stays in cache for all its steps when only
    one pair is live, while a vmapped batch streams every matrix from memory at every step (measured
    ≈ 2× faster for p = q = 16–48). It also lets ``Config.power_tol`` stop each pair on its own, and
    padding pairs (``cand`` = −1, which fill a call up to its compiled size) are skipped by
    ``lax.cond`` (match −1, δ = inf) instead of being matched. ``c`` (eq. 2) is a traced scalar: a
    sweep over c reuses the compiled kernels.
    """
    live = cand >= 0
    cand = jnp.maximum(cand, 0)
    mask_i = jnp.arange(p)[None, :] < n_i[:, None]

    def match_one(a_i1, mask_i1, cand1):
        # the database graph is gathered inside the live branch: padding pairs cost no copy
        a_j = jax.lax.dynamic_slice(db_adj[cand1], (0, 0), (q, q))
        mask_j = jnp.arange(q) < db_n[cand1]
        return spectral_match(a_i1, mask_i1, a_j, mask_j, c=c, n_iter=n_iter,
                              min_matched=min_matched, tol=tol)

    return skip_padding(match_one, live, (a_i, mask_i, cand),
                        (jnp.full((p,), -1, jnp.int32), jnp.asarray(jnp.inf, jnp.float32)))


def skip_padding(fn, live, args, dead):
    """``lax.map`` of ``fn(*args_n)`` over pairs n, returning ``dead`` for pairs where ``live`` is False.

    On CPU ``lax.cond`` inside a sequential map runs one branch only, so padding costs nothing.
    """
    def one(xs):
        return jax.lax.cond(xs[0], lambda a: fn(*a), lambda a: dead, xs[1:])

    return jax.lax.map(one, (live, *args))


@functools.partial(jax.jit, static_argnames=("r", "max_skip"))
def _bound_pairs(a_i, n_i, cand, db_adj, db_n, *, r, max_skip):
    """:func:`~.bound.error_lower_bound` of N (image graph, database graph) pairs → (N,) (deg).

    Vectorized over groups of 16 pairs (``vmap``); groups made only of padding pairs (``cand`` = −1)
    are skipped (bound 0).
    """
    live = cand >= 0
    cand = jnp.maximum(cand, 0)
    n = cand.shape[0]
    group = math.gcd(n, 16)
    bound = functools.partial(error_lower_bound, max_skip=max_skip)

    def one_group(a_g, ni_g, cand_g):
        a_j = db_adj[cand_g][:, :r, :r]
        n_j = db_n[cand_g]
        rows_i = sorted_rows(a_g, jnp.arange(r)[None, :] < ni_g[:, None])
        rows_j = sorted_rows(a_j, jnp.arange(r)[None, :] < n_j[:, None])
        return jax.vmap(bound)(rows_i, ni_g, rows_j, n_j)

    def split(x):
        return x.reshape((n // group, group) + x.shape[1:])

    out = skip_padding(one_group, jnp.any(split(live), axis=1), (split(a_i), split(n_i), split(cand)),
                       jnp.zeros((group,), jnp.float32))
    return out.reshape(n)


MIN_CALL_PAIRS = 64  # smallest compiled pair count of a kernel call


def _batches(n_pairs: int, per_pair_bytes: int, budget_bytes: int):
    """Slices of ≤ the budget, each padded to a power of two ≥ :data:`MIN_CALL_PAIRS`.

    Power-of-two sizes bound the number of compilations per kernel. The floor of 64 (not 16) merges
    the small sizes that most blocks of a small batch need into one compilation (≈ 1.5 s each on 2
    cores): ``bench_sgm.py --batch 128`` at σ = 0 / 1 / 3 px took 29 / 21 / 47 s for its first call
    instead of 61 / 30 / 66 s, at the same steady rate within the machine's run-to-run spread. The
    padding pairs cost next to nothing: the kernels skip them (:func:`skip_padding`), gathers included.
    """
    cap = max(MIN_CALL_PAIRS,
              1 << int(math.floor(math.log2(max(budget_bytes // max(per_pair_bytes, 1), 16)))))
    for lo in range(0, n_pairs, cap):
        hi = min(lo + cap, n_pairs)
        yield lo, hi, max(MIN_CALL_PAIRS, next_pow2(hi - lo))


def run_pairs(kernel, key_sizes, adj_i, n_i, scene, cand, per_pair_bytes, budget, size_names, out_tails,
              tables, **static):
    """Run a pair kernel over flat (scene, candidate) pairs grouped by padded graph size.

    Each call's pairs are split over every device (:func:`jstarid.sweep.map_batch`): on a CPU with
    ``--xla_force_host_platform_device_count=n`` the n slices run on n cores at once, where one device
    leaves the second core of a 2-core machine mostly idle (a pair's small matrix products do not
    spread over threads: one core measured only 12 % slower than two).

    Args:
        kernel: :func:`_match_pairs` or :func:`_bound_pairs`; called as
            ``kernel(a_i, n_i, cand, *tables, **static, **sizes)`` with the image adjacency sliced to
            the group's size; calls are filled up to a power of two with padding pairs whose
            ``cand`` is −1 (the kernel must skip them or give them a harmless value).
        key_sizes: (N, k) int static sizes of each pair (e.g. (p, q) or (r,)); pairs are grouped by row.
        adj_i: (B, K, K) image adjacencies (NumPy). n_i: (B,) image vertex counts.
        scene, cand: (N,) int scene row and database row of each pair.
        per_pair_bytes: function of the sizes → bytes one pair needs inside the kernel.
        budget: bytes per call. size_names: the kernel's static keyword for each column of
            ``key_sizes``.
        out_tails: trailing shape of each kernel output in the result (a per-vertex axis, which the
            kernel returns at its group's size, is given as K and padded with −1).
        tables: tuple of arrays every pair reads (database tables), ideally already on every device
            (:func:`database_tables`).
        **static: the kernel's other (hashable) keyword arguments.

    Returns:
        List of the kernel outputs in pair order (NumPy arrays of shape (N,) + tail).
    """
    outs = None
    n_dev = jax.device_count()
    groups = {}
    for idx, key in enumerate(map(tuple, key_sizes)):
        groups.setdefault(key, []).append(idx)
    for sizes, members in groups.items():
        members = np.asarray(members)
        for lo, hi, padded in _batches(members.size, per_pair_bytes(*sizes), budget):
            sel = members[lo:hi]
            # padding pairs repeat the first pair's scene with candidate −1 (kernels skip them); the
            # real pairs are dealt round-robin to the devices' equal slices so each gets its share
            slot = _spread(sel.size, padded, n_dev)
            fill = np.full(padded, sel[0])
            fill[slot] = sel
            cand_fill = np.full(padded, -1, np.int64)
            cand_fill[slot] = cand[sel]
            batched = (jnp.asarray(adj_i[scene[fill], :sizes[0], :sizes[0]]),
                       jnp.asarray(n_i[scene[fill]]), jnp.asarray(cand_fill))
            res = map_batch(kernel, batched, tuple(tables),
                            static={**static, **dict(zip(size_names, sizes, strict=True))})
            res = res if isinstance(res, tuple) else (res,)
            if outs is None:
                outs = [np.full((scene.size,) + tuple(t), -1, np.asarray(r).dtype)
                        for r, t in zip(res, out_tails, strict=True)]
            for o, r in zip(outs, res, strict=True):
                r = np.asarray(r)[slot]
                o[(sel,) + tuple(slice(0, d) for d in r.shape[1:])] = r
    return outs


def _spread(n: int, padded: int, n_dev: int) -> np.ndarray:
    """Slots (n,) in a call of ``padded`` pairs for n real pairs: k-th pair → device k mod n_dev."""
    if n_dev <= 1 or padded % n_dev:
        return np.arange(n)
    k = np.arange(n)
    return (k % n_dev) * (padded // n_dev) + k // n_dev


def database_tables(db):
    """``(adj, n)`` of the database as device arrays on every device (placed once per database)."""
    cached = db.__dict__.get("_tables")
    if cached is None:
        cached = replicate((db.device_adj, jnp.asarray(db.n)))
        object.__setattr__(db, "_tables", cached)
    return cached


def prune_mask(db, adj_i, n_i, scene, rows, config: Config, max_error_deg: float) -> np.ndarray:
    """Which (scene, candidate) pairs survive the exact bound of :mod:`.bound`.

    Args:
        db: the database. adj_i: (B, K, K) image adjacencies (deg). n_i: (B,) image vertex counts.
        scene, rows: (N,) scene and database row of each pair.
        config: :class:`Config` (``prune_max_skip``, ``size_bucket``, ``memory_budget_mb``).
        max_error_deg: ε; a pair is dropped when its bound on δ exceeds it (with a small margin
            for the float32 rounding of the two computations).

    Returns:
        (N,) bool, True for the pairs to match (pairs differing by more than ``prune_max_skip``
        vertices are always kept).
    """
    n_j = db.n[rows]
    s_diff = np.abs(n_i[scene] - n_j)
    bounded = np.nonzero(s_diff <= config.prune_max_skip)[0]
    lb = np.zeros(rows.size, np.float32)
    if bounded.size:
        # grouped by padded size and by skip count (0, 1, 2, 4, 8, …: the programme's width)
        r = np.maximum(bucket_up(n_i[scene[bounded]], config.size_bucket),
                       bucket_up(n_j[bounded], config.size_bucket))
        sk = np.where(s_diff[bounded] == 0, 0,
                      1 << np.ceil(np.log2(np.maximum(s_diff[bounded], 1))).astype(np.int64))
        (lb[bounded],) = run_pairs(
            _bound_pairs, np.stack([r, sk], axis=1), adj_i, n_i, scene[bounded], rows[bounded],
            lambda r_, s_: r_ * r_ * (r_ - 1 + 3 * (s_ + 1)) * 4, config.memory_budget_mb * 2**20,
            ("r", "max_skip"), [()], database_tables(db))
    return ~(lb > max_error_deg * (1 + 1e-4) + 1e-5)


def dynamic_search(db, graphs: dict, usable: np.ndarray, config: Config) -> dict:
    """Algorithm 1 for a batch of image graphs (host loop over blocks of candidate ranks).

    Each step takes the next block of ranks of every unfinished scene (16 ranks, then twice as many
    at every step up to 512: most scenes finish within their first few dozen candidates), drops the
    candidates whose :mod:`.bound` proves δ > ε_δ (``Config.prune``; exact, see that module), and
    runs the spectral matching on the rest as flat (scene, candidate) pairs grouped by padded graph
    sizes.

    Args:
        db: :class:`~jstarid.algorithms.sgm.database.Database`.
        graphs: per-scene image graphs as NumPy arrays: ``adj`` (B, K, K) deg, ``mask`` (B, K),
            ``n`` (B,), ``w`` (B,) deg.
        usable: (B,) bool scenes to search (the others fail).
        config: :class:`Config`.

    Returns:
        dict of NumPy arrays: ``ok`` (B,) bool, ``best`` (B,) int32 database row of J* (−1),
        ``match`` (B, K) int32 database vertex of each image vertex (−1), ``error`` (B,) δ_{I,J*}
        (deg; inf when nothing was matched — with pruning, also when every candidate was pruned),
        ``n_matched_graphs`` (B,) candidates whose spectral matching ran, ``n_pruned`` (B,)
        candidates the bound removed, ``level`` (B,) index of the Δw level that succeeded (−1).
    """
    b, k = graphs["mask"].shape
    n_levels = config.n_levels
    w_i = jnp.asarray(graphs["w"], jnp.float32)
    start, stop = candidate_windows(db.kvector, w_i, jnp.float32(config.dw_last_deg))
    count = np.where(usable, np.asarray(stop) - np.asarray(start), 0)
    block = int(config.chunk_size)
    width = next_pow2(max(int(count.max(initial=0)), block))
    cand_all, level_all = order_candidates(
        jnp.asarray(db.w), start, stop, w_i, width=width, dw0=float(config.dw0_deg),
        step=float(config.dw_step_deg), n_levels=n_levels)
    cand_all, level_all = np.asarray(cand_all), np.asarray(level_all)

    best_err = np.full(b, np.inf, np.float32)
    best = np.full(b, -1, np.int32)
    best_match = np.full((b, k), -1, np.int32)
    lstar = np.full(b, n_levels, np.int32)  # level of the first success; n_levels = none yet
    n_done = np.zeros(b, np.int32)
    n_pruned = np.zeros(b, np.int32)
    done = ~usable | (count == 0)
    adj_i, n_i = graphs["adj"], graphs["n"].astype(np.int32)
    budget = config.memory_budget_mb * 2**20
    prune_at = config.max_error_deg
    r0 = 0
    while not np.all(done) and r0 < width:
        act = np.nonzero(~done)[0]
        cand = cand_all[act, r0:r0 + block]
        lev = level_all[act, r0:r0 + block]
        cand = np.where(lev <= lstar[act, None], cand, -1)
        s_idx, c_idx = np.nonzero(cand >= 0)
        scene, rows = act[s_idx], cand[s_idx, c_idx]
        n_j = db.n[rows]
        if config.prune and rows.size:
            keep = prune_mask(db, adj_i, n_i, scene, rows, config, prune_at)
            np.add.at(n_pruned, scene[~keep], 1)
            s_idx, c_idx, scene, rows, n_j = (x[keep] for x in (s_idx, c_idx, scene, rows, n_j))
        np.add.at(n_done, scene, 1)
        err = np.full(cand.shape, np.inf, np.float32)
        pair_of = np.full(cand.shape, -1, np.int64)
        if rows.size:
            pq = np.stack([bucket_up(n_i[scene], config.size_bucket),
                           bucket_up(n_j, config.size_bucket)], axis=1)
            match_flat, err_flat = run_pairs(
                _match_pairs, pq, adj_i, n_i, scene, rows, lambda p, q: (p * q) ** 2 * 4 * 3, budget,
                ("p", "q"), [(k,), ()], (*database_tables(db), jnp.float32(config.c)),
                n_iter=int(config.power_iterations), tol=float(config.power_tol),
                min_matched=int(config.min_matched))
            err[s_idx, c_idx] = err_flat
            pair_of[s_idx, c_idx] = np.arange(rows.size)
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
        if upd.size:
            best_match[upd] = match_flat[pair_of[better, j[better]]]
        r0 += block
        block = min(2 * block, 512)
        nxt = level_all[act, r0] if r0 < width else np.full(act.size, n_levels)
        done[act] = (r0 >= count[act]) | (nxt > lstar[act])
    ok = usable & (best_err <= config.max_error_deg)
    return {"ok": ok, "best": np.where(ok, best, -1), "match": np.where(ok[:, None], best_match, -1),
            "error": best_err, "n_matched_graphs": n_done, "n_pruned": n_pruned,
            "level": np.where(ok, lstar, -1).astype(np.int32)}


def bucket_up(x: np.ndarray, m: int) -> np.ndarray:
    """Round each entry up to a multiple of ``m`` (at least ``m``)."""
    return np.maximum(m, -(-np.asarray(x) // m) * m).astype(np.int64)
