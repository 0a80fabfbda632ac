"""Robust statistics of masked residuals (attitude-fit verification in SGM and RpNet)."""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["masked_median"]


def masked_median(x, mask, *, lower: bool = False):
    """Median of ``x[mask]`` for (N,) arrays, inside jit (the mask's count is traced).

    Args:
        x: (N,) values.
        mask: (N,) bool, the entries that count.
        lower: return the lower median (the ⌈n/2⌉-th smallest) instead of the mean of the two middle
            values when n is even.

    Returns:
        () the median; +inf when the mask is empty.
    """
    n = jnp.sum(mask)
    srt = jnp.sort(jnp.where(mask, x, jnp.inf))
    low = srt[jnp.maximum(n - 1, 0) // 2]
    if lower:
        return low
    return 0.5 * (low + srt[jnp.minimum(n // 2, x.shape[0] - 1)])
