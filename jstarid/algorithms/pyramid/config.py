"""Settings of the pyramid baseline (Mortari et al. 2004)."""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax

__all__ = ["Config", "Tuning"]


class Tuning(NamedTuple):
    """Traced tolerance: ``eps_px`` () float32, the pair-angle tolerance ε (px at the focal length)."""

    eps_px: jax.Array


@dataclasses.dataclass(frozen=True)
class Config:
    """Pyramid settings.

    Attributes:
        n_stars: the brightest N valid detections the triples and fourth stars are taken from.
        eps_px: pair-angle tolerance ε (px; ε_rad = eps_px / f_px) of every k-vector window and check.
            The paper sizes ε from the centroid accuracy; 3 px covers about 2 σ of a pair's angle at
            σ = 1 px (a pair's error is √2 σ).
        n_triples: the first T triples of the pyramid's order (Mortari et al. §"star selection":
            ``for dj, for dk, for i: (i, i + dj, i + dj + dk)``) that are tried; the first one whose
            triangle is confirmed wins. A fixed T keeps the work per scene bounded.
        min_confirm: fourth detections that must confirm a triangle. The paper asks for one; on a
            dense catalog one chance confirmation among a triple's dozens of candidate triangles is
            common (≈ 0.1 % per candidate and detection at ε = 3 px, V ≤ 6), so ``Config()`` asks
            for two (extension; ``Config.paper()``: 1).
        triangle_capacity: candidate catalog triangles kept per triple. A triple with more is
            flagged (``Diagnostics.overflow``) and not used: its list would be cut.
        star_capacity: catalog pairs of one star inside one window (the triangle join); more is
            flagged like the above.
        batch_chunk: scenes per compiled call. map_chunk: scenes vmapped together inside a call.
    """

    n_stars: int = 8
    eps_px: float = 3.0
    n_triples: int = 12
    min_confirm: int = 2
    triangle_capacity: int = 64
    star_capacity: int = 16
    batch_chunk: int = 128
    map_chunk: int = 1

    def __post_init__(self):
        if not (isinstance(self.n_stars, int) and self.n_stars >= 4):
            raise ValueError(f"n_stars must be an integer ≥ 4 (a triangle and a fourth star), "
                             f"got {self.n_stars}")
        if not (math.isfinite(self.eps_px) and self.eps_px > 0):
            raise ValueError(f"eps_px must be a positive number of pixels, got {self.eps_px}")
        if not (isinstance(self.n_triples, int) and 1 <= self.n_triples <= math.comb(self.n_stars, 3)):
            raise ValueError(f"n_triples must be in [1, C(n_stars, 3)], got {self.n_triples}")
        if not (isinstance(self.min_confirm, int) and 1 <= self.min_confirm <= self.n_stars - 3):
            raise ValueError(f"min_confirm must be in [1, n_stars − 3], got {self.min_confirm}")
        if min(self.triangle_capacity, self.star_capacity, self.batch_chunk, self.map_chunk) < 1:
            raise ValueError("capacities and chunk sizes must be ≥ 1")

    @classmethod
    def paper(cls, **overrides) -> Config:
        """The paper's algorithm: one confirming fourth star."""
        return cls(**{"min_confirm": 1, **overrides})

    def tuning(self) -> Tuning:
        return Tuning(eps_px=jax.numpy.float32(self.eps_px))

    def database_fields(self) -> dict:
        """The pair table depends on the catalog and the camera's field only."""
        return {}
