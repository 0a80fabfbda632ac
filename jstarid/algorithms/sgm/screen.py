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
each image neighbor's m database neighbors of nearest radius (a (P, Q) comparison against the
database graph's radii, sorted once per database, and a window about the insertion point), then
(H, m, P, m) angle comparisons — O(P·Q + H·m²·P), against the spectral matching's O((PQ)²)
affinity and power steps.

The screen is a heuristic, not a bound: it can reject the true graph (when fewer than
``screen.fraction`` of the smaller graph's vertices survive, e.g. most stars crossed the circle;
the spectral matching's δ would then rarely pass ε_δ either), so it is off in ``Config.paper()``
and its effect is measured side by side (experiments/RESULTS.md, Throughput).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.runtime import device_cache, map_batch
from jstarid.runtime.padding import power_of_two_chunks
from jstarid.runtime.pairs import MIN_CALL_PAIRS
from jstarid.runtime.program_store import stored_jit

__all__ = ["hypothesis_neighbors", "nearest_partners", "neighbor_polar", "polar_support", "radius_order",
           "screen_pairs", "screen_pass", "triangle_support"]


def neighbor_polar(plane):
    """Polar coordinates of a graph's neighbors about its main star, read by :func:`polar_support`.

    Args:
        plane: (..., P, 2) :func:`~.graph.plane_coords` (deg; vertex 0 the main star at the origin).

    Returns:
        ``(r, phi)``: (..., P − 1) radius (deg) and azimuth (rad) of vertices 1 … P − 1.
    """
    x = plane[..., 1:, :]
    return jnp.hypot(x[..., 0], x[..., 1]), jnp.arctan2(x[..., 1], x[..., 0])


def hypothesis_neighbors(r_i, n_i, tol, hypotheses: int):
    """The image neighbors the screen tries as the hypothesis' i: the first ``hypotheses`` (vertex
    order, i.e. the brightest) that lie at least 4·tol from the main star.

    Args:
        r_i: (P − 1,) neighbor radii (deg, :func:`neighbor_polar`). n_i: () vertex count.
        tol: () position tolerance (deg). hypotheses: static H ≤ P − 1.

    Returns:
        ``(hyp, eligible)``: (H,) int32 neighbor indices (into ``r_i``) and (H,) bool, False where
        fewer than H neighbors qualify (those entries are padding).
    """
    valid = jnp.arange(1, r_i.shape[-1] + 1) < n_i
    eligible = valid & (r_i >= 4.0 * tol)
    hyp = jnp.argsort(~eligible, stable=True)[:hypotheses]
    return hyp.astype(jnp.int32), eligible[hyp]


def radius_order(r, phi, n):
    """A graph's neighbors sorted by radius, the order :func:`nearest_partners` searches.

    Args:
        r, phi: (..., P − 1) :func:`neighbor_polar` (deg, rad). n: (...) vertex counts (the first
            n − 1 neighbors are valid).

    Returns:
        ``(r, phi)``: (..., P − 1) radii ascending, +inf past the n − 1 valid ones (ties: the lower
        vertex first), and their azimuths.
    """
    valid = jax.lax.broadcasted_iota(jnp.int32, r.shape, r.ndim - 1) + 1 < jnp.expand_dims(n, -1)
    r = jnp.where(valid, r, jnp.inf)
    order = jnp.argsort(r, axis=-1, stable=True)
    return jnp.take_along_axis(r, order, axis=-1), jnp.take_along_axis(phi, order, axis=-1)


def nearest_partners(r_i, r_sorted, m: int):
    """For each image neighbor, the ``m`` database neighbors of nearest radius (a window of the sorted
    radii: the m points of a sorted list nearest to a value are contiguous in it).

    Costs one (P − 1, Q − 1) comparison (the insertion point) and a ranking of the 2m slots about
    it, not m passes over the whole (P − 1, Q − 1) table of gaps (docs/design/sgm.md, Triangle
    screen).

    Args:
        r_i: (P − 1,) image neighbor radii (deg). r_sorted: (Q − 1,) database radii from
            :func:`radius_order` (ascending, +inf where absent). m: static, ≤ Q − 1.

    Returns:
        ``(gap, part)``: (P − 1, m) |r_i − r_sorted[part]| (deg; +inf for a window slot past the
        list or an absent neighbor, whose ``part`` is clipped into range) and (P − 1, m) int32
        positions in ``r_sorted``. Of equal gaps the smaller radius comes first.
    """
    q1 = r_sorted.shape[0]
    at = jnp.sum(r_sorted[None, :] < r_i[:, None], axis=1)  # insertion point
    slots = jnp.arange(2 * m)
    near = at[:, None] - m + slots[None, :]  # (P − 1, 2m): the m below, the m from it up
    gap = jnp.where((near >= 0) & (near < q1), jnp.abs(r_i[:, None] - r_sorted[jnp.clip(near, 0, q1 - 1)]),
                    jnp.inf)
    before = (gap[:, None, :] < gap[:, :, None]) | ((gap[:, None, :] == gap[:, :, None])
                                                    & (slots[None, :] < slots[:, None])[None])
    chosen = jnp.sum(before, axis=2) < m  # the m nearest slots
    start = at - jnp.sum(chosen[:, :m], axis=1)  # every chosen finite slot lies in [start, start + m)
    part = start[:, None] + jnp.arange(m)[None, :]
    inside = (part >= 0) & (part < q1)
    part = jnp.clip(part, 0, q1 - 1)
    return jnp.where(inside, jnp.abs(r_i[:, None] - r_sorted[part]), jnp.inf), part.astype(jnp.int32)


def polar_support(r_i, phi_i, hyp, hyp_ok, n_i, r_j, phi_j, *, tol, partners: int):
    """:func:`triangle_support` from precomputed neighbor coordinates and hypotheses (the search
    computes them once per graph, not once per candidate pair).

    Args:
        r_i, phi_i: (P − 1,) image neighbors' :func:`neighbor_polar` (deg, rad). hyp, hyp_ok: (H,)
            :func:`hypothesis_neighbors` (indices may run past P − 1 only where ``hyp_ok`` is False).
        n_i: () image vertex count. r_j, phi_j: (Q − 1,) database neighbors' coordinates in
            :func:`radius_order` (+inf radius where absent).
        tol: () position tolerance (deg). partners: static m.

    Returns:
        () int32, as :func:`triangle_support`.
    """
    p1, q1 = r_i.shape[0], r_j.shape[0]
    m = min(partners, q1)
    vi = jnp.arange(1, p1 + 1) < n_i
    near, part = nearest_partners(r_i, r_j, m)  # (P − 1, m) database neighbors of nearest radius
    ok = (near <= tol) & vi[:, None]
    rot = phi_j[part] - phi_i[:, None]  # (P − 1, m) rotation implied by each pair (rad)
    slack = tol / jnp.maximum(r_i, 1e-6)  # (P − 1,) its uncertainty (rad)
    d = rot[hyp][:, :, None, None] - rot[None, None, :, :]  # (H, m, P − 1, m)
    d = d - (2 * jnp.pi) * jnp.round(d / (2 * jnp.pi))
    agree = jnp.abs(d) <= slack[hyp][:, None, None, None] + slack[None, None, :, None]
    agree = agree & ok[None, None, :, :] & (part[None, None, :, :] != part[hyp][:, :, None, None])
    agree = agree & (jnp.arange(p1)[None, None, :, None] != hyp[:, None, None, None])  # k ≠ i
    support = jnp.sum(jnp.any(agree, axis=3), axis=2)  # (H, m)
    usable = ok[hyp] & hyp_ok[:, None]
    best = jnp.max(jnp.where(usable, support, -2))
    return jnp.maximum(best + 2, 0).astype(jnp.int32)


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
    r_i, phi_i = neighbor_polar(plane_i)
    r_j, phi_j = radius_order(*neighbor_polar(plane_j), n_j)
    hyp, hyp_ok = hypothesis_neighbors(r_i, n_i, tol, min(hypotheses, plane_i.shape[0] - 1))
    return polar_support(r_i, phi_i, hyp, hyp_ok, n_i, r_j, phi_j, tol=tol, partners=partners)


def screen_pass(support, n_i, n_j, *, fraction: float, min_matched: int):
    """True where a candidate's triangle support reaches ``max(min_matched, ⌈fraction·min(n_i, n_j)⌉)``.

    Args:
        support: (...) int from :func:`triangle_support`. n_i, n_j: (...) vertex counts.
        fraction: share of the smaller graph's vertices that must be supported.
        min_matched: the spectral matching's own floor (``Config.min_matched``).
    """
    need = jnp.maximum(min_matched, jnp.ceil(fraction * jnp.minimum(n_i, n_j)))
    return support >= need


@functools.partial(stored_jit, static_argnames=("hypotheses",))
def graph_polar(plane, n, tol, *, hypotheses: int):
    """:func:`neighbor_polar` and :func:`hypothesis_neighbors` of a batch of graphs, computed once
    per graph rather than once per candidate pair.

    Args:
        plane: (B, K, 2) :func:`~.graph.plane_coords` (deg). n: (B,) vertex counts. tol: () deg.
        hypotheses: static H (at most K − 1 are used).

    Returns:
        ``(r, phi, hyp, hyp_ok)``: (B, K − 1) float32 deg and rad, (B, H') int32 and bool,
        H' = min(H, K − 1).
    """
    r, phi = neighbor_polar(plane)
    h = min(hypotheses, plane.shape[1] - 1)
    hyp, hyp_ok = jax.vmap(hypothesis_neighbors, in_axes=(0, 0, None, None))(r, n, tol, h)
    return r, phi, hyp, hyp_ok


def database_polar(db) -> tuple[np.ndarray, np.ndarray]:
    """``(r, phi)``: (D, K − 1) float32 :func:`neighbor_polar` of every database graph in
    :func:`radius_order` (deg, +inf past its neighbors; rad), computed once per database
    (:data:`jstarid.runtime.device_cache`)."""
    def make():
        out = [jax.device_get(radius_order(*neighbor_polar(jnp.asarray(db.plane[lo:lo + 4096])),
                                           jnp.asarray(db.n[lo:lo + 4096])))
               for lo in range(0, len(db.n), 4096)]
        return tuple(np.concatenate([o[k] for o in out]) for k in range(2))

    return device_cache.cached(db, "sgm_screen_polar", make)


@functools.partial(stored_jit, static_argnames=("partners", "fraction", "min_matched"))
def _screen_kernel(r_i, phi_i, hyp, hyp_ok, n_i, r_j, phi_j, n_j, tol, *, partners, fraction,
                   min_matched):
    """:func:`polar_support` and :func:`screen_pass` of N pairs (``vmap``) → (N,) bool."""
    support = jax.vmap(functools.partial(polar_support, tol=tol, partners=partners))(
        r_i, phi_i, hyp, hyp_ok, n_i, r_j, phi_j)
    return screen_pass(support, n_i, n_j, fraction=fraction, min_matched=min_matched)


def screen_pairs(db, plane_i, n_i, scene, rows, config) -> np.ndarray:
    """Which (scene, candidate) pairs pass the triangle screen (host side, grouped by padded size).

    Each graph's neighbor coordinates and hypotheses are computed once (:func:`graph_polar`,
    :func:`database_polar`); a pair of padded size r reads the first r − 1 neighbors of both.

    Args:
        db: the SGM database (``plane``, ``n``). plane_i: (B, K, 2) image graphs'
            :func:`~.graph.plane_coords` (deg). n_i: (B,) image vertex counts.
        scene, rows: (N,) scene and database row of each pair.
        config: :class:`~.config.Config` (``screen.tol_deg``, ``screen.fraction``,
            ``screen.partners``, ``screen.hypotheses``, ``min_matched``, ``size_bucket``).

    Returns:
        (N,) bool, True for the pairs to keep.
    """
    keep = np.ones(rows.size, bool)
    if not rows.size:
        return keep
    n_j = db.n[rows].astype(np.int32)
    bucket = int(config.size_bucket)
    size = np.maximum(-(-np.maximum(n_i[scene], n_j) // bucket) * bucket, bucket)
    tol = jnp.float32(config.screen.tol_deg)
    r_i, phi_i, hyp, hyp_ok = jax.device_get(graph_polar(
        jnp.asarray(plane_i), jnp.asarray(n_i), tol, hypotheses=int(config.screen.hypotheses)))
    r_j, phi_j = database_polar(db)
    static = {"partners": int(config.screen.partners), "fraction": float(config.screen.fraction),
              "min_matched": int(config.min_matched)}
    pending = []
    for r in np.unique(size):
        group = np.nonzero(size == r)[0]
        # calls of power-of-two sizes with little padding; every call dispatched before any is read
        for lo, hi, padded in power_of_two_chunks(group.size, MIN_CALL_PAIRS):
            at = group[lo:hi]
            fill = np.concatenate([at, np.full(padded - at.size, at[0])])
            s, j = scene[fill], rows[fill]
            pending.append((at, map_batch(
                _screen_kernel, (r_i[s, :r - 1], phi_i[s, :r - 1], hyp[s], hyp_ok[s], n_i[s].astype(np.int32),
                                 r_j[j, :r - 1], phi_j[j, :r - 1], n_j[fill]),
                (tol,), static=static)))
    for at, out in pending:
        keep[at] = np.asarray(out)[:at.size]
    return keep
