"""Robust statistics of masked residuals: the attitude-fit verification of SGM and RpNet, and the
brightness test of names (a detection against the catalog magnitude of its star)."""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["brighter_than_named", "magnitude_offsets", "masked_median"]

MAD_TO_SIGMA = 1.4826  # σ of a Gaussian per median absolute deviation


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


def magnitude_offsets(det_mag, star_mag, named):
    """Each detection's brightness against its star, relative to the scene's named stars.

    Detections carry instrumental magnitudes (any zero point), so only the offset
    ``(det_mag − star_mag) − median over the named`` tells a name apart.

    Args:
        det_mag: (N,) observed magnitudes (mag). star_mag: (N,) catalog V of each detection's
            star (anything where not used). named: (N,) bool, the names that set the zero point.

    Returns:
        ``(offset, spread, count)``: (N,) offsets (mag, negative: brighter than its star), the
        robust σ̂ of the named offsets (1.4826 × MAD, mag) and the number of names.
    """
    diff = det_mag - star_mag
    zero = masked_median(diff, named)
    spread = MAD_TO_SIGMA * masked_median(jnp.abs(diff - zero), named)
    return diff - zero, spread, jnp.sum(named)


def brighter_than_named(det_mag, star_mag, named, *, tol_mag: float, sigmas: float, min_names: int = 4):
    """(N,) bool: named detections far *brighter* than their star, by the other names' zero point.

    A detection is flagged when its offset (:func:`magnitude_offsets`) is below
    ``−max(tol_mag, sigmas · σ̂)``. One-sided on purpose: saturation and a star at a bright limit
    make real detections fainter than their catalog V, while a detection far brighter than its
    star is another object (a false star, a planet, a hot pixel) lying where that star should be.
    With fewer than ``min_names`` names nothing is flagged (no zero point to trust).

    Args:
        det_mag, star_mag, named: as in :func:`magnitude_offsets`, (N,) each.
        tol_mag: the smallest offset (mag) that counts. sigmas: … in units of σ̂.
        min_names: fewest names from which the test is made.
    """
    offset, spread, count = magnitude_offsets(det_mag, star_mag, named)
    return named & (count >= min_names) & (offset < -jnp.maximum(tol_mag, sigmas * spread))
