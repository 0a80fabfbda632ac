"""Exact lower bounds on the matching error δ (eq. 5) that hold for every vertex correspondence.

Not in the paper. Algorithm 1 only returns a candidate with δ ≤ ε_δ, and one with δ > ε_δ is neither
a level's first success nor the argmin of a successful level, so a candidate whose δ *provably*
exceeds ε_δ is skipped without changing the outcome (:mod:`.search`, branch and bound).

Row bound (:func:`error_lower_bound`): with m = min(n_I, n_J), S the smaller graph, L the other
(s = n_L − m extra vertices) and π the one-to-one map of S into L,

    (m·δ)² = Σ_{i ∈ S} Σ_{k ∈ S, k ≠ i} (A_S(i,k) − A_L(π(i), π(k)))²  ≥  min_π Σ_i C(i, π(i)),

C(i, j) the cheapest monotone assignment of sorted row i of A_S into sorted row j of A_L (a dynamic
programme over the skips 0 … s); the assignment problem is bounded by its Lagrangian dual
(:func:`_assignment_bound`), and when n_I = n_J also by ``Σ_{j ∈ L} min_i C(i, j)``. s = 0 gives
the sorted-row distance; s > ``max_skip`` gives 0. Edge bound (:func:`edge_lower_bound`): sorted
edge lengths; looser, any s, about a tenth of the cost. Both read tables sorted once
(:func:`row_table`, :func:`sorted_edges`). Derivation, yield and the bounds tried: docs/design/sgm.md.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["sorted_rows", "row_table", "error_lower_bound", "sorted_edges", "edge_lower_bound"]


def _array_module(x):
    """NumPy for host arrays (its sort is several times faster than XLA:CPU's), else ``jax.numpy``."""
    return np if isinstance(x, np.ndarray) else jnp


def sorted_rows(adj, mask):
    """Rows of a padded adjacency without the diagonal, each sorted ascending, +inf padded.

    Args:
        adj: (..., K, K) adjacency (deg). mask: (..., K) bool vertices. NumPy arrays give a NumPy
            result (the same values: sorting is exact).

    Returns:
        (..., K, K − 1) float32: row i holds its n − 1 edge lengths first (ascending), then +inf; rows of
        padding vertices are all +inf.
    """
    xp = _array_module(adj)
    k = adj.shape[-1]
    off = (~xp.eye(k, dtype=bool)).reshape((1,) * (mask.ndim - 1) + (k, k))
    keep = mask[..., :, None] & mask[..., None, :] & off
    rows = xp.sort(xp.where(keep, adj, xp.float32(xp.inf)), axis=-1)
    return rows[..., : k - 1].astype(xp.float32)


def row_table(adj, mask):
    """:func:`sorted_rows` padded with one more +inf column to a square (..., K, K) table.

    Sorting is the dearest part of the row bound on a CPU and does not depend on the candidate, so the
    search sorts every graph once and reads this table. Square like the adjacency: the ``r × r`` corner
    of a graph of ≤ r vertices holds its rows whole (the first r − 1 columns are :func:`sorted_rows` at
    size r).

    Args:
        adj: (..., K, K) adjacency (deg). mask: (..., K) bool vertices.

    Returns:
        (..., K, K) float32.
    """
    xp = _array_module(adj)
    rows = sorted_rows(adj, mask)
    return xp.concatenate([rows, xp.full(rows.shape[:-1] + (1,), xp.inf, rows.dtype)], axis=-1)


def _row_cost(short, long, n_short, max_skip: int):
    """Cheapest monotone injective assignment of each short row into each long row.

    Args:
        short: (P, R) sorted rows with ``n_short`` finite entries each (R ≥ n_short).
        long: (Q, R) sorted rows with n_short + s finite entries.
        n_short: () int number of entries of a short row (m − 1).
        max_skip: static s_max; long entries beyond n_short + max_skip are never reached.

    Returns:
        (P, Q) Σ (short_t − long_{t+u_t})² minimised over non-decreasing skips 0 ≤ u_t ≤ max_skip.
    """
    r = short.shape[-1]
    big = jnp.asarray(jnp.inf, jnp.float32)
    # pad so that entry t + u is always in range
    long_pad = jnp.concatenate([long, jnp.full((long.shape[0], max_skip + 1), big)], axis=-1)

    def step(t, d):
        # d[u]: (P, Q) cost of the first t entries with short entry t − 1 on long entry t − 1 + u
        x = short[:, t][:, None]
        y = jax.lax.dynamic_slice_in_dim(long_pad, t, max_skip + 1, axis=1)  # (Q, s+1)
        out, best = [], big
        for u in range(max_skip + 1):  # unrolled: (P, Q) planes vectorize well, the u axis is tiny
            best = jnp.minimum(best, d[u])  # non-decreasing skips: min over u' ≤ u
            out.append((x - y[None, :, u]) ** 2 + best)
        return jnp.stack(out)

    zeros = jnp.zeros((short.shape[0], long.shape[0]), jnp.float32)
    d0 = jnp.stack([zeros] + [zeros + big] * max_skip)
    # n_short steps, not R: looping over all R columns gives the same (bitwise) result in 1.3–2× the
    # time; an unrolled loop fuses into one kernel but compiles far longer (docs/design/sgm.md)
    d = jax.lax.fori_loop(0, jnp.minimum(n_short, r), step, d0)
    return jnp.min(d, axis=0)


def _assignment_bound(cost, rows, cols, square, n_iter: int):
    """Lower bound on min Σ_i cost(i, π(i)) over one-to-one π from ``rows`` into ``cols``.

    Lagrangian relaxation of the column constraints: for any prices w (w ≥ 0 when columns may stay
    unused; free when all are used, ``square``), ``Σ_i min_j (cost(i, j) + w_j) − Σ_j w_j`` is a lower
    bound (weak duality). w = 0 gives the row minima; ``n_iter`` subgradient steps ``s₀/√(t + 1)``
    (s₀ = half the mean row minimum; a row "chooses" every column at its minimum) tighten it, and the
    best iterate is returned (every iterate is valid). 20 steps prune about as much as the exact
    optimum would (docs/design/sgm.md).

    Args:
        cost: (P, Q) non-negative costs (+inf allowed off ``cols``). rows: (P,) bool rows to assign.
        cols: (Q,) bool available columns. square: () bool, every column must be used.
        n_iter: static number of subgradient steps.

    Returns:
        () the bound.
    """
    c = jnp.where(rows[:, None] & cols[None, :], cost, jnp.inf)
    row_min = jnp.min(c, axis=1)
    scale = 0.5 * jnp.sum(jnp.where(rows, row_min, 0.0)) / jnp.maximum(jnp.sum(rows), 1)
    n_cols = cost.shape[1]

    def body(t, carry):
        w, best = carry
        red = c + w[None, :]
        least = jnp.min(red, axis=1, keepdims=True)
        value = jnp.sum(jnp.where(rows, least[:, 0], 0.0)) - jnp.sum(jnp.where(cols, w, 0.0))
        best = jnp.maximum(best, value)
        demand = jnp.sum((red == least) & rows[:, None], axis=0).astype(cost.dtype)
        w = w + scale / jnp.sqrt(t + 1.0) * (demand - 1.0)
        w = jnp.where(square, w, jnp.maximum(w, 0.0))
        return jnp.where(cols, w, 0.0), best

    _, best = jax.lax.fori_loop(0, n_iter, body, (jnp.zeros((n_cols,), cost.dtype),
                                                 jnp.asarray(0.0, cost.dtype)))
    return best


def error_lower_bound(rows_i, n_i, rows_j, n_j, *, max_skip: int, n_dual: int = 20):
    """Lower bound on δ_{I,J} of eq. 5 valid for every one-to-one correspondence of min(n_I, n_J) pairs.

    Args:
        rows_i: (R + 1, R) :func:`sorted_rows` of the image graph (padded to R + 1 vertices).
        n_i: () int image vertex count.
        rows_j: (R + 1, R) sorted rows of the database graph, same padding.
        n_j: () int database vertex count.
        max_skip: static; candidates with |n_I − n_J| > max_skip get bound 0.
        n_dual: static subgradient steps of the assignment bound (:func:`_assignment_bound`).

    Returns:
        () float32 bound on δ (deg); 0 when |n_I − n_J| > ``max_skip`` or m < 2.
    """
    i_small = n_i <= n_j
    short = jnp.where(i_small, rows_i, rows_j)
    long = jnp.where(i_small, rows_j, rows_i)
    m = jnp.minimum(n_i, n_j)
    s = jnp.abs(n_i - n_j)
    cost = _row_cost(short, long, m - 1, max_skip)  # (R+1, R+1)
    # short-side vertices are its first m rows; long-side rows beyond n_L are padding (+inf rows)
    used = jnp.arange(short.shape[0]) < m
    cols = jnp.arange(short.shape[0]) < jnp.maximum(n_i, n_j)
    total = _assignment_bound(cost, used, cols, s == 0, n_dual)
    # equal vertex counts: every long-side vertex is matched too, so its column minimum also counts
    col_min = jnp.sum(jnp.where(used, jnp.min(jnp.where(used[:, None], cost, jnp.inf), axis=0), 0.0))
    total = jnp.where(s == 0, jnp.maximum(total, col_min), total)
    bound = jnp.sqrt(jnp.maximum(total, 0.0)) / jnp.maximum(m, 1)
    return jnp.where((s <= max_skip) & (m >= 2) & jnp.isfinite(bound), bound, 0.0)


def sorted_edges(adj, mask):
    """Edge lengths of a padded complete graph, each graph's list sorted ascending, +inf padded.

    Args:
        adj: (..., K, K) adjacency (deg). mask: (..., K) bool vertices.

    Returns:
        (..., K(K − 1)/2) float32: the n(n − 1)/2 edges between valid vertices first, then +inf.
    """
    xp = _array_module(adj)
    iu, ju = np.triu_indices(adj.shape[-1], 1)
    keep = mask[..., iu] & mask[..., ju]
    return xp.sort(xp.where(keep, adj[..., iu, ju], xp.float32(xp.inf)), axis=-1).astype(xp.float32)


def edge_lower_bound(edges_i, n_i, edges_j, n_j):
    """A looser, much cheaper lower bound on δ_{I,J} of eq. 5 than :func:`error_lower_bound`.

    Eq. 5 sums over ordered pairs: ``(m·δ)² = 2 Σ_{e ∈ E_S} (a_e − b_{π(e)})²`` with distinct edges of S
    on distinct edges of L. Dropping distinctness, each term is ≥ the squared distance from a_e to the
    nearest edge length of L (binary search). When n_I = n_J the edge multisets match one to one and
    the sorted order is the cheapest matching (tighter). O(E log E), E = n(n − 1)/2, any |n_I − n_J|;
    the search's first stage (:func:`~.search.advance_search`).

    Args:
        edges_i: (E,) :func:`sorted_edges` of the image graph. n_i: () int its vertex count.
        edges_j: (E,) sorted edges of the database graph, same padding. n_j: () int.

    Returns:
        () float32 bound on δ (deg); 0 when m < 2.
    """
    i_small = n_i <= n_j
    short = jnp.where(i_small, edges_i, edges_j)
    long = jnp.where(i_small, edges_j, edges_i)
    m = jnp.minimum(n_i, n_j)
    used = jnp.isfinite(short)
    # nearest edge of L to each edge of S: its neighbours in L's sorted list (+inf tail never wins)
    at = jnp.searchsorted(long, short)
    below = long[jnp.maximum(at - 1, 0)]
    above = long[jnp.minimum(at, long.shape[0] - 1)]
    nearest = jnp.minimum(jnp.abs(short - below), jnp.abs(above - short))
    gap = jnp.where(n_i == n_j, short - long, nearest)
    total = 2.0 * jnp.sum(jnp.where(used, gap * gap, 0.0))
    return jnp.where(m >= 2, jnp.sqrt(total) / jnp.maximum(m, 1), 0.0).astype(jnp.float32)
