"""Magnitude-robust SGM: the image graph matched as a subgraph (extension, ``Config.subgraph``).

The paper's rough search (eq. 1) compares MST weights, which assumes the image graph and the
database graph hold the same stars. On a real frame they do not: detections scatter by 0.16–0.20
mag about the catalog's limit and a tracker keeps its N brightest, so the image graph lacks some
catalog stars and holds some that the catalog lacks (experiments/RESULTS.md, Real images). This
module keeps SGM's spectral matching and replaces what assumes equal vertex sets:

1. **Rough search on radii** (:func:`radial_votes`): a database graph gets one vote per image
   neighbor whose angle to the main star it has within ``tol`` among its own neighbors. Each vote
   depends on one star only, so a star missing on either side costs one vote and no more (the MST
   weight changes by a whole edge). The ``candidates`` graphs of most votes go on.
2. **Triangle screen** (:func:`~.screen.triangle_support`): a rotation about the main star that
   brings most image neighbors onto database neighbors; the ``matchings`` graphs of most support
   go on.
3. **Spectral matching of a subgraph** (:func:`partial_match`): the database graph is cut to its
   main star and the neighbors whose radius matches an image neighbor's (the only ones that can be
   paired), the affinity of eq. 2 and its principal eigenvector as in the paper, greedy binarization;
   then pairs that disagree with the others are unmatched (:func:`drop_outliers`) and free vertices
   that agree with the rest are paired (:func:`grow_match`): unmatched vertices are allowed on both
   sides. The matching error eq. 5 is taken over the pairs that remain.
4. **Acceptance**: δ ≤ ε_δ, the main star paired, and at least ``max(min_matched,
   ⌈screen.fraction · min(n_I, n_J)⌉)`` pairs (n_J: the cut graph). Accepted candidates are ranked by
   pairs (more first), then δ; the verification (:mod:`.verify`) takes them in that order.

Choices a reviewer should know (the paper is silent, as it assumes equal vertex sets):
``subgraph.tol_deg`` is the radius tolerance of step 1 (tight: a tight vote is rare by chance),
``screen.tol_deg`` the edge-residual tolerance of step 3 (one star's position error, as in the
screen); the cut graph holds at most ``P + size_bucket`` vertices (P: the image graph's padded
size), those of nearest radius first — a graph with more radius partners is cut further
(:func:`partner_vertices`; ``Diagnostics.cut`` reports it for the accepted graph), which can only
lose a match, never make one wrong, because every name is verified.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.sgm.graph import ImageGraph
from jstarid.algorithms.sgm.matching import affinity_eigenvector, greedy_binarize, matching_error
from jstarid.algorithms.sgm.screen import triangle_support
from jstarid.algorithms.sgm.search import SearchOutcome
from jstarid.runtime import device_cache, map_batch, on_every_device, padded_indices
from jstarid.runtime.program_store import stored_jit

__all__ = ["Ranking", "radii_table", "radial_votes", "partner_vertices", "drop_outliers", "grow_match",
           "partial_match", "rank_candidates", "subgraph_search"]


class Ranking(NamedTuple):
    """Each scene's matched candidates, best first (:func:`subgraph_search`; NumPy, batch axis
    first, M = ``min(subgraph.matchings, subgraph.candidates)``).

    Attributes:
        rows: (B, M) int32 database rows (−1 where the scene was not searched).
        match: (B, M, K) int32 database vertex (of the whole graph) per image vertex (−1 none;
            K the image graphs' capacity).
        error: (B, M) float32 δ over the remaining pairs (deg, eq. 5; inf where the scene was not
            searched or fewer than ``min_matched`` pairs remain).
        pairs: (B, M) int32 matched pairs.
        ok: (B, M) bool accepted (step 4; False where the scene was not searched).
        cut: (B, M) bool, the cut graph was cut further (:func:`partner_vertices`).
    """

    rows: np.ndarray
    match: np.ndarray
    error: np.ndarray
    pairs: np.ndarray
    ok: np.ndarray
    cut: np.ndarray

    def outcome_at(self, pick: np.ndarray, n_rejected: np.ndarray) -> SearchOutcome:
        """The :class:`~.search.SearchOutcome` of the candidate ``pick`` (B,) of each scene's
        ranking (none where ``pick`` is past the ranking's end), so that the naming and the
        verification take it as they take Algorithm 1's answer; ``n_rejected`` (B,) int32 the
        answers struck out so far (``level`` 0 when accepted)."""
        at = np.arange(pick.size)
        inside = pick < self.ok.shape[1]
        pick = np.minimum(pick, self.ok.shape[1] - 1)
        ok = self.ok[at, pick] & inside
        n_tried = np.sum(np.isfinite(self.error), axis=1).astype(np.int32)
        return SearchOutcome(ok=ok, best=np.where(ok, self.rows[at, pick], -1).astype(np.int32),
                             rank=np.where(ok, pick, -1).astype(np.int32),
                             match=np.where(ok[:, None], self.match[at, pick], -1),
                             error=self.error[at, pick], n_matched=n_tried,
                             n_pruned=np.zeros(pick.size, np.int32), n_rejected=n_rejected,
                             level=np.where(ok, 0, -1).astype(np.int32))


def radii_table(db) -> np.ndarray:
    """(D, K) float32 angle (deg) of each database graph's neighbors to its main star, ascending,
    +inf padded (vertex 0, the main star, excluded: K − 1 real slots and one more +inf)."""
    def make():
        r = np.array(db.adj[:, 0, :], np.float32)
        r[np.arange(db.capacity)[None, :] >= db.n[:, None]] = np.inf
        r[:, 0] = np.inf
        return np.sort(r, axis=1)

    return device_cache.cached(db, "sgm_radii", make)


def radial_votes(r_i, valid_i, radii_db, tol):
    """Votes of every database graph for one image graph (rough search, step 1).

    Args:
        r_i: (P,) angle (deg) of each image vertex to the main star. valid_i: (P,) bool neighbors
            (the main star and padding False).
        radii_db: (D, K) :func:`radii_table`. tol: () radius tolerance (deg).

    Returns:
        (D,) int32: image neighbors with a database neighbor within ``tol`` in radius.
    """
    def one(row):
        lo = jnp.searchsorted(row, r_i - tol, side="left")
        hit = row[jnp.clip(lo, 0, row.shape[0] - 1)] <= r_i + tol
        return jnp.sum(hit & valid_i & (lo < row.shape[0]))

    return jax.vmap(one)(radii_db).astype(jnp.int32)


def partner_vertices(r_i, valid_i, r_j, mask_j, tol, q: int):
    """The database vertices that can be paired: the main star, then neighbors of nearest radius.

    Args:
        r_i: (P,) image radii (deg); valid_i: (P,) bool image neighbors. r_j: (K,) database graph
            radii (deg; vertex 0 the main star); mask_j: (K,) bool vertices. tol: () deg.
        q: static size of the cut graph (≤ K).

    Returns:
        ``(take, keep, cut)``: (q,) int32 database vertices in the cut graph's order (vertex 0 the
        main star), (q,) bool real ones, () bool True when more than q − 1 neighbors had a partner.
    """
    k = r_j.shape[0]
    gap = jnp.where(valid_i[:, None] & mask_j[None, :], jnp.abs(r_i[:, None] - r_j[None, :]), jnp.inf)
    nearest = jnp.min(gap, axis=0)  # (K,) each database vertex's best radius gap
    partner = (nearest <= tol) & (jnp.arange(k) > 0)
    key = jnp.where(jnp.arange(k) == 0, -1.0, jnp.where(partner, nearest, jnp.inf))
    take = jnp.argsort(key, stable=True)[:q].astype(jnp.int32)
    keep = (jnp.arange(q) == 0) | partner[take]
    return take, keep, jnp.sum(partner) > q - 1


def drop_outliers(a_i, a_j, match, tol, min_keep: int):
    """Unmatch the pairs whose edges disagree with the other pairs (step 3).

    Repeatedly, the matched vertex with the largest median edge residual ``|A_I(i, k) − A_J(π(i),
    π(k))|`` over the other matched vertices k is unmatched while that median exceeds ``tol``, and
    while more than ``min_keep`` pairs remain (a wrong pair's edges disagree with nearly all the
    others; a right pair's agree with every other right one).

    Args:
        a_i: (P, P) image adjacency (deg). a_j: (Q, Q) database adjacency (deg).
        match: (P,) int32 database vertex per image vertex (−1 none). tol: () deg.
        min_keep: static, stop at this many pairs.

    Returns:
        (P,) int32 the match with the outliers set to −1.
    """
    p = match.shape[0]
    mj = jnp.clip(match, 0, a_j.shape[0] - 1)
    resid = jnp.abs(a_i - a_j[mj[:, None], mj[None, :]])
    off = ~jnp.eye(p, dtype=bool)

    def medians(used):
        both = used[:, None] & used[None, :] & off
        rows = jnp.sort(jnp.where(both, resid, jnp.inf), axis=1)
        count = jnp.sum(both, axis=1)
        med = jnp.take_along_axis(rows, jnp.maximum(count - 1, 0)[:, None] // 2, axis=1)[:, 0]
        return jnp.where(used & (count > 0), med, -jnp.inf)

    def cond(carry):
        used, _ = carry
        med = medians(used)
        return (jnp.max(med) > tol) & (jnp.sum(used) > min_keep)

    def body(carry):
        used, t = carry
        worst = jnp.argmax(medians(used))
        return used.at[worst].set(False), t + 1

    used, _ = jax.lax.while_loop(cond, body, (match >= 0, 0))
    return jnp.where(used, match, -1).astype(jnp.int32)


def grow_match(a_i, mask_i, a_j, mask_j, match, tol):
    """Pair the unmatched image vertices that agree with the matched ones (step 3, after
    :func:`drop_outliers`).

    In vertex order, an unmatched image vertex i is paired with the free database vertex j whose
    edges to every matched pair (k, π(k)) agree within ``tol``, the one of least Σ_k residual² when
    several do. Why: the greedy binarization pairs every image vertex, and a vertex it paired wrongly
    (with a database vertex of no image partner, chosen before its true partner) is unmatched by the
    outlier removal, its true partner still free.

    Args:
        a_i: (P, P) deg; mask_i: (P,) bool. a_j: (Q, Q) deg; mask_j: (Q,) bool.
        match: (P,) int32 (−1 unmatched). tol: () deg.

    Returns:
        (P,) int32 the grown match.
    """
    p, q = a_i.shape[0], a_j.shape[0]

    def body(i, match):
        used = match >= 0
        mj = jnp.clip(match, 0, q - 1)
        resid = a_i[i][None, :] - a_j[:, mj]  # (Q, P): database vertex j against matched vertices k
        resid = jnp.where(used[None, :], resid, 0.0)
        taken = jnp.zeros((q,), bool).at[mj].max(used)
        fits = mask_j & ~taken & jnp.all(jnp.abs(resid) <= tol, axis=1)
        cost = jnp.where(fits, jnp.sum(resid * resid, axis=1), jnp.inf)
        j = jnp.argmin(cost)
        take = mask_i[i] & ~used[i] & jnp.isfinite(cost[j]) & jnp.any(used)
        return match.at[i].set(jnp.where(take, j, match[i]).astype(jnp.int32))

    return jax.lax.fori_loop(0, p, body, match)


def partial_match(a_i, mask_i, a_j, mask_j, *, c, tol, n_iter: int, power_tol: float, min_matched: int):
    """Spectral matching with unmatched vertices allowed on both sides (step 3).

    Args:
        a_i: (P, P) image adjacency (deg); mask_i: (P,) bool. a_j: (Q, Q) database adjacency (deg);
            mask_j: (Q,) bool. c: eq. 2 adjustor (1/deg). tol: edge-residual tolerance (deg).
        n_iter, power_tol: the power iteration's (:func:`~.matching.principal_eigenvector`).
        min_matched: fewer pairs → infinite error.

    Returns:
        ``(match, error)``: (P,) int32 database vertex per image vertex (−1 none), () eq. 5 over the
        remaining pairs (deg; +inf below ``min_matched``).
    """
    gamma = affinity_eigenvector(a_i, mask_i, a_j, mask_j, c, n_iter, power_tol)
    match = drop_outliers(a_i, a_j, greedy_binarize(gamma, mask_i, mask_j), tol, min_matched)
    match = grow_match(a_i, mask_i, a_j, mask_j, match, tol)
    return match, matching_error(a_i, a_j, match, min_matched)


def rank_candidates(a_i, n_i, plane_i, radii_db, db_adj, db_plane, db_n, *, radius, tol, screen_tol,
                    c, max_error, fraction, n_candidates: int, n_matchings: int, partners: int,
                    hypotheses: int, n_iter: int, power_tol: float, min_matched: int, extra: int):
    """Steps 1–4 for one image graph: the ``n_matchings`` candidates matched, best first.

    Args:
        a_i: (P, P) image adjacency (deg). n_i: () vertices. plane_i: (P, 2) plane coordinates (deg).
        radii_db: (D, K) :func:`radii_table`. db_adj: (D, K, K) deg. db_plane: (D, K, 2) deg.
        db_n: (D,) vertex counts. radius: the database's r (deg). tol, screen_tol, c, max_error
        (deg, 1/deg): ``Config``'s ``subgraph.tol_deg``, ``screen.tol_deg``, ``c``,
        ``max_error_deg``. fraction: ``screen.fraction``. extra: static, the cut graph holds
        P + ``extra`` vertices. The rest static: ``Config``'s fields of the same meaning.

    Returns:
        ``(rows, match, error, pairs, accepted, cut)``: (M,) int32 database rows, best first; (M, P)
        int32 database vertex (of the whole graph) per image vertex; (M,) δ (deg); (M,) int32 pairs;
        (M,) bool accepted; (M,) bool the cut graph was cut further (:func:`partner_vertices`).
    """
    p = a_i.shape[0]
    q = min(p + extra, db_adj.shape[1])
    mask_i = jnp.arange(p) < n_i
    r_i = a_i[0]
    valid_i = mask_i & (jnp.arange(p) > 0)
    votes = radial_votes(r_i, valid_i, radii_db, tol)
    # votes a graph of n_J vertices gets by chance: its n_J − 1 neighbors spread uniformly over the
    # circle's disc put one within tol of radius r with probability ≈ 4·r·tol / R² each
    per_star = jnp.where(valid_i, 4.0 * tol * r_i / radius**2, 0.0)
    chance = jnp.sum(-jnp.expm1(-(db_n[:, None] - 1).astype(jnp.float32) * per_star[None, :]), axis=1)
    _, cand = jax.lax.top_k(votes - chance, n_candidates)
    kmask = jnp.arange(db_adj.shape[1])[None, :] < db_n[cand][:, None]
    take, keep, cut = jax.vmap(partner_vertices, in_axes=(None, None, 0, 0, None, None))(
        r_i, valid_i, db_adj[cand, 0], kmask, tol, q)
    n_cut = jnp.sum(keep, axis=1)
    plane_cut = jnp.take_along_axis(db_plane[cand], take[:, :, None], axis=1)
    support = jax.vmap(functools.partial(triangle_support, tol=screen_tol, partners=partners,
                                         hypotheses=hypotheses), in_axes=(None, None, 0, 0))(
        plane_i, n_i, plane_cut, n_cut)
    # the most support first; its ties go to more votes
    _, best = jax.lax.top_k(support * (n_i + 1) + votes[cand], n_matchings)
    rows, take, keep, cut = cand[best], take[best], keep[best], cut[best]

    def one(row, take, keep):
        a_j = jnp.where(keep[:, None] & keep[None, :], db_adj[row][take[:, None], take[None, :]], 0.0)
        match, err = partial_match(a_i, mask_i, a_j, keep, c=c, tol=screen_tol, n_iter=n_iter,
                                   power_tol=power_tol, min_matched=min_matched)
        pairs = jnp.sum(match >= 0)
        need = jnp.maximum(min_matched, jnp.ceil(fraction * jnp.minimum(n_i, jnp.sum(keep))))
        ok = (err <= max_error) & (match[0] == 0) & (pairs >= need)
        return jnp.where(match >= 0, take[jnp.clip(match, 0, q - 1)], -1), err, pairs, ok

    match, err, pairs, ok = jax.vmap(one)(rows, take, keep)
    # accepted first, then more pairs, then smaller δ
    order = jnp.lexsort((err, -pairs, ~ok))
    return (rows[order].astype(jnp.int32), match[order], err[order], pairs[order].astype(jnp.int32),
            ok[order], cut[order])


def _rank_scenes(a_i, n_i, plane_i, radii_db, db_adj, db_plane, db_n, radius, tol, screen_tol, c,
                 max_error, fraction, **static):
    """:func:`rank_candidates` of a batch of image graphs (``vmap``), as :func:`map_batch` splits them."""
    fn = functools.partial(rank_candidates, radius=radius, tol=tol, screen_tol=screen_tol, c=c,
                           max_error=max_error, fraction=fraction, **static)
    return jax.vmap(fn, in_axes=(0, 0, 0, None, None, None, None))(
        a_i, n_i, plane_i, radii_db, db_adj, db_plane, db_n)


_rank_scenes_jit = stored_jit(_rank_scenes, static_argnames=(
    "n_candidates", "n_matchings", "partners", "hypotheses", "n_iter", "power_tol", "min_matched",
    "extra"))


def subgraph_search(db, graphs: ImageGraph, usable: np.ndarray, config) -> Ranking:
    """Steps 1–4 for a batch of image graphs (host side).

    Scenes are grouped by their image graph's padded size P (``size_bucket``) and run in chunks
    whose affinity matrices fit ``matching.memory_budget_mb`` (``subgraph.matchings`` × (P·Q)² floats per
    scene, Q = P + ``size_bucket`` the cut graph's size).

    Args:
        db: :class:`~.database.Database`. graphs: NumPy :class:`~.graph.ImageGraph` (B, K, …).
        usable: (B,) bool scenes to search. config: :class:`~.config.Config` with ``subgraph``.

    Returns:
        :class:`Ranking` (``match`` padded to the image capacity K).
    """
    b, k = graphs.mask.shape
    m = int(min(config.subgraph.matchings, config.subgraph.candidates))
    out = Ranking(rows=np.full((b, m), -1, np.int32), match=np.full((b, m, k), -1, np.int32),
                  error=np.full((b, m), np.inf, np.float32), pairs=np.zeros((b, m), np.int32),
                  ok=np.zeros((b, m), bool), cut=np.zeros((b, m), bool))
    todo = np.nonzero(usable)[0]
    if not todo.size:
        return out
    bucket = int(config.size_bucket)
    sizes = np.minimum(k, np.maximum(bucket, -(-graphs.n[todo] // bucket) * bucket))
    tables = on_every_device(db, "subgraph", lambda: (
        jnp.asarray(radii_table(db)), jnp.asarray(db.adj), jnp.asarray(db.plane), jnp.asarray(db.n)))
    static = dict(n_candidates=int(min(config.subgraph.candidates, len(db))), n_matchings=m,
                  partners=int(config.screen.partners), hypotheses=int(config.screen.hypotheses),
                  n_iter=int(config.matching.power_iterations), power_tol=float(config.matching.power_tol),
                  min_matched=int(config.min_matched), extra=bucket)
    scalars = tuple(jnp.float32(v) for v in (db.radius_deg, config.subgraph.tol_deg,
                                             config.screen.tol_deg, config.c, config.max_error_deg,
                                             config.screen.fraction))
    for p in np.unique(sizes):
        p = int(p)
        group = todo[sizes == p]
        q = min(k, p + bucket)
        per_scene = m * (p * q) ** 2 * 4 * 3  # the affinity and two temporaries of its size
        chunk = 1 << int(np.clip(np.log2(config.matching.memory_budget_mb * 2**20 / per_scene), 0, 6))
        for lo in range(0, group.size, chunk):
            rows = group[lo:lo + chunk]
            fill = padded_indices(rows, floor=chunk)  # chunk: a power of two ≥ rows.size
            res = map_batch(_rank_scenes_jit, (jnp.asarray(graphs.adj[fill, :p, :p]),
                                               jnp.asarray(graphs.n[fill]),
                                               jnp.asarray(graphs.plane[fill, :p])),
                            (*tables, *scalars), static=static)
            r, mt, e, pr, okk, ct = (np.asarray(a)[:rows.size] for a in res)
            out.rows[rows], out.error[rows], out.pairs[rows] = r, e, pr
            out.ok[rows], out.cut[rows] = okk, ct
            out.match[rows, :, :p] = mt
    return out
