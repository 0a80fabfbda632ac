"""Settings of the grid baseline (Padgett & Kreutz-Delgado 1997)."""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax

__all__ = ["Config", "Tuning"]


class Tuning(NamedTuple):
    """Traced tolerance: ``eps_px`` () float32, the verification's pair-angle tolerance (px)."""

    eps_px: jax.Array


@dataclasses.dataclass(frozen=True)
class Config:
    """Grid algorithm settings. Radii are fractions of the frame's shorter side, so the pattern
    follows the camera.

    Attributes:
        pattern_radius: neighbours within this distance of the reference star make its pattern
            (paper: the pattern radius, a fraction of the field).
        buffer_radius: neighbours closer than this are ignored (paper: the buffer radius, so that a
            close pair blurred into one spot or split by noise does not set the orientation).
        grid: g, cells per side of the pattern's square: g² bits, stored as 32-bit words (g² must be
            a multiple of 32).
        n_refs: the detections nearest the frame's centre used as reference stars (their pattern
            circle is the most inside the frame).
        min_overlap: fewest common bits for a reference star's best match to count.
        eps_px: the verification's tolerance (px at the focal length): two named references agree
            when their stars' angle is within ε of the measured one.
        min_verified: fewest mutually agreeing references for a scene to be claimed. The paper names
            each reference by its best pattern; a lost-in-space answer needs a check, and this pair-
            angle consistency (as in the other baselines) is our choice, in ``Config.paper()`` too.
        batch_chunk: scenes per compiled call.
    """

    pattern_radius: float = 0.3
    buffer_radius: float = 0.02
    grid: int = 32
    n_refs: int = 8
    min_overlap: int = 4
    eps_px: float = 3.0
    min_verified: int = 3
    batch_chunk: int = 256

    def __post_init__(self):
        if not (0 < self.buffer_radius < self.pattern_radius <= 1.0):
            raise ValueError("need 0 < buffer_radius < pattern_radius ≤ 1 (fractions of the shorter side)")
        if not (isinstance(self.grid, int) and self.grid >= 4 and (self.grid * self.grid) % 32 == 0):
            raise ValueError(f"grid must be an integer ≥ 4 with grid² a multiple of 32, got {self.grid}")
        if not (isinstance(self.n_refs, int) and self.n_refs >= 2):
            raise ValueError(f"n_refs must be an integer ≥ 2, got {self.n_refs}")
        if not (isinstance(self.min_verified, int) and 2 <= self.min_verified <= self.n_refs):
            raise ValueError(f"min_verified must be in [2, n_refs], got {self.min_verified}")
        if self.min_overlap < 1:
            raise ValueError(f"min_overlap must be ≥ 1, got {self.min_overlap}")
        if not (math.isfinite(self.eps_px) and self.eps_px > 0):
            raise ValueError(f"eps_px must be a positive number of pixels, got {self.eps_px}")
        if self.batch_chunk < 1:
            raise ValueError("batch_chunk must be ≥ 1")

    @classmethod
    def paper(cls, **overrides) -> Config:
        """The paper's algorithm: ``Config()`` adds no extension (the check is documented above)."""
        return cls(**overrides)

    def tuning(self) -> Tuning:
        return Tuning(eps_px=jax.numpy.float32(self.eps_px))

    def database_fields(self) -> dict:
        return {"pattern_radius": self.pattern_radius, "buffer_radius": self.buffer_radius, "grid": self.grid}
