"""Spectral graph matching of two neighbor graphs (You et al. 2022, "Spectral graph matching").

For an image graph G_I (P ≥ n_I vertex slots) and a database graph G_J (Q ≥ n_J):

1. affinity K (eq. 2), (P·Q, P·Q), index ``ij = i·Q + j``: ``K(ij, km) = exp(−c |A_I(i,k) −
   A_J(j,m)|)`` for i ≠ k and j ≠ m; 0 on the diagonal (vertex similarity 0 in the paper), for
   conflicting pairs (i = k xor j = m) and on padding;
2. its unit principal (Perron) eigenvector γ by power iteration;
3. greedy one-to-one binarization of γ (Leordeanu & Hebert 2005): min(n_I, n_J) pairs;
4. matching error eq. 5, ``‖A'_I − A_J‖_F / min(n_I, n_J)`` over the matched sub-graphs.

K has (P·Q)² entries, read by every power step: the paper's n⁴ growth (conventions §7, SGM pitfall
4). :func:`spectral_match` builds them from e^{±c·a} factors (:func:`affinity_eigenvector`);
:func:`affinity` and :func:`principal_eigenvector` are the written-out reference. Callers pad P, Q
to small buckets and bound the batch.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from jstarid.geometry import precise

__all__ = ["affinity", "principal_eigenvector", "affinity_eigenvector", "greedy_binarize",
           "matching_error", "spectral_match"]


def affinity(a_i, mask_i, a_j, mask_j, c: float):
    """Affinity matrix of eq. 2.

    ``exp(−c|a − b|) = min(e^{c a}·e^{−c b}, e^{−c a}·e^{c b})``: P² + Q² exponentials instead of (P·Q)².
    Exponents are taken about a common centre, so e^{±c·a} stays in float32 range for
    c·(largest edge) up to ≈ 170.

    Args:
        a_i: (P, P) image adjacency (deg). mask_i: (P,) bool image vertices.
        a_j: (Q, Q) database adjacency (deg). mask_j: (Q,) bool database vertices.
        c: edge-similarity adjustor (1/deg).

    Returns:
        (P·Q, P·Q) float32 symmetric non-negative matrix, index ``i·Q + j``.
    """
    p, q = a_i.shape[0], a_j.shape[0]
    up_i, dn_i, up_j, dn_j = _affinity_factors(a_i, mask_i, a_j, mask_j, c)
    return _affinity_block(up_i, dn_i, up_j, dn_j).reshape(p * q, p * q).astype(jnp.float32)


def _affinity_factors(a_i, mask_i, a_j, mask_j, c):
    """``e^{±c(a − centre)}`` of both graphs, 0 on the diagonal and padding (:func:`affinity`)."""
    p, q = a_i.shape[0], a_j.shape[0]
    keep_i = mask_i[:, None] & mask_i[None, :] & ~jnp.eye(p, dtype=bool)
    keep_j = mask_j[:, None] & mask_j[None, :] & ~jnp.eye(q, dtype=bool)
    # half the mean largest edge: exponents stay within ±c·(largest edge)/2
    centre = 0.25 * (jnp.max(jnp.where(keep_i, a_i, 0.0)) + jnp.max(jnp.where(keep_j, a_j, 0.0)))
    up_i = jnp.where(keep_i, jnp.exp(c * (a_i - centre)), 0.0)
    dn_i = jnp.where(keep_i, jnp.exp(-c * (a_i - centre)), 0.0)
    up_j = jnp.where(keep_j, jnp.exp(c * (a_j - centre)), 0.0)
    dn_j = jnp.where(keep_j, jnp.exp(-c * (a_j - centre)), 0.0)
    return up_i, dn_i, up_j, dn_j


def _affinity_block(up_i, dn_i, up_j, dn_j):
    """K as a (P, Q, P, Q) array, entry (i, j, k, m): edge ik of G_I against edge jm of G_J; the zeros
    of up/dn give the zero rows/columns (diagonal, conflicting pairs, padding).
    """
    return jnp.minimum(up_i[:, None, :, None] * dn_j[None, :, None, :],
                       dn_i[:, None, :, None] * up_j[None, :, None, :])


def principal_eigenvector(k, n_iter: int, tol: float = 0.0):
    """Unit principal eigenvector of a symmetric non-negative matrix by power iteration.

    Starts from the uniform vector (not orthogonal to the Perron vector); iterates stay non-negative.
    A zero matrix gives the zero vector.

    Args:
        k: (M, M) symmetric, non-negative.
        n_iter: static largest number of steps.
        tol: stop once no entry changed by more than ``tol`` in a step (0: always ``n_iter``). Under
            ``vmap`` a lane that stopped keeps its vector, so batched and single calls agree.

    Returns:
        (M,) non-negative unit vector (or zeros).
    """
    return _power_iteration(lambda x: precise.matmul(k, x), (k.shape[0],), n_iter, tol)


def _power_iteration(apply, shape, n_iter, tol):
    """``x ← K x / ‖K x‖`` from the uniform unit vector of ``shape``; ``apply(x)`` = K x; early stop and
    zero matrix as in :func:`principal_eigenvector`.
    """
    def cond(carry):
        t, _, change = carry
        return (t < n_iter) & (change > tol)

    def body(carry):
        t, x, _ = carry
        y = apply(x)
        norm = jnp.linalg.norm(y)
        y = jnp.where(norm > 0, y / jnp.where(norm > 0, norm, 1.0), 0.0)
        return t + 1, y, jnp.max(jnp.abs(y - x))

    x0 = jnp.full(shape, 1.0 / jnp.sqrt(math.prod(shape)), jnp.float32)
    _, x, _ = jax.lax.while_loop(cond, body, (0, x0, jnp.asarray(jnp.inf, jnp.float32)))
    return x


def affinity_eigenvector(a_i, mask_i, a_j, mask_j, c: float, n_iter: int, tol: float = 0.0):
    """:func:`principal_eigenvector` of :func:`affinity`, K's entries made from the factors.

    Written as if each step recomputed the entries it sums (``y(ij) = Σ_km K(ij, km) x(km)``); XLA on
    CPU hoists the (P, Q, P, Q) block out of the loop, so K is written once per pair. Same steps,
    matches and errors as the reference; cheaper (docs/design/sgm.md).

    Args:
        a_i, mask_i, a_j, mask_j, c: as :func:`affinity`.
        n_iter, tol: as :func:`principal_eigenvector`.

    Returns:
        (P, Q) non-negative confidences γ(ij), unit norm (or zeros).
    """
    up_i, dn_i, up_j, dn_j = _affinity_factors(a_i, mask_i, a_j, mask_j, c)

    def apply(x):  # (P, Q) → (P, Q): Σ_km K(ij, km) x(km), K's entries made as they are summed
        return jnp.sum(_affinity_block(up_i, dn_i, up_j, dn_j) * x[None, None], axis=(2, 3))

    return _power_iteration(apply, (a_i.shape[0], a_j.shape[0]), n_iter, tol)


def greedy_binarize(conf, mask_i, mask_j):
    """Greedy one-to-one assignment: take the largest remaining confidence, fix the pair, drop its row
    and column.

    Computed in rounds: every pair that is the maximum of both its row and its column among the
    remaining entries is fixed at once — the same assignment, since under the strict order (confidence
    descending, flat index ``i·Q + j`` ascending; ``argmax`` takes the first maximum) no earlier entry
    can take such a pair's row or column. Each round fixes at least one pair (≤ min(P, Q) rounds).

    Args:
        conf: (P, Q) confidences γ(ij) ≥ 0.
        mask_i: (P,) bool image vertices. mask_j: (Q,) bool database vertices.

    Returns:
        (P,) int32: the database vertex matched to each image vertex, −1 if none. Exactly
        min(n_I, n_J) image vertices are matched. Ties go to the smaller flat index ``i·Q + j``.
    """
    p, q = conf.shape
    neg = jnp.asarray(-jnp.inf, conf.dtype)
    valid = mask_i[:, None] & mask_j[None, :]

    def cond(carry):
        _, live_i, live_j = carry
        return jnp.any(valid & live_i[:, None] & live_j[None, :])

    def body(carry):
        match, live_i, live_j = carry
        score = jnp.where(valid & live_i[:, None] & live_j[None, :], conf, neg)
        best_j = jnp.argmax(score, axis=1)  # (P,) first maximum of each row
        best_i = jnp.argmax(score, axis=0)  # (Q,) first maximum of each column
        fixed = (best_i[best_j] == jnp.arange(p)) & jnp.isfinite(jnp.max(score, axis=1))
        match = jnp.where(fixed, best_j.astype(jnp.int32), match)
        taken_j = jnp.zeros((q,), bool).at[best_j].max(fixed)
        return match, live_i & ~fixed, live_j & ~taken_j

    match, _, _ = jax.lax.while_loop(
        cond, body, (jnp.full((p,), -1, jnp.int32), jnp.ones((p,), bool), jnp.ones((q,), bool)))
    return match


def matching_error(a_i, a_j, match, min_matched: int = 1):
    """Matching error eq. 5 on the matched sub-graphs.

    Args:
        a_i: (P, P) image adjacency (deg). a_j: (Q, Q) database adjacency (deg).
        match: (P,) int32 database vertex of each image vertex (−1 unmatched).
        min_matched: fewer matched pairs than this → +inf.

    Returns:
        () ``‖A'_I − A_J(π, π)‖_F / n_matched`` (deg), +inf when fewer than ``min_matched`` pairs.
    """
    used = match >= 0
    mj = jnp.clip(match, 0, a_j.shape[0] - 1)
    a_j_perm = a_j[mj[:, None], mj[None, :]]
    both = used[:, None] & used[None, :]
    d = jnp.where(both, a_i - a_j_perm, 0.0)
    n = jnp.sum(used)
    err = jnp.sqrt(jnp.sum(d * d)) / jnp.maximum(n, 1)
    return jnp.where(n >= min_matched, err, jnp.inf)


def spectral_match(a_i, mask_i, a_j, mask_j, *, c: float, n_iter: int, min_matched: int = 1,
                   tol: float = 0.0):
    """Match two padded neighbor graphs (eqs. 2–5).

    Args:
        a_i: (P, P) image adjacency (deg); mask_i: (P,) bool.
        a_j: (Q, Q) database adjacency (deg); mask_j: (Q,) bool.
        c: eq. 2 adjustor (1/deg). n_iter: largest number of power-iteration steps. min_matched: see
            :func:`matching_error`. tol: early stop of the power iteration
            (:func:`principal_eigenvector`).

    Returns:
        ``(match, error)``: (P,) int32 database vertex per image vertex (−1 none), () error (deg).
    """
    gamma = affinity_eigenvector(a_i, mask_i, a_j, mask_j, c, n_iter, tol)
    match = greedy_binarize(gamma, mask_i, mask_j)
    return match, matching_error(a_i, a_j, match, min_matched)
