"""Initial match (paper §2.3.1): candidate triangles within Th1/Th2 (eq. 7) and triangle voting; per
scene and jit-able (:mod:`jstarid.algorithms.mlv.identify` vmaps it).
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["candidate_ranges", "gather_candidates", "gather_pool", "cast_votes", "match_vertices",
           "cast_matched_votes", "best_candidates", "opposite_sides", "observed_sides"]


def candidate_ranges(keys, v1h, v2h, *, th1, th2, v1_offset: int, stride: int, n_rows: int,
                     th1_max: int | None = None):
    """Database ranges holding the triangles with |v̂1ˢ − v̂1ᶜ| ≤ Th1 and |v̂2ˢ − v̂2ᶜ| ≤ Th2 (eq. 7).

    Keys ``(v̂1 − v1_offset)·stride + v̂2`` are sorted ascending, so each of the 2·Th1 + 1 v̂1 values of
    the window gives one contiguous key range.

    Args:
        keys: (T,) int32 sorted database keys.
        v1h, v2h: (...,) int32 discretized features of the query triangles.
        th1, th2: tolerances (bins): Python ints, or traced int32 scalars (then ``th1_max`` is
            required), so that one compilation serves a grid of tolerances.
        v1_offset, stride, n_rows: key layout (see :class:`~jstarid.algorithms.mlv.Database`).
        th1_max: static upper bound of ``th1``; the result has 2·th1_max + 1 ranges, those with
            |Δv̂1| > th1 empty. ``None``: ``th1`` (which must then be a Python int).

    Returns:
        ``(start, count)``: (..., 2·th1_max + 1) int32 first key index and length of each range.
    """
    if th1_max is None:
        th1_max = int(th1)
    d1 = jnp.arange(-th1_max, th1_max + 1, dtype=jnp.int32)
    # rows outside the table are clipped to −1 / n_rows: their key ranges are empty (no overflow)
    row = jnp.clip(v1h[..., None] - v1_offset + d1.reshape((1,) * jnp.ndim(v1h) + (-1,)), -1, n_rows)
    lo2 = jnp.clip(v2h - th2, 0, stride - 1)[..., None]
    hi2 = jnp.clip(v2h + th2, 0, stride - 1)[..., None]
    empty = (v2h + th2 < 0) | (v2h - th2 > stride - 1)
    lo_key = row * stride + lo2
    hi_key = row * stride + hi2
    # one search over both ends (half the dispatches); side="left" on hi_key + 1 equals
    # side="right" on hi_key for integer keys
    both = jnp.searchsorted(keys, jnp.stack([lo_key, hi_key + 1]), side="left").astype(jnp.int32)
    start, end = both[0], both[1]
    # window rows beyond a traced Th1 (none when th1 == th1_max)
    off = (jnp.abs(d1) > th1).reshape((1,) * empty.ndim + (-1,))
    count = jnp.where(empty[..., None] | off, 0, end - start)
    return start, count


def gather_candidates(start, count, capacity: int):
    """Pack the ranges of one query into a fixed buffer of ``capacity`` database indices.

    Args:
        start, count: (R,) int32 ranges (from :func:`candidate_ranges`).
        capacity: K, static buffer size.

    Returns:
        ``(index, valid, overflow, total)``: (K,) int32 database rows (0 where not valid), (K,) bool,
        scalar bool (more than K candidates: only the first K are held), scalar int32 candidates.
    """
    incl = jnp.cumsum(count)
    excl = incl - count
    total = incl[-1]
    slot = jnp.arange(capacity, dtype=jnp.int32)
    which = jnp.sum(slot[:, None] >= incl[None, :], axis=1)  # range holding slot t
    which = jnp.minimum(which, count.shape[0] - 1)
    valid = slot < total
    index = jnp.where(valid, start[which] + slot - excl[which], 0)
    return index.astype(jnp.int32), valid, total > capacity, total.astype(jnp.int32)


def gather_pool(start, count, pool: int):
    """Pack the candidate ranges of all query triangles of one scene into one flat buffer, range by
    range in the order of ``start`` / ``count`` (per-triangle buffers of K slots are mostly empty).

    Args:
        start, count: (T, R) int32 ranges of each query triangle (:func:`candidate_ranges`), the counts
            of triangles that must not vote already set to 0.
        pool: P, static buffer size.

    Returns:
        ``(index, tri, valid, total)``: (P,) int32 database rows (0 where not valid), (P,) int32 query
        triangle of each slot, (P,) bool, and the scalar int32 number of candidates (more than P: only
        the first P are held; the caller must retry with a larger pool).
    """
    r = count.shape[-1]
    start, count = start.reshape(-1), count.reshape(-1)
    incl = jnp.cumsum(count)
    excl = incl - count
    total = incl[-1]
    slot = jnp.arange(pool, dtype=jnp.int32)
    # range of each slot = the last range starting at or before it: mark every range's first slot
    # and count the marks (5× cheaper on CPU than a binary search of every slot). Empty ranges share
    # their first slot with the next range and come before it, so the count lands on the right one.
    marks = jnp.zeros((pool,), jnp.int32).at[excl].add(1, mode="drop")
    which = jnp.clip(jnp.cumsum(marks) - 1, 0, count.shape[0] - 1)
    valid = slot < total
    index = jnp.where(valid, start[which] + slot - excl[which], 0)
    return index.astype(jnp.int32), which // r, valid, total.astype(jnp.int32)


def cast_votes(tri_det, cand_stars, cand_valid, n_det: int, n_ref: int):
    """Triangle voting (Fig. 3): every candidate votes for its three catalog stars at each of the three
    detections of the query triangle (singular values do not tell which vertex is which).

    A detection's true star collects a vote from every true triangle through it (C(N−1, 2) = 36 at
    N = 10), any other star only from triangles through both (N − 2 = 8).

    Args:
        tri_det: (T, 3) int32 detection index of each query triangle's vertices.
        cand_stars: (T, K, 3) int32 reference-catalog stars of each candidate triangle.
        cand_valid: (T, K) bool, the candidate counts (it exists, its query triangle is valid and did
            not overflow).
        n_det: number of detections N. n_ref: reference-catalog size S.

    Returns:
        (N, S) int32 vote counters.
    """
    t, k, _ = cand_stars.shape
    det = jnp.broadcast_to(tri_det[:, None, :, None], (t, k, 3, 3))
    star = jnp.broadcast_to(cand_stars[:, :, None, :], (t, k, 3, 3))
    flat = jnp.where(cand_valid[:, :, None, None], det * n_ref + star, n_det * n_ref)
    counts = jnp.zeros((n_det * n_ref + 1,), jnp.int32).at[flat.reshape(-1)].add(1)
    return counts[:-1].reshape(n_det, n_ref)


def best_candidates(votes):
    """Candidate per detection: the star with the most votes (ties → smallest index; ``argmax``, far
    cheaper than ``top_k`` on CPU).

    Args:
        votes: (N, S) int32 counters.

    Returns:
        ``(star, n_votes)``: (N,) int32 best star and its votes.
    """
    star = jnp.argmax(votes, axis=1).astype(jnp.int32)
    return star, jnp.take_along_axis(votes, star[:, None], axis=1)[:, 0]


def opposite_sides(vectors):
    """(..., 3) angles (rad) opposite each vertex of triangles (..., 3, 3): θ(b,c), θ(a,c), θ(a,b)."""
    a, b, c = vectors[..., 0, :], vectors[..., 1, :], vectors[..., 2, :]

    def ang(u, v):
        return 2.0 * jnp.arcsin(jnp.clip(0.5 * jnp.linalg.norm(u - v, axis=-1), 0.0, 1.0))

    return jnp.stack([ang(b, c), ang(a, c), ang(a, b)], axis=-1)


def observed_sides(obs_vectors):
    """Side angles of query triangles, ascending, and the vertex opposite each.

    Args:
        obs_vectors: (T, 3, 3) detection directions of each query triangle (camera frame).

    Returns:
        ``(vertex, sides)``: (T, 3) int32 query vertex (0–2) opposite the m-th shortest side, and
        (T, 3) those sides (rad), ascending (compare with ``Database.sides``).
    """
    obs = opposite_sides(obs_vectors)  # (T, 3)
    vertex = jnp.argsort(obs, axis=-1).astype(jnp.int32)
    return vertex, jnp.take_along_axis(obs, vertex, axis=-1)


def match_vertices(obs_vectors, cand_sides, tol_rad: float):
    """Vertex correspondence of each candidate triangle and a side-length check (extension).

    Singular values fix two of a triangle's three shape parameters; its side angles fix all three and,
    by which side is opposite which vertex, which candidate star belongs to which detection. Sorted
    matching of the sides minimises the largest side error over the six permutations (optimal
    bottleneck assignment on a line), so the database stores each triangle's stars ordered by their
    opposite side. A candidate is accepted when every side agrees within ``tol_rad``.

    Args:
        obs_vectors: (T, 3, 3) detection directions of each query triangle (camera frame).
        cand_sides: (T, K, 3) each candidate's sides (rad), ascending (``Database.sides``).
        tol_rad: side tolerance (rad).

    Returns:
        ``(vertex, ok)``: (T, 3) int32 query vertex (0–2) opposite the observed sides in ascending
        order (↔ candidate star m = 0, 1, 2), and (T, K) bool.
    """
    vertex, obs_sorted = observed_sides(obs_vectors)
    err = jnp.max(jnp.abs(cand_sides - obs_sorted[:, None, :]), axis=-1)  # (T, K)
    return vertex, err <= tol_rad


def cast_matched_votes(tri_det, cand_stars, cand_valid, n_det: int, n_ref: int):
    """Vertex-matched triangle voting: each detection votes only for its corresponding star.

    Args:
        tri_det: (T, 3) int32 detection of each query triangle vertex, ordered as the candidate
            stars (detection ``tri_det[t, m]`` ↔ star ``cand_stars[t, k, m]``).
        cand_stars: (T, K, 3) int32 reference-catalog stars of each candidate triangle.
        cand_valid: (T, K) bool.
        n_det, n_ref: N and S.

    Returns:
        (N, S) int32 vote counters.
    """
    t, k, _ = cand_stars.shape
    det = jnp.broadcast_to(tri_det[:, None, :], (t, k, 3))
    flat = jnp.where(cand_valid[:, :, None], det * n_ref + cand_stars, n_det * n_ref)
    counts = jnp.zeros((n_det * n_ref + 1,), jnp.int32).at[flat.reshape(-1)].add(1)
    return counts[:-1].reshape(n_det, n_ref)
