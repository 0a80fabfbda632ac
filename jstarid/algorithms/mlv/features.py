"""Triangle-unit features: the singular values of M = [p_i p_j p_k] (paper eqs. 1–4).

The singular values are the square roots of the eigenvalues μ of ``MᵀM`` (unit diagonal, pair
cosines off it). A naive 3×3 eigensolver loses most float32 digits of the two small values of a star
triangle (all cosines ≈ 1), so the characteristic polynomial is written in well-conditioned
invariants, each from cross products and differences of unit vectors (no cancellation):

    μ³ − S1 μ² + S2 μ − S3 = 0,   S1 = tr MᵀM = 3,
    S2 = Σ_{pairs} sin²θ_ij = Σ |p_i × p_j|²,
    S3 = det(M)² = (p_i · ((p_j − p_i) × (p_k − p_i)))².

The largest root μ1 ∈ (1, 3] by Newton from μ = 3 (monotone: the cubic is convex and increasing right
of μ1); the small roots by Vieta, μ2 + μ3 = (S2 − S3/μ1)/μ1, μ2 μ3 = S3/μ1. The same code runs in
NumPy float64 (database) and jax.numpy float32 (identification); tested against ``np.linalg.svd``.
"""

from __future__ import annotations

import itertools
from functools import cache

import jax.numpy as jnp
import numpy as np

__all__ = ["singular_values", "discretize", "triangle_features", "triangle_combinations"]

_NEWTON_STEPS = 6  # error after k steps from μ = 3 ≲ 0.35^(2^k); 6 steps reach float64 precision


def _cross(a, b, xp):
    return xp.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def singular_values(p_i, p_j, p_k, xp=jnp):
    """Singular values v1 ≥ v2 ≥ v3 of M = [p_i p_j p_k] (eqs. 1–3) for unit vectors.

    Args:
        p_i, p_j, p_k: (..., 3) unit vectors (any common frame: the values are rotation invariant).
        xp: array module, ``jax.numpy`` (default, jit-able) or ``numpy`` (float64 database build).

    Returns:
        (..., 3) singular values, descending (dimensionless). Degenerate triangles (coincident or
        collinear stars) give v2 and/or v3 = 0 without NaNs.
    """
    d_ij = p_j - p_i
    d_ik = p_k - p_i
    d_jk = p_k - p_j
    # sin²θ = |a × b|² and a × b = a × (b − a): no cancellation for nearby stars.
    s2 = (xp.sum(_cross(p_i, d_ij, xp) ** 2, -1) + xp.sum(_cross(p_i, d_ik, xp) ** 2, -1)
          + xp.sum(_cross(p_j, d_jk, xp) ** 2, -1))
    det = xp.sum(p_i * _cross(d_ij, d_ik, xp), -1)  # det[p_i, p_j, p_k] = det[p_i, d_ij, d_ik]
    s3 = det * det
    mu1 = xp.full_like(s2, 3.0)
    for _ in range(_NEWTON_STEPS):  # fixed count: jit- and vmap-friendly
        f = mu1 * (mu1 * (mu1 - 3.0) + s2) - s3
        df = mu1 * (3.0 * mu1 - 6.0) + s2
        mu1 = mu1 - f / df
    mu1 = xp.maximum(mu1, 1.0)  # μ1 ≥ tr/3 = 1 always
    prod = s3 / mu1  # μ2 μ3
    total = xp.maximum((s2 - prod) / mu1, 0.0)  # μ2 + μ3
    disc = xp.maximum(total * total - 4.0 * prod, 0.0)
    mu2 = 0.5 * (total + xp.sqrt(disc))
    safe_mu2 = xp.where(mu2 > 0, mu2, 1.0)  # double-where: μ3 = μ2μ3 / μ2 without 0/0
    mu3 = xp.where(mu2 > 0, prod / safe_mu2, 0.0)
    return xp.stack([xp.sqrt(mu1), xp.sqrt(mu2), xp.sqrt(xp.maximum(mu3, 0.0))], axis=-1)


def discretize(v1, v2, dv1: float, dv2: float, xp=jnp):
    """Discretized features v̂1 = ceil(v1/Δv1), v̂2 = ceil(v2/Δv2) (eq. 4; the paper's second worked
    example matches ``floor`` instead, docs/design/mlv.md).

    Args:
        v1, v2: (...,) singular values (dimensionless).
        dv1, dv2: discretization units Δv1, Δv2.
        xp: array module.

    Returns:
        ``(v̂1, v̂2)``, (...,) int32 (jax) or int64 (numpy).
    """
    dtype = xp.int64 if xp is np else xp.int32
    return xp.ceil(v1 / dv1).astype(dtype), xp.ceil(v2 / dv2).astype(dtype)


@cache
def triangle_combinations(n: int) -> np.ndarray:
    """(C(n, 3), 3) int32 index triples i < j < k in lexicographic order."""
    return np.array(list(itertools.combinations(range(n), 3)), dtype=np.int32).reshape(-1, 3)


def triangle_features(vectors, dv1: float, dv2: float, xp=jnp):
    """Discretized features of every triangle of n unit vectors.

    Args:
        vectors: (..., n, 3) unit vectors.
        dv1, dv2: discretization units Δv1, Δv2 (eq. 4).
        xp: array module.

    Returns:
        ``(v̂1, v̂2, sv)``: (..., C(n,3)) integer features and (..., C(n,3), 3) singular values, the
        triangles in the order of :func:`triangle_combinations`.
    """
    combos = triangle_combinations(vectors.shape[-2])
    sv = singular_values(vectors[..., combos[:, 0], :], vectors[..., combos[:, 1], :],
                         vectors[..., combos[:, 2], :], xp=xp)
    v1h, v2h = discretize(sv[..., 0], sv[..., 1], dv1, dv2, xp=xp)
    return v1h, v2h, sv
