"""Rough search (eq. 1, k-vector) and the dynamic Δw search of Algorithm 1, batched.

Algorithm 1 (You et al. 2022) for an image graph with MST weight w_I visits Δw_l = Δw₀ + l·h_Δw,
l = 0, 1, … while Δw_l ≤ Δw_max; at each level it matches every database graph J with
``|w_J − w_I| ≤ Δw_l`` not matched before, takes J* = argmin δ (eq. 6) over everything matched so
far, and stops at the first level where δ_{I,J*} ≤ ε_δ; if no level succeeds, the scene fails.

Batched form. Candidates are ranked by d_J = |w_J − w_I|; J enters at level
``l(J) = ⌈(d_J − Δw₀)/h⌉⁺``, non-decreasing in rank, so every level searches a prefix of the ranks.
Ranks are matched in chunks, all scenes of the batch in lock-step (done scenes leave the batch). With
t the first rank with δ ≤ ε_δ and l* = l(t), a scene stops once it has covered the prefix
``{J : l(J) ≤ l*}`` and returns the argmin of δ over it; with no success it fails after the whole
window ``d_J ≤ Δw_last``. Invariant: the outcome is the sequential loop's, up to ties in δ (tested
against it; the argument is in docs/design/sgm.md).

Branch and bound (``Config.pruning``: by default only without the screen; not in the paper;
changes only the work). Lower bounds on δ
(:mod:`.bound`) in two stages: :func:`~.bound.edge_lower_bound` for every candidate examined, the
≈ 10× dearer :func:`~.bound.error_lower_bound` only for a candidate the first keeps and the search
needs (:func:`_refine`). A bound > ε_δ prunes the candidate. Once a success δ* ≤ ε_δ is known at
level l*, a candidate below l* is still matched (it could lower l*), one at l* whose bound exceeds
δ* is *deferred* (left unmatched). Each step first matches every scene's candidate with the smallest
bound, to find δ* early. The bound prunes but does not order: best-first matching needed more
matchings and named more wrong main stars (docs/design/sgm.md).

Triangle screen (``Config.screen``, an extension that may change the outcome, off in
``Config.paper()``): a candidate that fails :mod:`.screen` is struck out as if its δ exceeded ε_δ,
so the search is Algorithm 1 over the candidates that pass (tested). It runs first on every
examined candidate, before the bounds: at σ = 3 px it strikes out ≈ 99.5 % of them (1,000 scenes:
367k of 369k), which leaves the bounds too little to save (``Config.pruning`` is off with it).

Resumption. :class:`SearchState` keeps δ of every matched candidate and the bound of every deferred
one. When the post-match verification rejects J* (``Config.verify.retries``), :func:`reject_best`
sets its δ to ∞ and :func:`advance_search` goes on: Algorithm 1 on the database without the
struck-out graphs (tested against the sequential loop with those graphs removed).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.sgm.bound import edge_lower_bound, error_lower_bound, row_table, sorted_edges
from jstarid.algorithms.sgm.config import Config
from jstarid.algorithms.sgm.database import database_tables
from jstarid.algorithms.sgm.graph import ImageGraph
from jstarid.algorithms.sgm.matching import spectral_match
from jstarid.algorithms.sgm.screen import screen_pairs
from jstarid.geometry import range_search
from jstarid.runtime import map_batch, next_power_of_two, release_staging, run_pairs, skip_padding
from jstarid.runtime.pairs import MIN_CALL_PAIRS
from jstarid.runtime.program_store import stored_jit
from jstarid.runtime.staging_memory import trim_heap

__all__ = ["ImageTables", "SearchOutcome", "SearchState", "advance_search", "beyond_row_bound",
           "bucket_up", "candidate_windows", "dynamic_search", "edge_bounds", "image_tables",
           "lower_bounds", "order_candidates", "prune_mask", "reject_best", "search_outcome",
           "start_search"]


@stored_jit
def candidate_windows(kvector, w_i, dw_last_deg):
    """Rough search (eq. 1) at the widest Δw: ``(start, stop)`` (B,) int32 rows of the database."""
    return jax.vmap(range_search, in_axes=(None, 0, 0))(kvector, w_i - dw_last_deg,
                                                         w_i + dw_last_deg)


def order_candidates(w_db, start, stop, w_i, *, width: int, dw0: float, step: float, n_levels: int):
    """Candidates of each scene ordered by |w_J − w_I|, with the Δw level where each enters (host side).

    A window of the w-sorted database holds two runs of distances (falling below w_I, rising above
    it): NumPy's stable sort (timsort) merges them in linear time. Each scene sorts its own window
    only (the batch's widest window sets W, often 10× a typical scene's), where XLA's CPU sort
    compares element by element (≈ 6× slower at a batch of 1,000, width 8,192). Ties keep the
    database order (stable), as the sequential Algorithm 1 visits them.

    Args:
        w_db: (D,) ascending database w (deg).
        start, stop: (B,) int window of each scene (from :func:`candidate_windows`).
        w_i: (B,) image MST weights (deg).
        width: window capacity W; a longer window is cut to its first W rows.
        dw0, step, n_levels: Δw₀, h_Δw (deg) and the number of levels (Config).

    Returns:
        ``(cand, level)``: (B, W) int32 database rows by rank (−1 past the window), (B, W) int32
        level l(J) of each (n_levels past the window); NumPy arrays.
    """
    w_db = np.asarray(w_db, np.float32)
    start, stop = np.asarray(start, np.int64), np.asarray(stop, np.int64)
    w_i = np.asarray(w_i, np.float32)
    b = start.shape[0]
    cand = np.full((b, width), -1, np.int64)
    d_sorted = np.full((b, width), np.inf, np.float32)
    for s in range(b):
        lo, hi = start[s], min(stop[s], start[s] + width)
        if hi <= lo:
            continue
        d = np.abs(w_db[lo:hi] - w_i[s])
        perm = np.argsort(d, kind="stable")
        cand[s, :hi - lo] = lo + perm
        d_sorted[s, :hi - lo] = d[perm]
    finite = np.isfinite(d_sorted)
    # float32 throughout, as the kernels compute it (Δw levels at their edges are exact ties)
    with np.errstate(invalid="ignore"):
        level = np.ceil((d_sorted - np.float32(dw0)) / np.float32(step) - np.float32(1e-4))
    level = np.where(finite, np.clip(level, 0, n_levels - 1), n_levels)
    return cand.astype(np.int32), level.astype(np.int32)


@functools.partial(stored_jit, static_argnames=("p", "q", "n_iter", "tol", "min_matched"))
def _match_pairs(a_i, n_i, cand, db_adj, db_n, c, *, p, q, n_iter, tol, min_matched):
    """Spectral matching of N (image graph, database graph) pairs → (N, p) match, (N,) δ (deg).

    Pairs run one after another (``lax.map``), not ``vmap``: a lone pair's (p·q)² affinity matrix stays
    in cache for all its power steps (docs/design/sgm.md), and each pair stops on its own
    (``Config.matching.power_tol``). Padding pairs (``cand`` = −1) are skipped (match −1, δ = inf). ``c``
    (eq. 2) is traced: a sweep over c reuses the compiled kernels.
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


@functools.partial(stored_jit, static_argnames=("r", "max_skip"))
def _bound_pairs(rows_i, n_i, cand, db_rows, db_n, *, r, max_skip):
    """:func:`~.bound.error_lower_bound` of N (image graph, database graph) pairs → (N,) (deg).

    Reads sorted rows (:func:`~.bound.row_table`: the image's (N, r, r) corner, the database's whole
    table); ``vmap`` over groups of 16 pairs; groups of padding pairs only (``cand`` = −1) get bound 0.
    """
    live = cand >= 0
    cand = jnp.maximum(cand, 0)
    n = cand.shape[0]
    group = math.gcd(n, 16)
    bound = functools.partial(error_lower_bound, max_skip=max_skip)

    def one_group(rows_g, ni_g, cand_g):
        # (r, r − 1): a graph of ≤ r vertices has ≤ r − 1 finite entries per row
        return jax.vmap(bound)(rows_g[:, :, :r - 1], ni_g, db_rows[cand_g, :r, :r - 1], db_n[cand_g])

    def split(x):
        return x.reshape((n // group, group) + x.shape[1:])

    out = skip_padding(one_group, jnp.any(split(live), axis=1),
                       (split(rows_i), split(n_i), split(cand)), jnp.zeros((group,), jnp.float32))
    return out.reshape(n)


@stored_jit
def _edge_bound_pairs(e_i, n_i, e_j, n_j):
    """:func:`~.bound.edge_lower_bound` of N pairs of sorted edge lists (N, E) → (N,) (deg); ``vmap``."""
    return jax.vmap(edge_lower_bound)(e_i, n_i, e_j, n_j)


class ImageTables(NamedTuple):
    """The image graphs' tables the bounds read, sorted once per search (NumPy).

    Attributes:
        rows: (B, K, K) :func:`~.bound.row_table`. edges: (B, K(K − 1)/2) :func:`~.bound.sorted_edges`.
    """

    rows: np.ndarray
    edges: np.ndarray


class SearchOutcome(NamedTuple):
    """Algorithm 1's answer per scene (:func:`search_outcome`; NumPy arrays, batch axis first).

    Attributes:
        ok: (B,) bool, a match with δ ≤ ε_δ was found.
        best: (B,) int32 database row of J* (−1). rank: (B,) int32 its rank (−1).
        match: (B, K) int32 database vertex of each image vertex (−1).
        error: (B,) float32 δ_{I,J*} (deg; for a failed scene the least δ examined, inf when nothing
            was matched — with pruning, also when every candidate was pruned).
        n_matched: (B,) int32 candidates whose spectral matching ran.
        n_pruned: (B,) int32 candidates the bound removed (against ε_δ, or the best δ found).
        n_rejected: (B,) int32 answers struck out.
        level: (B,) int32 index of the Δw level that succeeded (−1).
    """

    ok: np.ndarray
    best: np.ndarray
    rank: np.ndarray
    match: np.ndarray
    error: np.ndarray
    n_matched: np.ndarray
    n_pruned: np.ndarray
    n_rejected: np.ndarray
    level: np.ndarray


def image_tables(adj_i, n_i) -> ImageTables:
    """Sorted rows and edges of image graphs, the bounds' inputs (:mod:`.bound`), sorted once.

    Args:
        adj_i: (B, K, K) image adjacencies (deg). n_i: (B,) vertex counts.

    Returns:
        :class:`ImageTables`.
    """
    adj = np.asarray(adj_i, np.float32)  # sorted by NumPy (XLA:CPU's sort is several times slower)
    mask = np.arange(adj.shape[-1])[None, :] < np.asarray(n_i)[:, None]
    return ImageTables(rows=row_table(adj, mask), edges=sorted_edges(adj, mask))


def edge_bounds(db, image: ImageTables, n_i, scene, rows, config: Config) -> np.ndarray:
    """:func:`~.bound.edge_lower_bound` of (scene, candidate) pairs: the search's first-stage bound.

    Reads tables sorted once (``Database.edges``, :func:`image_tables`); pairs are grouped by padded
    vertex count r (lists of r(r − 1)/2 entries), one vectorized call of power-of-two size per group.

    Args:
        db: the database. image: :func:`image_tables` of the image graphs. n_i: (B,) image vertex counts.
        scene, rows: (N,) scene and database row of each pair.
        config: :class:`Config` (``size_bucket``).

    Returns:
        (N,) float32 bound on δ (deg).
    """
    lb = np.zeros(rows.size, np.float32)
    if not rows.size:
        return lb
    n_j = db.n[rows]
    r = np.maximum(bucket_up(n_i[scene], config.size_bucket), bucket_up(n_j, config.size_bucket))
    for size in np.unique(r):
        at = np.nonzero(r == size)[0]
        width = int(size * (size - 1) // 2)
        padded = max(MIN_CALL_PAIRS, next_power_of_two(at.size))
        fill = np.concatenate([at, np.full(padded - at.size, at[0])])
        out = map_batch(_edge_bound_pairs,
                        (jnp.asarray(image.edges[scene[fill], :width]), jnp.asarray(n_i[scene[fill]]),
                         jnp.asarray(db.edges[rows[fill], :width]), jnp.asarray(n_j[fill])))
        lb[at] = np.asarray(out)[:at.size]
    return lb


def beyond_row_bound(n_i, n_j, config: Config) -> np.ndarray:
    """True where two vertex counts differ by more than ``matching.prune_max_skip``: the row bound
    (:func:`~.bound.error_lower_bound`) knows nothing there and is not computed."""
    return np.abs(np.asarray(n_i, np.int64) - np.asarray(n_j, np.int64)) > config.matching.prune_max_skip


def lower_bounds(db, image: ImageTables, n_i, scene, rows, config: Config):
    """:func:`~.bound.error_lower_bound` of (scene, candidate) pairs: the search's second-stage bound.

    Args:
        db: the database. image: :func:`image_tables` of the image graphs. n_i: (B,) image vertex
            counts.
        scene, rows: (N,) scene and database row of each pair.
        config: :class:`Config` (``matching.prune_max_skip``, ``size_bucket``, ``matching.memory_budget_mb``).

    Returns:
        ``(bound, bounded)``: (N,) float32 bound on δ (deg; 0 where nothing is known) and (N,) bool,
        False for pairs whose vertex counts differ by more than ``matching.prune_max_skip`` (not bounded).
    """
    n_j = db.n[rows]
    s_diff = np.abs(n_i[scene] - n_j)
    bounded = ~beyond_row_bound(n_i[scene], n_j, config)
    at = np.nonzero(bounded)[0]
    lb = np.zeros(rows.size, np.float32)
    if at.size:
        # grouped by padded size and by skip count (0, 1, 2, 4, 8, …: the programme's width)
        r = np.maximum(bucket_up(n_i[scene[at]], config.size_bucket),
                       bucket_up(n_j[at], config.size_bucket))
        sk = np.where(s_diff[at] == 0, 0,
                      1 << np.ceil(np.log2(np.maximum(s_diff[at], 1))).astype(np.int64))
        (lb[at],) = run_pairs(
            _bound_pairs, np.stack([r, sk], axis=1), image.rows, n_i, scene[at], rows[at],
            lambda r_, s_: r_ * r_ * (r_ - 1 + 3 * (s_ + 1)) * 4, config.matching.memory_budget_mb * 2**20,
            ("r", "max_skip"), [()], database_tables(db, "rows"))
    return lb, bounded


def _exceeds(bound, error_deg):
    """``bound > error_deg`` with a small margin for the float32 rounding of the two computations."""
    return bound > error_deg * (1 + 1e-4) + 1e-5


def prune_mask(db, adj_i, n_i, scene, rows, config: Config, max_error_deg: float) -> np.ndarray:
    """Which (scene, candidate) pairs survive the bounds of :mod:`.bound` (the edge bound first, the
    row bound for the pairs it keeps).

    Args:
        db: the database. adj_i: (B, K, K) image adjacencies (deg). n_i: (B,) image vertex counts.
        scene, rows: (N,) scene and database row of each pair.
        config: :class:`Config` (``matching.prune_max_skip``, ``size_bucket``, ``matching.memory_budget_mb``).
        max_error_deg: ε; a pair is dropped when its bound on δ exceeds it.

    Returns:
        (N,) bool, True for the pairs to match (pairs differing by more than ``matching.prune_max_skip``
        vertices face the edge bound only).
    """
    image = image_tables(adj_i, n_i)
    keep = ~_exceeds(edge_bounds(db, image, n_i, scene, rows, config), max_error_deg)
    at = np.nonzero(keep)[0]
    lb, _ = lower_bounds(db, image, n_i, scene[at], rows[at], config)
    keep[at] = ~_exceeds(lb, max_error_deg)
    return keep


@dataclasses.dataclass
class SearchState:
    """Host-side bookkeeping of Algorithm 1 for a batch: what each scene has matched so far.

    Ranks order each scene's candidates by |w_J − w_I| (:func:`order_candidates`); the examined ranks
    are a prefix. An examined rank is pruned (bound > ε_δ), matched (δ known) or *deferred* (not
    excluded, not needed yet). Keeping δ and bounds lets a search resume after :func:`reject_best`
    without matching anything twice.

    Attributes:
        cand: (B, W) int32 database rows by rank (−1 past the window). level: (B, W) int32 Δw level
            l(J) of each rank (``n_levels`` past the window). count: (B,) ranks in the window.
        usable: (B,) bool, scenes searched at all. covered: (B,) int32 ranks examined (a prefix).
        err: (B, W) float32 δ of each matched rank (deg; inf: pruned, deferred, struck out, unexamined).
        bound: (B, W) float32 lower bound on δ (deg; 0 where unknown): :func:`~.bound.edge_lower_bound`
            when examined, the larger of it and :func:`~.bound.error_lower_bound` once refined.
        refined: (B, W) bool, the bound is final (second stage run, or useless: vertex counts
            further apart than ``matching.prune_max_skip``, or no pruning). deferred: (B, W) bool, examined,
            neither pruned nor matched.
        matches: ``{(scene, rank): (K,) int32}`` correspondences of the matched pairs with δ ≤ ε_δ.
        n_matched, n_pruned, n_rejected: (B,) int32 spectral matchings run, candidates the bound removed
            against ε_δ (never-matched deferred ones are added by :func:`search_outcome`), answers
            struck out.
        image: :func:`image_tables` of the batch (``None`` without pruning).
    """

    cand: np.ndarray
    level: np.ndarray
    count: np.ndarray
    usable: np.ndarray
    err: np.ndarray
    bound: np.ndarray
    refined: np.ndarray
    deferred: np.ndarray
    covered: np.ndarray
    matches: dict[tuple[int, int], np.ndarray]
    n_matched: np.ndarray
    n_pruned: np.ndarray
    n_rejected: np.ndarray
    image: ImageTables | None

    def copy(self, fields: tuple[str, ...] | None = None) -> SearchState:
        """A new state whose ``fields`` (default: every array and the match table) are copies; the
        other fields are shared with this one (the caller must not write to those)."""
        names = [f.name for f in dataclasses.fields(self)] if fields is None else fields
        return dataclasses.replace(self, **{n: getattr(self, n).copy() for n in names
                                            if isinstance(getattr(self, n), np.ndarray | dict)})


def start_search(db, graphs: ImageGraph, usable: np.ndarray, config: Config) -> SearchState:
    """Rough search at the widest Δw and the candidate order of every scene; nothing matched yet."""
    b = graphs.mask.shape[0]
    w_i = jnp.asarray(graphs.w, jnp.float32)
    start, stop = candidate_windows(db.kvector, w_i, jnp.float32(config.dw_last_deg))
    count = np.where(usable, np.asarray(stop) - np.asarray(start), 0)
    width = next_power_of_two(max(int(count.max(initial=0)), int(config.matching.chunk_size)))
    cand, level = order_candidates(
        db.w, start, stop, w_i, width=width, dw0=float(config.dw0_deg),
        step=float(config.dw_step_deg), n_levels=config.n_levels)
    zeros = np.zeros(b, np.int32)
    return SearchState(cand=cand, level=level, count=count,
                       usable=np.asarray(usable, bool), err=np.full(cand.shape, np.inf, np.float32),
                       bound=np.zeros(cand.shape, np.float32), refined=np.zeros(cand.shape, bool),
                       deferred=np.zeros(cand.shape, bool), covered=zeros.copy(), matches={},
                       n_matched=zeros.copy(), n_pruned=zeros.copy(), n_rejected=zeros.copy(),
                       image=image_tables(graphs.adj, graphs.n) if config.pruning else None)


def _examined(state: SearchState, rows: np.ndarray) -> int:
    """Ranks examined by the most advanced scene of ``rows`` (≥ 1): past it, every rank of these
    scenes is unexamined (δ = inf, not deferred), so per-rank bookkeeping reads only this prefix of
    the (B, W) tables (W is set by the widest window of the batch, often 10× a typical scene's)."""
    return max(1, int(state.covered[rows].max(initial=0)))


def _first_success_level(state: SearchState, config: Config, rows: np.ndarray) -> np.ndarray:
    """(R,) l* of each scene: the level of its first matched rank with δ ≤ ε_δ (``n_levels``: none)."""
    upto = _examined(state, rows)
    succ = state.err[rows, :upto] <= config.max_error_deg
    t = np.argmax(succ, axis=1)
    return np.where(succ.any(axis=1), state.level[rows, t], config.n_levels)


def _prefix_done(state: SearchState, config: Config, rows: np.ndarray) -> np.ndarray:
    """(R,) bool: every rank of the l* prefix (or of the window) has been examined."""
    width = state.cand.shape[1]
    cov = state.covered[rows]
    nxt = np.where(cov < width, state.level[rows, np.minimum(cov, width - 1)], config.n_levels)
    return (~state.usable[rows] | (cov >= state.count[rows])
            | (nxt > _first_success_level(state, config, rows)))


def _needed(state: SearchState, config: Config, rows: np.ndarray) -> np.ndarray:
    """(R, U) bool: deferred ranks whose δ can still change Algorithm 1's answer (U ≤ W: the
    examined prefix, :func:`_examined`).

    With l* the level of the first matched success and δ* the least δ matched in the l* prefix, a
    deferred rank matters when its level is below l* (δ ≤ ε_δ would make an earlier level succeed), or
    at l* when its bound does not exceed δ* (it could be the argmin). Before any success
    (l* = ``n_levels``) every deferred rank matters.
    """
    lstar = _first_success_level(state, config, rows)
    upto = _examined(state, rows)  # nothing past the examined prefix is deferred
    level = state.level[rows, :upto]
    in_prefix = level <= lstar[:, None]
    best = np.min(np.where(in_prefix, state.err[rows, :upto], np.inf), axis=1)
    could_be_best = ~_exceeds(state.bound[rows, :upto], best[:, None])
    return state.deferred[rows, :upto] & in_prefix & ((level < lstar[:, None]) | could_be_best)


def _finished(state: SearchState, config: Config, rows: np.ndarray) -> np.ndarray:
    """(R,) bool: Algorithm 1 has stopped — the l* prefix (or the window) examined and every
    deferred rank that could change the answer matched."""
    return _prefix_done(state, config, rows) & ~np.any(_needed(state, config, rows), axis=1)


def _match_ranks(db, graphs: ImageGraph, state: SearchState, config: Config, scene: np.ndarray,
                 rank: np.ndarray) -> None:
    """Spectral matching of the (scene, rank) pairs (in place: δ, correspondences, counts)."""
    if not scene.size:
        return
    k = graphs.adj.shape[1]
    n_i = graphs.n.astype(np.int32)
    rows = state.cand[scene, rank]
    pq = np.stack([bucket_up(n_i[scene], config.size_bucket),
                   bucket_up(db.n[rows], config.size_bucket)], axis=1)
    match_flat, err_flat = run_pairs(
        _match_pairs, pq, graphs.adj, n_i, scene, rows, lambda p, q: (p * q) ** 2 * 4 * 3,
        config.matching.memory_budget_mb * 2**20, ("p", "q"), [(k,), ()],
        (*database_tables(db), jnp.float32(config.c)),
        n_iter=int(config.matching.power_iterations), tol=float(config.matching.power_tol),
        min_matched=int(config.min_matched))
    state.err[scene, rank] = err_flat
    state.deferred[scene, rank] = False
    np.add.at(state.n_matched, scene, 1)
    for i in np.nonzero(err_flat <= config.max_error_deg)[0]:
        state.matches[(int(scene[i]), int(rank[i]))] = match_flat[i]


def _examine_block(db, graphs: ImageGraph, state: SearchState, config: Config, act: np.ndarray,
                   block: int) -> None:
    """Screen and bound the next ``block`` ranks of the l* prefix of each scene in ``act`` (in place):
    a candidate that fails the triangle screen (``Config.screen``) or whose first-stage bound
    (:func:`~.bound.edge_lower_bound`) exceeds ε_δ is pruned, the others deferred (refined when
    needed: :func:`_refine`).
    """
    width = state.cand.shape[1]
    ranks = state.covered[act, None] + np.arange(block)[None, :]  # (A, block)
    inwin = ranks < state.count[act, None]
    rk = np.minimum(ranks, width - 1)
    lev = np.where(inwin, np.take_along_axis(state.level[act], rk, axis=1), config.n_levels)
    lstar = _first_success_level(state, config, act)
    # levels are non-decreasing in rank: the ranks within the l* prefix are a prefix of the block
    take = inwin & (lev <= lstar[:, None])
    s_idx, c_idx = np.nonzero(take)
    scene, rank = act[s_idx], ranks[s_idx, c_idx]
    state.refined[scene, rank] = True  # without pruning there is nothing to refine
    if config.screen.on and scene.size:
        # first: the screen strikes out ≈ 90 % of the candidates at a cost per pair near the edge
        # bound's, which strikes out ≈ 9 % (400 σ = 3 px scenes: 339k of 372k pairs screened when
        # the screen ran after it), so the bounds run on the few it keeps
        keep = screen_pairs(db, graphs.plane, graphs.n.astype(np.int32), scene, state.cand[scene, rank],
                            config)
        np.add.at(state.n_pruned, scene[~keep], 1)
        scene, rank = scene[keep], rank[keep]
    if config.pruning and scene.size:
        n_i = graphs.n.astype(np.int32)
        rows = state.cand[scene, rank]
        lb = edge_bounds(db, state.image, n_i, scene, rows, config)
        keep = ~_exceeds(lb, config.max_error_deg)
        np.add.at(state.n_pruned, scene[~keep], 1)
        state.bound[scene, rank] = lb
        # the second stage only knows something where the vertex counts are close enough
        state.refined[scene, rank] = beyond_row_bound(n_i[scene], db.n[rows], config)
        scene, rank = scene[keep], rank[keep]
    state.deferred[scene, rank] = True
    state.covered[act] += np.sum(take, axis=1).astype(np.int32)


def _refine(db, graphs: ImageGraph, state: SearchState, config: Config, scene: np.ndarray,
            rank: np.ndarray) -> None:
    """Second stage of the deferred (scene, rank) pairs not refined yet (in place): the row bound
    (:func:`~.bound.error_lower_bound`); a pair whose bound exceeds ε_δ is pruned. Run only for
    ranks the search still needs, so most candidates of a scene solved early are not bounded."""
    todo = ~state.refined[scene, rank]
    scene, rank = scene[todo], rank[todo]
    if not scene.size:
        return
    n_i = graphs.n.astype(np.int32)
    rows = state.cand[scene, rank]
    state.refined[scene, rank] = True
    lb, _ = lower_bounds(db, state.image, n_i, scene, rows, config)
    lb = np.maximum(lb, state.bound[scene, rank])
    state.bound[scene, rank] = lb
    out = _exceeds(lb, config.max_error_deg)
    state.deferred[scene[out], rank[out]] = False
    np.add.at(state.n_pruned, scene[out], 1)


def _probe(db, graphs: ImageGraph, state: SearchState, config: Config, act: np.ndarray) -> None:
    """Match each scene's needed rank with the smallest bound (the likeliest J*; in place), if its
    refined bound keeps it. Ranks whose vertex count differs by more than ``matching.prune_max_skip``
    come last: only the loose first stage bounds them, they are seldom J*, and a failed probe leaves
    no δ*.
    """
    need = _needed(state, config, act)
    upto = need.shape[1]
    far = beyond_row_bound(graphs.n[act, None], db.n[np.maximum(state.cand[act, :upto], 0)], config)
    first = np.argmin(np.where(need, state.bound[act, :upto] + np.where(far, 1e6, 0.0), np.inf),
                      axis=1)
    probe = np.nonzero(need[np.arange(act.size), first])[0]
    scene, rank = act[probe], first[probe]
    _refine(db, graphs, state, config, scene, rank)
    live = state.deferred[scene, rank]
    _match_ranks(db, graphs, state, config, scene[live], rank[live])


def advance_search(db, graphs: ImageGraph, state: SearchState, config: Config,
                   active: np.ndarray | None = None) -> SearchState:
    """Run Algorithm 1 on the ``active`` scenes (default: all) until each has stopped.

    Each step examines the next block of ranks of every scene whose l* prefix is not covered
    (``matching.chunk_size`` ranks, doubling up to 512) and prunes by the first-stage bound. With
    ``matching.prune``: a probe (:func:`_probe`) matches the needed rank with the smallest bound, the
    other needed ranks (:func:`_needed`) are refined, a second probe, then every rank that can still
    change the answer is matched; without it, every examined rank of the l* prefix. Ranks beyond the
    l* prefix stay unexamined. The outcome is Algorithm 1's (module docstring).

    Args:
        db: :class:`~jstarid.algorithms.sgm.database.Database`.
        graphs: per-scene image graphs as NumPy arrays: ``adj`` (B, K, K) deg, ``n`` (B,).
        state: :class:`SearchState` from :func:`start_search` (left unchanged).
        config: :class:`Config`. active: (B,) bool scenes to advance.

    Returns:
        The new :class:`SearchState`.
    """
    # the steps below write to these fields of a private copy (the candidate order is shared)
    state = state.copy(("err", "bound", "refined", "deferred", "covered", "matches", "n_matched",
                        "n_pruned"))
    b = state.cand.shape[0]
    todo = np.ones(b, bool) if active is None else np.asarray(active, bool).copy()
    rows_all = np.nonzero(todo)[0]
    todo[rows_all] = ~_finished(state, config, rows_all)
    block = int(config.matching.chunk_size)
    while np.any(todo):
        act = np.nonzero(todo)[0]
        grow = act[~_prefix_done(state, config, act)]
        if grow.size:
            _examine_block(db, graphs, state, config, grow, block)
            block = min(2 * block, 512)
        if config.pruning:  # without bounds every examined rank is matched, in one round
            # probe by the first-stage bound: where it finds δ*, most other ranks need no more work
            _probe(db, graphs, state, config, act)
            # refine every rank still needed; probe again by the refined bound (where the first
            # probe found no δ* ≤ ε_δ, all ranks were needed); then match whatever is still needed
            s_idx, rank = np.nonzero(_needed(state, config, act))
            _refine(db, graphs, state, config, act[s_idx], rank)
            _probe(db, graphs, state, config, act)
        s_idx, rank = np.nonzero(_needed(state, config, act))
        _match_ranks(db, graphs, state, config, act[s_idx], rank)
        todo[act] = ~_finished(state, config, act)
        # a round can compile a kernel for each new size bucket and pair count: what JAX keeps of
        # staging them is most of the search's memory (runtime.staging_memory)
        release_staging()
    # the rounds' host arrays are freed too: one trim gives their heap back (a trim after every
    # round cost ≈ 16 ms each, 0.4 s of a 6.7 s call of 1,000 σ = 3 px scenes)
    trim_heap()
    return state


def search_outcome(state: SearchState, config: Config, k: int) -> SearchOutcome:
    """Algorithm 1's answer from what has been examined: J* = argmin δ over the l* prefix.

    Args:
        state: :class:`SearchState` after :func:`advance_search`. config: :class:`Config`.
        k: K, the image graphs' vertex capacity.

    Returns:
        :class:`SearchOutcome` (NumPy arrays, batch axis first; fields documented there).
    """
    b = state.cand.shape[0]
    everyone = np.arange(b)
    lstar = _first_success_level(state, config, everyone)
    upto = _examined(state, everyone)  # δ = inf past it
    err = np.where(state.level[:, :upto] <= lstar[:, None], state.err[:, :upto], np.inf)
    j = np.argmin(err, axis=1)
    best_err = err[everyone, j]
    ok = state.usable & (lstar < config.n_levels)
    match = np.full((b, k), -1, np.int32)
    for s in np.nonzero(ok)[0]:
        match[s] = state.matches[(int(s), int(j[s]))]
    return SearchOutcome(
        ok=ok, best=np.where(ok, state.cand[everyone, j], -1).astype(np.int32),
        rank=np.where(ok, j, -1).astype(np.int32), match=match, error=best_err,
        n_matched=state.n_matched.copy(),
        n_pruned=state.n_pruned + np.sum(state.deferred, axis=1).astype(np.int32),
        n_rejected=state.n_rejected.copy(), level=np.where(ok, lstar, -1).astype(np.int32))


def reject_best(state: SearchState, outcome: SearchOutcome, rows: np.ndarray) -> SearchState:
    """A new state with J* of the scenes ``rows`` struck out, as if its δ exceeded ε_δ: a later
    :func:`advance_search` goes on as Algorithm 1 would without it (the next best of the same l* prefix
    when another has δ ≤ ε_δ, else further levels).
    """
    state = state.copy(("err", "matches", "n_rejected"))
    rows = np.asarray(rows)
    rows = rows[outcome.ok[rows]]
    state.err[rows, outcome.rank[rows]] = np.inf
    for s in rows:
        state.matches.pop((int(s), int(outcome.rank[s])), None)
    state.n_rejected[rows] += 1
    return state


def dynamic_search(db, graphs: ImageGraph, usable: np.ndarray, config: Config) -> SearchOutcome:
    """Algorithm 1 for a batch of image graphs (:func:`start_search`, :func:`advance_search`,
    :func:`search_outcome`).

    Args:
        db: :class:`~jstarid.algorithms.sgm.database.Database`.
        graphs: per-scene NumPy image graphs: ``adj`` (B, K, K) deg, ``mask`` (B, K), ``n`` (B,),
            ``w`` (B,) deg.
        usable: (B,) bool scenes to search (the others fail). config: :class:`Config`.

    Returns:
        :class:`SearchOutcome`.
    """
    state = advance_search(db, graphs, start_search(db, graphs, usable, config), config)
    return search_outcome(state, config, graphs.mask.shape[1])


def bucket_up(x: np.ndarray, m: int) -> np.ndarray:
    """Round each entry up to a multiple of ``m`` (at least ``m``)."""
    return np.maximum(m, -(-np.asarray(x) // m) * m).astype(np.int64)
