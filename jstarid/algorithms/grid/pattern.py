"""A star's grid pattern (Padgett & Kreutz-Delgado 1997, §III), one pure function for the catalog
and the image alike.

The neighbours are projected on the plane tangent at the reference star (gnomonic, in pixels of the
camera's focal length), turned so that the nearest neighbour beyond the buffer radius lies along
+x, and every neighbour inside the pattern square sets the bit of its cell of a g × g grid (cells
2R/g wide; the rows are shifted by half a cell so that the +x axis runs through their middle).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["grid_pattern", "overlap"]


def _tangent_basis(u):
    """Right-handed unit vectors (e1, e2) perpendicular to the unit vector u (e1 × e2 = u)."""
    helper = jnp.where(jnp.abs(u[0]) < 0.9, jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0]))
    e1 = helper - (helper[0] * u[0] + helper[1] * u[1] + helper[2] * u[2]) * u
    e1 = e1 / jnp.sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2])
    e2 = jnp.stack([u[1] * e1[2] - u[2] * e1[1], u[2] * e1[0] - u[0] * e1[2], u[0] * e1[1] - u[1] * e1[0]])
    return e1, e2


def grid_pattern(u, neighbours, real, *, f_px: float, pattern_px: float, buffer_px: float, grid: int):
    """The grid pattern of a reference star.

    Args:
        u: (3,) unit vector of the reference star.
        neighbours: (M, 3) unit vectors of candidate neighbours (the reference itself may be among
            them: it lies at the centre, inside the buffer radius, and is ignored).
        real: (M,) bool, the entry is a star.
        f_px: focal length (px). pattern_px, buffer_px: the pattern and buffer radii (px).
        grid: g (static).

    Returns:
        ``(words, oriented)``: (g²/32,) uint32 the pattern's bits, and () bool the reference has a
        neighbour to orient by (no pattern otherwise).
    """
    e1, e2 = _tangent_basis(u)
    along = neighbours[:, 0] * u[0] + neighbours[:, 1] * u[1] + neighbours[:, 2] * u[2]
    x = f_px * (neighbours[:, 0] * e1[0] + neighbours[:, 1] * e1[1] + neighbours[:, 2] * e1[2]) / along
    y = f_px * (neighbours[:, 0] * e2[0] + neighbours[:, 1] * e2[1] + neighbours[:, 2] * e2[2]) / along
    r2 = x * x + y * y
    near = real & (along > 0) & (r2 <= pattern_px * pattern_px) & (r2 > buffer_px * buffer_px)
    nearest = jnp.argmin(jnp.where(near, r2, jnp.inf))
    oriented = jnp.any(near)
    phi = jnp.arctan2(y[nearest], x[nearest])
    c, s = jnp.cos(phi), jnp.sin(phi)
    xr, yr = c * x + s * y, -s * x + c * y  # turned by −φ: the nearest neighbour on +x
    ix = jnp.floor((xr / pattern_px + 1.0) * 0.5 * grid).astype(jnp.int32)
    # rows centred on the +x axis (half a cell down): the nearest neighbour, at y = 0 exactly, sits in
    # the middle of its cell instead of on a border that rounding would decide
    iy = jnp.floor((yr / pattern_px + 1.0) * 0.5 * grid + 0.5).astype(jnp.int32)
    inside = near & (ix >= 0) & (ix < grid) & (iy >= 0) & (iy < grid)
    cell = jnp.where(inside, ix * grid + iy, grid * grid)
    bits = jnp.zeros((grid * grid,), jnp.uint32).at[cell].set(1, mode="drop")
    shifts = jnp.asarray(np.arange(32, dtype=np.uint32))
    words = jnp.sum(jnp.left_shift(bits.reshape(-1, 32), shifts[None, :]), axis=1, dtype=jnp.uint32)
    return jnp.where(oriented, words, jnp.uint32(0)), oriented


def overlap(pattern, table):
    """(S,) int32 common bits of one pattern (W,) uint32 with every row of a table (S, W) uint32."""
    from jax import lax

    return jnp.sum(lax.population_count(jnp.bitwise_and(table, pattern[None, :])), axis=1, dtype=jnp.int32)
