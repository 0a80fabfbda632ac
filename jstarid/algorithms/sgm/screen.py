"""Triangle screen: a cheap test that a database graph can be the image graph (not in the paper).

Most candidates that Algorithm 1 matches under noise fail by far (δ = 5–7.5 ε_δ; docs/design/sgm.md),
and the exact bounds of :mod:`.bound` cannot exclude them, because a bound on a sum of squared edge
residuals over an unknown correspondence is weak. The screen asks a sharper, local question: is
there one rotation about the main star that takes most of the image neighbors onto database
neighbors, each within ``tol``? Each agreeing neighbor k closes an oriented triangle (main, i, k)
with the hypothesis' star i that matches (main, j, l). In the true graph every star present on both
sides agrees (apart from noise beyond ``tol``); in a wrong graph a neighbor agrees by chance with
probability ≈ (partners within ``tol`` in radius) × (2·tol / r_k) / 2π, a few per cent, so the
best rotation explains far fewer (docs/design/sgm.md, Triangle screen).

Work per candidate, with P, Q the padded vertex counts, m partners per vertex and H hypotheses:
each image neighbor's m database neighbors of nearest radius (a (P, Q) difference and a top-m), then
(H, m, P, m) angle comparisons — O(P·Q + H·m²·P), against the spectral matching's O((PQ)²)
affinity and power steps.

The screen is a heuristic, not a bound: it can reject the true graph (when fewer than
``screen_fraction`` of the smaller graph's vertices survive, e.g. most stars crossed the circle;
the spectral matching's δ would then rarely pass ε_δ either), so it is off in ``Config.paper()``
and its effect is measured side by side (experiments/RESULTS.md, Throughput).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.runtime import map_batch
from jstarid.runtime.padding import power_of_two_chunks
from jstarid.runtime.program_store import stored_jit

__all__ = ["triangle_support", "screen_pass", "screen_pairs"]

MIN_CALL_PAIRS = 64  # smallest compiled pair count (as the search's other pair kernels)


def triangle_support(plane_i, n_i, plane_j, n_j, *, tol, partners: int, hypotheses: int):
    """Size of the largest rotation-consistent correspondence the screen finds between two graphs.

    Every image neighbor k gets the m database neighbors l of nearest radius (within ``tol``); each
    such pair implies a rotation about the main star θ_kl = φ_l − φ_k, known to ≈ tol / r_k rad. A
    hypothesis is one pair (i, j) of the first H image neighbors (vertex order: the brightest in a
    scene) that lie at least 4·tol from the main star; a neighbor k ≠ i supports it when one of its
    pairs (k, l ≠ j) implies the same rotation within tol / r_i + tol / r_k — the rotation that takes
    i onto j then takes k to within ≈ tol·(1 + r_k / r_i) of l.

    Args:
        plane_i: (P, 2) image :func:`~.graph.plane_coords` (deg; vertex 0 the main star at the
            origin). n_i: () its vertex count.
        plane_j: (Q, 2) database graph's coordinates (deg). n_j: () its vertex count.
        tol: () position tolerance of one agreeing star (deg).
        partners: static m, database neighbors of nearest radius tried for each image neighbor.
        hypotheses: static H, image neighbors tried as the hypothesis' i.

    Returns:
        () int32: 2 + the most neighbors k that support one hypothesis (the main star, i and the
        k's: vertices of a consistent correspondence); 0 when no hypothesis can be formed.
    """
    p, q = plane_i.shape[0], plane_j.shape[0]
    m = min(partners, q - 1)
    h = min(hypotheses, p - 1)
    xi, xj = plane_i[1:], plane_j[1:]  # neighbors, (P − 1, 2) and (Q − 1, 2)
    vi = jnp.arange(1, p) < n_i
    vj = jnp.arange(1, q) < n_j
    r_i = jnp.hypot(xi[:, 0], xi[:, 1])
    r_j = jnp.hypot(xj[:, 0], xj[:, 1])
    gap = jnp.where(vi[:, None] & vj[None, :], jnp.abs(r_i[:, None] - r_j[None, :]), jnp.inf)
    neg_gap, part = jax.lax.top_k(-gap, m)  # (P − 1, m) database neighbors of nearest radius
    ok = -neg_gap <= tol
    phi_i = jnp.arctan2(xi[:, 1], xi[:, 0])
    phi_j = jnp.arctan2(xj[:, 1], xj[:, 0])
    rot = phi_j[part] - phi_i[:, None]  # (P − 1, m) rotation implied by each pair (rad)
    slack = tol / jnp.maximum(r_i, 1e-6)  # (P − 1,) its uncertainty (rad)
    eligible = vi & (r_i >= 4.0 * tol)
    hyp = jnp.argsort(~eligible, stable=True)[:h]  # the first H eligible neighbors
    d = rot[hyp][:, :, None, None] - rot[None, None, :, :]  # (H, m, P − 1, m)
    d = d - (2 * jnp.pi) * jnp.round(d / (2 * jnp.pi))
    agree = jnp.abs(d) <= slack[hyp][:, None, None, None] + slack[None, None, :, None]
    agree = agree & ok[None, None, :, :] & (part[None, None, :, :] != part[hyp][:, :, None, None])
    agree = agree & (jnp.arange(p - 1)[None, None, :, None] != hyp[:, None, None, None])  # k ≠ i
    support = jnp.sum(jnp.any(agree, axis=3), axis=2)  # (H, m)
    usable = ok[hyp] & eligible[hyp][:, None]
    best = jnp.max(jnp.where(usable, support, -2))
    return jnp.maximum(best + 2, 0).astype(jnp.int32)


def screen_pass(support, n_i, n_j, *, fraction: float, min_matched: int):
    """True where a candidate's triangle support reaches ``max(min_matched, ⌈fraction·min(n_i, n_j)⌉)``.

    Args:
        support: (...) int from :func:`triangle_support`. n_i, n_j: (...) vertex counts.
        fraction: share of the smaller graph's vertices that must be supported.
        min_matched: the spectral matching's own floor (``Config.min_matched``).
    """
    need = jnp.maximum(min_matched, jnp.ceil(fraction * jnp.minimum(n_i, n_j)))
    return support >= need


@functools.partial(stored_jit, static_argnames=("partners", "hypotheses", "fraction", "min_matched"))
def _screen_kernel(plane_i, n_i, plane_j, n_j, tol, *, partners, hypotheses, fraction, min_matched):
    """:func:`triangle_support` and :func:`screen_pass` of N pairs (``vmap``) → (N,) bool."""
    support = jax.vmap(functools.partial(triangle_support, tol=tol, partners=partners,
                                         hypotheses=hypotheses))(
        plane_i, n_i, plane_j, n_j)
    return screen_pass(support, n_i, n_j, fraction=fraction, min_matched=min_matched)


def screen_pairs(db, plane_i, n_i, scene, rows, config) -> np.ndarray:
    """Which (scene, candidate) pairs pass the triangle screen (host side, grouped by padded size).

    Args:
        db: the SGM database (``plane``, ``n``). plane_i: (B, K, 2) image graphs'
            :func:`~.graph.plane_coords` (deg). n_i: (B,) image vertex counts.
        scene, rows: (N,) scene and database row of each pair.
        config: :class:`~.config.Config` (``screen_tol_deg``, ``screen_fraction``,
            ``screen_partners``, ``screen_hypotheses``, ``min_matched``, ``size_bucket``).

    Returns:
        (N,) bool, True for the pairs to keep.
    """
    keep = np.ones(rows.size, bool)
    if not rows.size:
        return keep
    n_j = db.n[rows]
    bucket = int(config.size_bucket)
    size = np.maximum(-(-np.maximum(n_i[scene], n_j) // bucket) * bucket, bucket)
    plane_db = db.plane
    static = {"partners": int(config.screen_partners), "hypotheses": int(config.screen_hypotheses),
              "fraction": float(config.screen_fraction),
              "min_matched": int(config.min_matched)}
    pending = []
    for r in np.unique(size):
        group = np.nonzero(size == r)[0]
        # calls of power-of-two sizes with little padding; every call dispatched before any is read
        for lo, hi, padded in power_of_two_chunks(group.size, MIN_CALL_PAIRS):
            at = group[lo:hi]
            fill = np.concatenate([at, np.full(padded - at.size, at[0])])
            pending.append((at, map_batch(
                _screen_kernel, (jnp.asarray(plane_i[scene[fill], :r]), jnp.asarray(n_i[scene[fill]]),
                                 jnp.asarray(plane_db[rows[fill], :r]), jnp.asarray(n_j[fill])),
                (jnp.float32(config.screen_tol_deg),), static=static)))
    for at, out in pending:
        keep[at] = np.asarray(out)[:at.size]
    return keep
