"""Linear algebra of small matrices (3 × 3 SVD, ≤ 6 × 6 positive definite solves) in plain array operations.

Wahba's problem needs the SVD of a 3 × 3 matrix per scene (or per hypothesis), and the camera fits a
4 × 4 or 5 × 5 normal-equation solve, batched. On CPU, ``jnp.linalg.svd``, ``solve`` and ``inv``
are LAPACK calls (``gesdd``, ``getrf``) that split a large batch into chunks run on XLA's intra-op
thread pool and then *wait* for them without running any themselves. When several host
devices (:func:`jstarid.runtime.use_cpu_cores`) each reach such a call from a thread of that same
pool, every pool thread can be waiting and no chunk ever runs: the process hangs with every thread
idle (seen on a 2-core machine in ``sgm.identify`` with two devices; gdb showed both pool threads in
``ParallelBatchMap`` of ``lapack_sgesdd_ffi``). The functions here are elementwise arithmetic that
XLA fuses into the surrounding kernel: no library call, no thread pool, the same result on every
backend. A test checks that the rest of the package calls no LAPACK routine.

SVD (Hestenes' one-sided Jacobi; Demmel & Veselić, SIAM J. Matrix Anal. Appl. 13 (1992)): rotate
pairs of columns of ``A`` until they are mutually orthogonal; then ``A V = U Σ`` with the column
norms as singular values. Each rotation zeroes one column inner product exactly, the sweep converges
quadratically, and a 3 × 3 float32 matrix is orthogonal to rounding after 4 sweeps (6 are run).
Errors are those of a backward-stable SVD (≈ ε‖A‖), as LAPACK's.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["svd3", "nearest_rotation", "cholesky_solve"]

def _jacobi_pair(cols, vecs, p, q):
    """One Jacobi rotation making columns p, q of ``cols`` (a list of (..., 3) arrays) orthogonal, in
    place; the same rotation applied to the right vectors ``vecs``."""
    alpha = jnp.sum(cols[p] ** 2, axis=-1)
    beta = jnp.sum(cols[q] ** 2, axis=-1)
    gamma = jnp.sum(cols[p] * cols[q], axis=-1)
    # t = tan θ, the smaller root of t² + 2ζt − 1 = 0 (ζ = (β − α) / 2γ): columns p, q become
    # orthogonal; no rotation where they already are (γ = 0)
    rotate = gamma != 0
    zeta = (beta - alpha) / (2.0 * jnp.where(rotate, gamma, 1.0))
    t = jnp.where(zeta >= 0, 1.0, -1.0) / (jnp.abs(zeta) + jnp.sqrt(1.0 + zeta * zeta))
    t = jnp.where(rotate, t, 0.0)
    c = (1.0 / jnp.sqrt(1.0 + t * t))[..., None]
    s = c * t[..., None]
    for x in (cols, vecs):
        x[p], x[q] = c * x[p] - s * x[q], s * x[p] + c * x[q]


def svd3(a, sweeps: int = 6):
    """Singular value decomposition of 3 × 3 matrices, ``a = u · diag(s) · vᵀ``.

    Args:
        a: (..., 3, 3) float matrices.
        sweeps: Jacobi sweeps over the three column pairs (a loop, not unrolled: a kernel that fits
            many attitudes would otherwise compile slowly).

    Returns:
        ``(u, s, v)``: (..., 3, 3) left singular vectors as columns (a column whose singular value is
        0 is 0, not a unit vector), (..., 3) singular values (≥ 0, in no particular order), (..., 3, 3)
        orthogonal right singular vectors as columns. Note ``v``, not ``vᵀ``.
    """
    a = jnp.asarray(a)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=a.dtype), a.shape)

    def sweep(_, state):
        cols, vecs = list(state[:3]), list(state[3:])
        for p, q in ((0, 1), (0, 2), (1, 2)):
            _jacobi_pair(cols, vecs, p, q)
        return (*cols, *vecs)

    state = jax.lax.fori_loop(0, sweeps, sweep, (*(a[..., :, j] for j in range(3)),
                                                 *(eye[..., :, j] for j in range(3))))
    cols, v = jnp.stack(state[:3], axis=-1), jnp.stack(state[3:], axis=-1)
    sigma = jnp.linalg.norm(cols, axis=-2)
    return cols / jnp.where(sigma > 0, sigma, 1.0)[..., None, :], sigma, v


def _unit(x, fallback):
    """x (..., 3) normalized; ``fallback`` (..., 3) where x is 0."""
    n = jnp.linalg.norm(x, axis=-1, keepdims=True)
    return jnp.where(n > 0, x / jnp.where(n > 0, n, 1.0), fallback)


def _perpendicular(x):
    """A unit vector perpendicular to the unit vector x (..., 3): x × e_x, or x × e_y where x is
    near e_x."""
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    zero = jnp.zeros_like(x0)
    near_x = jnp.abs(x0) >= 0.9
    cross = jnp.stack([jnp.where(near_x, -x2, zero), jnp.where(near_x, zero, x2),
                       jnp.where(near_x, x0, -x1)], axis=-1)
    return cross / jnp.linalg.norm(cross, axis=-1, keepdims=True)


def _larger_first(first, second):
    """Two (σ (...,), u (..., 3), v (..., 3)) triples, the one with the larger σ first."""
    swap = first[0] < second[0]
    masks = (swap, swap[..., None], swap[..., None])
    return (tuple(jnp.where(m, b, a) for m, a, b in zip(masks, first, second, strict=True)),
            tuple(jnp.where(m, a, b) for m, a, b in zip(masks, first, second, strict=True)))


def _outer(x, y):
    """x yᵀ of (..., 3) vectors → (..., 3, 3), as elementwise products (exact float32)."""
    return x[..., :, None] * y[..., None, :]


def nearest_rotation(a, sweeps: int = 6):
    """The proper rotation R maximizing tr(Rᵀ a): ``U diag(1, 1, det U det V) Vᵀ`` (Markley 1988).

    Built from the two largest singular pairs only, ``R = u₁v₁ᵀ + u₂v₂ᵀ + (u₁ × u₂)(v₁ × v₂)ᵀ``, which
    is the same matrix and needs neither a determinant nor the third left vector (undefined when
    ``a`` has rank 2, e.g. Wahba's problem with two stars).

    Args:
        a: (..., 3, 3) float matrices.
        sweeps: Jacobi sweeps (:func:`svd3`).

    Returns:
        (..., 3, 3) rotation matrices (det +1). Where ``a`` has rank below 2 the answer is not unique:
        one of the rotations is returned (the identity for ``a`` = 0).
    """
    u, s, v = svd3(a, sweeps)
    pairs = [(s[..., j], u[..., :, j], v[..., :, j]) for j in range(3)]
    for i, j in ((0, 1), (1, 2), (0, 1)):  # the two largest first: a sorting network of where-swaps
        pairs[i], pairs[j] = _larger_first(pairs[i], pairs[j])
    (_, u1, v1), (_, u2, v2) = pairs[0], pairs[1]  # v is orthogonal: v₁, v₂ unit, perpendicular
    # where a singular value is 0 its left vector is 0: take the right one instead (a = 0 → R = I),
    # made orthogonal to u₁ (u₂ also to absorb rounding), or any perpendicular
    u1 = _unit(u1, v1)
    u2 = jnp.where(jnp.linalg.norm(u2, axis=-1, keepdims=True) > 0, u2, v2)
    u2 = _unit(u2 - jnp.sum(u2 * u1, -1, keepdims=True) * u1, _perpendicular(u1))
    u3, v3 = jnp.cross(u1, u2), jnp.cross(v1, v2)
    return _outer(u1, v1) + _outer(u2, v2) + _outer(u3, v3)


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
