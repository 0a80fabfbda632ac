"""Angles between directions, accurate at small separations (shared by every algorithm).

``arccos`` of a float32 dot product cannot resolve separations below ≈ 0.02° (cos θ ≈ 1 − θ²/2
rounds), which is a whole pixel on a 20° / 1024 px tracker. ``atan2(‖u × v‖, u · v)`` keeps full
relative precision at every angle. Products are written out by component: a reviewer of the SGM code
saw XLA on CPU (jax 0.10) lower a broadcast ``sum(u * v, -1)`` to a reduced-precision dot inside a
large jit, and the explicit form leaves nothing to rewrite.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["angle_between", "angle_between_host", "pairwise_angles", "turn_sign"]


def angle_between(u, v):
    """Angle (rad) between vectors ``u`` and ``v`` (..., 3), broadcast; need not be unit length."""
    u0, u1, u2 = u[..., 0], u[..., 1], u[..., 2]
    v0, v1, v2 = v[..., 0], v[..., 1], v[..., 2]
    c0 = u1 * v2 - u2 * v1
    c1 = u2 * v0 - u0 * v2
    c2 = u0 * v1 - u1 * v0
    cross = jnp.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    dot = u0 * v0 + u1 * v1 + u2 * v2
    return jnp.arctan2(cross, dot)


def angle_between_host(u, v):
    """:func:`angle_between` on the host in float64 NumPy (database builds): (n, 3) each → (n,) rad."""
    u, v = np.asarray(u, np.float64), np.asarray(v, np.float64)
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.sum(u * v, axis=-1))


def pairwise_angles(vectors):
    """(..., n, n) angles (rad) between every pair of the vectors (..., n, 3)."""
    return angle_between(vectors[..., :, None, :], vectors[..., None, :, :])


def turn_sign(u, v, w):
    """Sign of the triple product u · (v × w): which way a triangle of unit vectors turns. A rotation
    keeps it, a mirror image flips it.

    Args:
        u, v, w: (..., 3) vectors.

    Returns:
        (...,) float32 in {−1, 0, 1}.
    """
    # written out by component, as angle_between is (module docstring)
    cross = jnp.stack([v[..., 1] * w[..., 2] - v[..., 2] * w[..., 1],
                       v[..., 2] * w[..., 0] - v[..., 0] * w[..., 2],
                       v[..., 0] * w[..., 1] - v[..., 1] * w[..., 0]], -1)
    return jnp.sign(u[..., 0] * cross[..., 0] + u[..., 1] * cross[..., 1] + u[..., 2] * cross[..., 2])
