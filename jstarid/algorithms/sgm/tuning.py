"""Vectorized parameter sweeps of SGM: a grid of c × ε_δ evaluated on one set of scenes.

Algorithm 1's outcome for a scene is a function of the ranked candidates (by |w_J − w_I|), the Δw
level at which each enters and their matching errors δ (:mod:`.search`). So a grid over the affinity
adjustor c and the error threshold ε_δ needs the spectral matching once per (candidate, c) — the c
axis is a ``vmap`` inside the matching kernel — and the stop rule is then replayed for every ε_δ on
the stored errors (:func:`replay_algorithm1`, pure array code), instead of re-running the search per
grid point.

Every candidate of the widest window (Δw_max) is matched, except those the exact bound of
:mod:`.bound` puts above the largest ε_δ of the grid (their δ is stored as +inf, which is exact for
every ε_δ of the grid). The verification step (``Config.verify``) is not applied: the sweep studies the
paper's algorithm.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.sgm.config import Config, Tuning
from jstarid.algorithms.sgm.database import database_tables
from jstarid.algorithms.sgm.graph import searchable_graphs
from jstarid.algorithms.sgm.matching import spectral_match
from jstarid.algorithms.sgm.naming import attitude_from_names
from jstarid.algorithms.sgm.search import bucket_up, candidate_windows, order_candidates, prune_mask
from jstarid.runtime import next_power_of_two, replicate, run_pairs, skip_padding
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Identification

__all__ = ["CandidateErrors", "candidate_errors", "grid_identifications", "identify_grid",
           "replay_algorithm1", "search_grid"]


class CandidateErrors(NamedTuple):
    """Matching errors of every candidate of the widest Δw window (:func:`candidate_errors`).

    Attributes:
        cand: (B, W) int32 database rows by rank (−1 past the window).
        level: (B, W) int32 Δw level of each rank.
        error: (B, W, C) float32 δ (deg; +inf when not a candidate or pruned), one column per c.
        match: ``{(scene, rank, c index): (K,) int16}`` correspondences of the pairs with δ ≤ the
            largest ε_δ (only those can be returned by Algorithm 1).
    """

    cand: np.ndarray
    level: np.ndarray
    error: np.ndarray
    match: dict[tuple[int, int, int], np.ndarray]


@functools.partial(stored_jit, static_argnames=("p", "q", "n_iter", "tol", "min_matched"))
def _match_pairs_grid(a_i, n_i, cand, db_adj, db_n, cs, *, p, q, n_iter, tol, min_matched):
    """Spectral matching of N pairs for every c of ``cs`` (C,) → (N, C, p) match, (N, C) δ (deg)."""
    live = cand >= 0
    cand = jnp.maximum(cand, 0)
    a_j = db_adj[cand][:, :q, :q]
    mask_i = jnp.arange(p)[None, :] < n_i[:, None]
    mask_j = jnp.arange(q)[None, :] < db_n[cand][:, None]

    def one(a, ma, b, mb, c):
        return spectral_match(a, ma, b, mb, c=c, n_iter=n_iter, min_matched=min_matched, tol=tol)

    over_c = jax.vmap(one, in_axes=(None, None, None, None, 0))
    # pairs one after the other, the c values of a pair side by side (see search._match_pairs)
    dead = (jnp.full((cs.shape[0], p), -1, jnp.int32), jnp.full((cs.shape[0],), jnp.inf, jnp.float32))
    return skip_padding(lambda *args: over_c(*args, cs), live, (a_i, mask_i, a_j, mask_j), dead)


def candidate_errors(db, graphs, usable: np.ndarray, config: Config, cs, max_error_deg: float,
                     *, block: int = 256) -> CandidateErrors:
    """Matching errors of every candidate of the widest Δw window, for every c.

    Args:
        db: :class:`~jstarid.algorithms.sgm.database.Database`.
        graphs: image graphs as NumPy arrays (``adj`` (B, K, K), ``mask``, ``n``, ``w``), as from
            :func:`~jstarid.algorithms.sgm.graph.scene_graphs`.
        usable: (B,) bool scenes to search.
        config: :class:`Config` (window, schedule, power iteration, pruning switch).
        cs: (C,) values of c (1/deg).
        max_error_deg: the largest ε_δ that will be replayed; candidates provably above it are
            stored as +inf.
        block: candidate ranks handled per step.

    Returns:
        :class:`CandidateErrors` (``match`` holds the pairs with δ ≤ ``max_error_deg``).
    """
    cs = np.asarray(cs, np.float32)
    b, k = graphs.mask.shape
    w_i = jnp.asarray(graphs.w, jnp.float32)
    start, stop = candidate_windows(db.kvector, w_i, jnp.float32(config.dw_last_deg))
    count = np.where(usable, np.asarray(stop) - np.asarray(start), 0)
    width = next_power_of_two(max(int(count.max(initial=0)), 1))
    cand_all, level_all = order_candidates(
        db.w, start, stop, w_i, width=width, dw0=float(config.dw0_deg),
        step=float(config.dw_step_deg), n_levels=config.n_levels)
    cand_all = np.where(np.arange(width)[None, :] < count[:, None], cand_all, -1)
    error = np.full((b, width, cs.size), np.inf, np.float32)
    matches = {}
    adj_i, n_i = graphs.adj, graphs.n.astype(np.int32)
    cs_dev = replicate(jnp.asarray(cs))
    budget = config.matching.memory_budget_mb * 2**20
    for r0 in range(0, width, block):
        s_idx, r_idx = np.nonzero(cand_all[:, r0:r0 + block] >= 0)
        r_idx = r_idx + r0
        rows = cand_all[s_idx, r_idx]
        n_j = db.n[rows]
        if config.pruning and rows.size:
            keep = prune_mask(db, adj_i, n_i, s_idx, rows, config, max_error_deg)
            s_idx, r_idx, rows, n_j = s_idx[keep], r_idx[keep], rows[keep], n_j[keep]
        if not rows.size:
            continue
        pq = np.stack([bucket_up(n_i[s_idx], config.size_bucket),
                       bucket_up(n_j, config.size_bucket)], axis=1)
        m, e = run_pairs(_match_pairs_grid, pq, adj_i, n_i, s_idx, rows,
                          lambda p, q: (p * q) ** 2 * 4 * 3 * cs.size, budget, ("p", "q"),
                          [(cs.size, k), (cs.size,)], (*database_tables(db), cs_dev),
                          n_iter=int(config.matching.power_iterations), tol=float(config.matching.power_tol),
                          min_matched=int(config.min_matched))
        error[s_idx, r_idx] = e
        for pair, ci in zip(*np.nonzero(e <= max_error_deg), strict=True):
            matches[(int(s_idx[pair]), int(r_idx[pair]), int(ci))] = m[pair, ci].astype(np.int16)
    return CandidateErrors(cand=cand_all.astype(np.int32), level=level_all.astype(np.int32), error=error,
                           match=matches)


def replay_algorithm1(level, error, eps):
    """Algorithm 1's decision from stored candidate errors, for a grid of ε_δ.

    Args:
        level: (B, W) int Δw level of each rank (non-decreasing; ranks past the window hold a level
            above every real one).
        error: (B, W, C) δ of each rank for each c (+inf: no candidate / pruned / too few matches).
        eps: (E,) thresholds ε_δ (deg).

    Returns:
        ``(ok, rank)``: (B, C, E) bool success and (B, C, E) int32 rank of J* (−1 on failure) — the
        first level whose best δ ≤ ε_δ, and the argmin of δ over every rank up to that level.
    """
    eps = np.asarray(eps, np.float32)
    err = np.moveaxis(np.asarray(error), 1, -1)[:, :, None, :]  # (B, C, 1, W)
    succ = err <= eps[None, None, :, None]  # (B, C, E, W)
    ok = succ.any(axis=-1)
    first = np.argmax(succ, axis=-1)
    lev = np.asarray(level)[:, None, None, :]
    lstar = np.take_along_axis(np.broadcast_to(lev, succ.shape), first[..., None], axis=-1)
    within = np.where(lev <= lstar, err, np.inf)
    rank = np.argmin(within, axis=-1).astype(np.int32)
    return ok, np.where(ok, rank, -1)


def grid_identifications(db, graphs, errors: CandidateErrors, ok, rank, n_detections: int):
    """Catalog ids of every detection for each (scene, c, ε_δ) of a replayed grid.

    Args:
        db: the database. graphs: image graphs (``members`` (B, K) detection of each vertex).
        errors: :func:`candidate_errors` output. ok, rank: :func:`replay_algorithm1` output (B, C, E).
        n_detections: N, detections per scene.

    Returns:
        (B, C, E, N) int32 ids (−1 unnamed), named through the matched vertex correspondence.
    """
    b, n_c, n_e = ok.shape
    ids = np.full((b, n_c, n_e, n_detections), -1, np.int32)
    for s, ci, ei in zip(*np.nonzero(ok), strict=True):
        r = int(rank[s, ci, ei])
        match = errors.match[(int(s), r, int(ci))].astype(np.int64)
        vert = np.nonzero(match >= 0)[0]
        row = errors.cand[s, r]
        ids[s, ci, ei, graphs.members[s, vert]] = db.members[row, match[vert]]
    return ids


def search_grid(db, scenes, config: Config, tuning: Tuning):
    """The paper's Algorithm 1 for every (c, ε_δ) of a grid, on one batch of scenes.

    One spectral matching per (candidate, c) — c is a ``vmap`` axis — and the stop rule replayed for
    every ε_δ on the stored errors: the grid costs about one search per c, not one per grid point.
    The post-match verification is not applied (the grid studies the paper's algorithm).

    Args:
        db: :class:`~jstarid.algorithms.sgm.database.Database`.
        scenes: (B, N) :class:`~jstarid.scene.Scene` from ``db.camera``.
        config: :class:`Config` (window, schedule, power iteration, pruning); its ``c`` and
            ``max_error_deg`` are not used.
        tuning: :class:`~jstarid.algorithms.sgm.Tuning` whose ``c`` (C,) (1/deg) and
            ``max_error_deg`` (E,) (deg) are the grid's axes (scalars count as one value).

    Returns:
        ``(ids, ok)``: (B, C, E, N) int32 catalog rows (−1 unnamed) and (B, C, E) bool.
    """
    g, usable = searchable_graphs(db, scenes, config)
    cs = np.atleast_1d(np.asarray(tuning.c, np.float32))
    eps = np.atleast_1d(np.asarray(tuning.max_error_deg, np.float64))
    errors = candidate_errors(db, g, usable, config, cs, float(eps.max()))
    ok, rank = replay_algorithm1(errors.level, errors.error, eps)
    ok = ok & usable[:, None, None]
    return grid_identifications(db, g, errors, ok, rank, scenes.xy.shape[1]), ok


# the fields a grid of search_grid may vary, and the extensions it does not apply
_GRID_FIELDS = ("c", "max_error_deg")


def identify_grid(db, scenes, configs) -> list[Identification]:
    """``identify`` with each of ``configs`` (the sweep engine's parameter grids, :func:`jstarid.grid`).

    Where every config runs the paper's Algorithm 1 alone (``verify.on`` off, no leftover naming) and
    they differ only in ``c`` and ``max_error_deg``, the grid is one :func:`search_grid` call (c a
    batch axis of the matching, ε_δ replayed on the stored errors), whose names equal separate
    searches; otherwise each config is a separate :func:`~jstarid.algorithms.sgm.identify` call.

    Args:
        db: the database. scenes: (B, N) scenes. configs: :class:`Config` s.

    Returns:
        One (B, N) :class:`~jstarid.scene.Identification` per config (attitudes fitted to the names).
    """
    from jstarid.algorithms.sgm.identify import identify

    configs = list(configs)
    base = dataclasses.replace(configs[0], c=1.0, max_error_deg=0.1)
    batched = (not base.verify.on and base.leftover_tol_deg is None and all(
        dataclasses.replace(c, c=1.0, max_error_deg=0.1) == base for c in configs))
    if not batched:
        return [identify(db, scenes, c) for c in configs]
    cs = sorted({float(c.c) for c in configs})
    eps = sorted({float(c.max_error_deg) for c in configs})
    ids, ok = search_grid(db, scenes, configs[0], Tuning(c=np.array(cs), max_error_deg=np.array(eps)))
    out = []
    for config in configs:
        ci, ei = cs.index(float(config.c)), eps.index(float(config.max_error_deg))
        result = Identification(ids=jnp.asarray(ids[:, ci, ei]), ok=jnp.asarray(ok[:, ci, ei]),
                                attitude=None)
        out.append(attitude_from_names(db, scenes, result))
    return out
