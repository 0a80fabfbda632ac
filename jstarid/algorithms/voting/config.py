"""Settings of the geometric-voting baseline (Kolomenkin et al. 2008)."""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax

__all__ = ["Config", "Tuning"]


class Tuning(NamedTuple):
    """Traced tolerance: ``eps_px`` () float32, the pair-angle tolerance ε in pixels at the focal
    length (a grid of values shares one compilation as long as each fits the static window)."""

    eps_px: jax.Array


@dataclasses.dataclass(frozen=True)
class Config:
    """Geometric voting settings.

    Attributes:
        n_stars: the brightest N valid detections that vote and are named. The paper votes with every
            detection; a fixed N keeps the work per scene bounded (C(N, 2) pair queries) and leaves
            the faint ones, the likeliest to be false or noisy, out. The true star's votes grow as
            N − 1 and the background's spread as √N, so more stars separate them better.
        eps_px: pair-angle tolerance ε (px; ε_rad = eps_px / f_px), used by both the voting window and
            the verification (paper: ε follows the centroid accuracy). Every window lets in ≈ 2W/S
            background votes per catalog star (W catalog pairs in the window, S stars) against the
            true star's one, and W grows with ε: on a 20° field with the V ≤ 6 sky (5,000 stars)
            ε = 1 px already gives W ≈ 2,400, so the votes single out the true star only when the
            centroids are good to a fraction of a pixel (experiments/RESULTS.md, baselines). This is
            the method's known limit with dense catalogs, kept as published.
        min_verified: fewest mutually consistent names for a scene to be claimed. Four names are
            checked by six pair angles; three by only three, which a chance triangle of the catalog
            can pass.
        attitude_check: extension: the verified names' Wahba attitude must place every one of them
            within ε of its detection; a name it cannot place is taken back (the scene fails below
            ``min_verified``).
        batch_chunk: scenes per compiled call (memory: each scene holds C(N, 2) × window slots).
        map_chunk: scenes vmapped together inside a call.
    """

    n_stars: int = 20
    eps_px: float = 1.0
    min_verified: int = 4
    attitude_check: bool = True
    batch_chunk: int = 128
    map_chunk: int = 8

    def __post_init__(self):
        if not (isinstance(self.n_stars, int) and self.n_stars >= 3):
            raise ValueError(f"n_stars must be an integer ≥ 3, got {self.n_stars}")
        if not (math.isfinite(self.eps_px) and self.eps_px > 0):
            raise ValueError(f"eps_px must be a positive number of pixels, got {self.eps_px}")
        if not (isinstance(self.min_verified, int) and 3 <= self.min_verified <= self.n_stars):
            raise ValueError(f"min_verified must be an integer in [3, n_stars], got {self.min_verified}")
        if self.batch_chunk < 1 or self.map_chunk < 1:
            raise ValueError("batch_chunk and map_chunk must be ≥ 1")

    @classmethod
    def paper(cls, **overrides) -> Config:
        """The paper's voting and verification alone (no attitude check)."""
        return cls(**{"attitude_check": False, **overrides})

    def tuning(self) -> Tuning:
        return Tuning(eps_px=jax.numpy.float32(self.eps_px))

    def database_fields(self) -> dict:
        """The pair table depends on the catalog and the camera's field only."""
        return {}
