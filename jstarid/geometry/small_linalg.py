"""Linear algebra of small matrices (3 × 3 nearest rotation, ≤ 6 × 6 positive definite solves) in
plain array operations.

Wahba's problem needs the nearest rotation to a 3 × 3 matrix per scene (or per hypothesis), and the
camera fits a 4 × 4 or 5 × 5 normal-equation solve, batched. On CPU, ``jnp.linalg.svd``, ``solve``
and ``inv`` are LAPACK calls (``gesdd``, ``getrf``) that split a large batch into chunks run on
XLA's intra-op thread pool and then *wait* for them without running any themselves. When several
host devices (:func:`jstarid.runtime.use_cpu_cores`) each reach such a call from a thread of that
same pool, every pool thread can be waiting and no chunk ever runs: the process hangs with every
thread idle (seen on a 2-core machine in ``sgm.identify`` with two devices; gdb showed both pool
threads in ``ParallelBatchMap`` of ``lapack_sgesdd_ffi``). The functions here are elementwise
arithmetic and short loops that XLA fuses into the surrounding kernel: no library call, no thread
pool, the same result on every backend. A test checks that the rest of the package calls no LAPACK
routine.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jstarid.geometry import precise

__all__ = ["largest_singular_value", "nearest_rotation", "cholesky_solve"]


def _first_row_dot(x, y):
    """Σ_k x[..., 0, k] y[..., 0, k], written out: XLA's reduce over a length-3 axis sums in an
    order that depends on the batch shape, and a result must not depend on its batch."""
    return x[..., 0, 0] * y[..., 0, 0] + x[..., 0, 1] * y[..., 0, 1] + x[..., 0, 2] * y[..., 0, 2]


def _combine(c1, x, c2, y):
    """c1·x + c2·y for (...,) weights and (..., 3, 3) matrices, as a dot_general: an elementwise
    multiply-add may be fused (FMA) in some batch shapes and not others, and a result must not
    depend on its batch."""
    return precise.einsum("...k,...kij->...ij", jnp.stack([c1, c2], axis=-1), jnp.stack([x, y], axis=-3))


def _cofactor(x):
    """Cofactor matrices of (..., 3, 3) x: rows are cross products of x's rows (= det(x) x⁻ᵀ)."""
    r0, r1, r2 = x[..., 0, :], x[..., 1, :], x[..., 2, :]
    return jnp.stack([jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)], axis=-2)


def largest_singular_value(a):
    """Largest singular value of (..., 3, 3) matrices: √ of the largest eigenvalue of aᵀa by the
    closed form for symmetric 3 × 3 matrices (Smith, Commun. ACM 4 (1961) 168).

    Returns:
        (...,) σ₁ ≥ 0 (to a few float32 ulps of ‖a‖²: an estimate, not for small singular values).
    """
    m = precise.einsum("...ki,...kj->...ij", a, a)  # aᵀa
    q = (m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]) / 3.0
    off = m[..., 0, 1] ** 2 + m[..., 0, 2] ** 2 + m[..., 1, 2] ** 2
    p = jnp.sqrt(((m[..., 0, 0] - q) ** 2 + (m[..., 1, 1] - q) ** 2 + (m[..., 2, 2] - q) ** 2 + 2.0 * off)
                 / 6.0)
    # the eigenvalues are q + 2p cos(φ + 2πk/3), cos 3φ = det((m − qI) / p) / 2
    eye = jnp.broadcast_to(jnp.eye(3, dtype=m.dtype), m.shape)
    c = (m - q[..., None, None] * eye) / jnp.where(p > 0, p, 1.0)[..., None, None]
    half_det = 0.5 * _first_row_dot(c, _cofactor(c))
    phi = jnp.arccos(jnp.clip(half_det, -1.0, 1.0)) / 3.0
    return jnp.sqrt(jnp.maximum(q + 2.0 * p * jnp.cos(phi), 0.0))


def nearest_rotation(a, iterations: int = 8):
    """The proper rotation R maximizing tr(Rᵀ a): ``U diag(1, 1, det U det V) Vᵀ`` for a = U Σ Vᵀ
    (Markley 1988), by Newton's iteration for the polar factor with determinant scaling
    (Higham, SIAM J. Sci. Stat. Comput. 7 (1986)): X ← ½(γX + γ⁻¹X⁻ᵀ), γ = |det X|^(−1/3).

    The polar factor of ``a`` itself is U Vᵀ, a reflection where det a < 0, and undefined where ``a``
    has rank 2 (Wahba's problem with two stars). The iteration starts instead from
    ``ã = a/σ₁ + cof(a)/σ₁²``: with cof(a) = d · U diag(σ₂σ₃, σ₁σ₃, σ₁σ₂) Vᵀ (d = det U det V), ã has
    the singular vectors of ``a`` and the values 1 + dσ₂σ₃/σ₁², (σ₂ + dσ₃)/σ₁, (σ₃ + dσ₂)/σ₁ — the
    first two positive and the third of sign d wherever σ₂ > σ₃ (the condition for a unique answer)
    — so its polar factor is the rotation sought, rank 2 included. 8 iterations (5 already reach
    float32 rounding on random Gaussian matrices; each step roughly squares the error).

    Args:
        a: (..., 3, 3) float matrices.
        iterations: Newton steps (static; a loop, not unrolled).

    Returns:
        (..., 3, 3) rotation matrices (det +1). Where ``a`` has rank below 2 the answer is not unique
        and the identity is returned.
    """
    s1 = largest_singular_value(a)
    t = 1.0 / jnp.where(s1 > 0, s1, 1.0)
    x = _combine(t, a, t * t, _cofactor(a))

    def step(_, x):
        cof = _cofactor(x)
        det = _first_row_dot(x, cof)
        gamma = jnp.abs(det) ** (-1.0 / 3.0)
        return _combine(0.5 * gamma, x, 0.5 / (gamma * det), cof)

    r = jax.lax.fori_loop(0, iterations, step, x)
    fine = jnp.all(jnp.isfinite(r), axis=(-2, -1))  # not where rank < 2 (det ã = 0)
    return jnp.where(fine[..., None, None], r, jnp.broadcast_to(jnp.eye(3, dtype=r.dtype), r.shape))


def cholesky_solve(a, b):
    """x with a x = b for symmetric positive definite a, by a Cholesky factorization written out.

    Args:
        a: (..., n, n) symmetric positive definite matrices (n static and small: the loops unroll).
        b: (..., n) right-hand sides.

    Returns:
        (..., n) solutions (non-finite where ``a`` is not positive definite: callers test them).
    """
    n = a.shape[-1]
    low = [[None] * n for _ in range(n)]  # L with a = L Lᵀ, entry by entry
    for j in range(n):
        diag = a[..., j, j] - sum(low[j][k] ** 2 for k in range(j))
        low[j][j] = jnp.sqrt(diag)
        for i in range(j + 1, n):
            low[i][j] = (a[..., i, j] - sum(low[i][k] * low[j][k] for k in range(j))) / low[j][j]
    y = [None] * n  # L y = b
    for i in range(n):
        y[i] = (b[..., i] - sum(low[i][k] * y[k] for k in range(i))) / low[i][i]
    x = [None] * n  # Lᵀ x = y
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(low[k][i] * x[k] for k in range(i + 1, n))) / low[i][i]
    return jnp.stack(x, axis=-1)
