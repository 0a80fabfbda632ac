"""Padding the batch axis to a static size (the one padding rule of the runtime)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["pad_rows"]


def pad_rows(tree, size: int, *, mode: str = "zeros"):
    """Pad every leaf's leading axis to ``size``.

    Args:
        tree: pytree of NumPy or JAX arrays sharing the leading axis length n ≤ size (JAX arrays
            may be traced: the padding is static).
        size: the padded length.
        mode: ``"zeros"`` (empty scenes: zero coordinates, ``valid`` False) or ``"edge"`` (copies of
            the last row, for kernels that must see real-looking data).

    Returns:
        The padded pytree (the input itself where n == size).
    """
    if mode not in ("zeros", "edge"):
        raise ValueError(f"mode must be 'zeros' or 'edge', got {mode!r}")

    def pad(a):
        extra = size - a.shape[0]
        if extra < 0:
            raise ValueError(f"cannot pad {a.shape[0]} rows to {size}")
        if extra == 0:
            return a
        xp = np if isinstance(a, np.ndarray) else jnp
        if mode == "edge":
            return xp.concatenate([a, xp.broadcast_to(a[-1:], (extra, *a.shape[1:]))])
        return xp.pad(a, [(0, extra)] + [(0, 0)] * (a.ndim - 1))

    return jax.tree.map(pad, tree)
