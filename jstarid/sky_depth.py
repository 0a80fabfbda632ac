"""How deep a catalog a camera needs: catalog depths that follow the field, not a fixed V 6.0.

Two depths, both from the sky's mean star density (the Hipparcos counts brighter than V, over the
whole sky) and the camera's field:

- :func:`identification_depth` — the catalog the algorithms' patterns are drawn from: deep enough that
  an average field holds :data:`STARS_PER_FIELD` catalog stars. The rule reproduces the cameras
  whose depth was chosen by hand (an 11.4° field at V 7.0, a 20° field at V 6.0) and gives a 6°
  field about V 8.5, where the fixed V 6.0 left it 1–3 stars. Sparse fields (near the galactic
  poles) hold about a third of the mean: 40 keeps 10 or more there.
- :func:`naming_depth` — the catalog that names the remaining detections once the attitude is known
  (:func:`jstarid.name_from_attitude`): as deep as Hipparcos goes, unless a catalog that deep would
  put a star within the naming tolerance of a random direction more often than
  :data:`CHANCE_NEIGHBOUR` (coarse pixels of a wide field), then shallower.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from jstarid.catalog import FULL_DEPTH as DEEPEST  # V: the whole Hipparcos catalog
from jstarid.catalog import load_every_star

__all__ = ["identification_depth", "naming_depth", "stars_brighter_than"]

STARS_PER_FIELD = 40.0  # mean catalog stars in the field the identification catalog aims at
CHANCE_NEIGHBOUR = 0.01  # largest mean chance of a catalog star within the naming radius
SHALLOWEST = 6.0  # V: never shallower than the papers' catalog (wide fields)
DEEPEST_IDENTIFICATION = 9.5  # V: Hipparcos is complete to about V 8–9; below, counts thin out
_SKY_DEG2 = 4.0 * math.pi * math.degrees(1.0) ** 2  # 41,253 deg²


@functools.cache
def _sorted_magnitudes() -> np.ndarray:
    return np.sort(np.asarray(load_every_star().mag, np.float64))


def stars_brighter_than(v: float) -> int:
    """Hipparcos stars with V ≤ ``v`` (mag) over the whole sky."""
    return int(np.searchsorted(_sorted_magnitudes(), float(v), side="right"))


def _depth_for_count(count: float) -> float:
    """The V (mag) at which the whole sky holds ``count`` Hipparcos stars (the faintest if fewer)."""
    mags = _sorted_magnitudes()
    k = int(math.ceil(count))
    return float(mags[min(max(k, 1), len(mags)) - 1])


def field_solid_angle_deg2(camera) -> float:
    """Solid angle (deg²) of the camera's rectangular pinhole field."""
    a = math.atan(camera.width / 2.0 / camera.f_px)
    b = math.atan(camera.height / 2.0 / camera.f_px)
    return 4.0 * math.asin(math.sin(a) * math.sin(b)) * math.degrees(1.0) ** 2


def identification_depth(camera, stars_per_field: float = STARS_PER_FIELD) -> float:
    """Identification catalog depth V (mag) for ``camera`` (module docstring), rounded up to 0.1 mag.

    Args:
        camera: a :class:`~jstarid.Camera` (its size and focal length give the field).
        stars_per_field: mean catalog stars the field should hold.

    Returns:
        V in [:data:`SHALLOWEST`, :data:`DEEPEST_IDENTIFICATION`].
    """
    count = stars_per_field * _SKY_DEG2 / field_solid_angle_deg2(camera)
    v = math.ceil(_depth_for_count(count) * 10.0 - 1e-9) / 10.0
    return float(min(max(v, SHALLOWEST), DEEPEST_IDENTIFICATION))


def naming_depth(camera, tol_px: float = 2.0, *, at_least: float = SHALLOWEST,
                 chance: float = CHANCE_NEIGHBOUR) -> float:
    """Naming catalog depth V (mag) for ``camera`` and a naming tolerance (module docstring).

    Args:
        camera: a :class:`~jstarid.Camera`.
        tol_px: the naming tolerance (px).
        at_least: the shallowest depth returned (the identification catalog's, so that every name the
            algorithm gave is in the naming catalog too).
        chance: the largest mean chance of a catalog star within ``tol_px`` of a random direction.

    Returns:
        V (mag), at least ``at_least`` and at most :data:`DEEPEST`.
    """
    radius_deg = math.degrees(tol_px / camera.f_px)
    allowed = chance * _SKY_DEG2 / (math.pi * radius_deg**2)  # stars over the whole sky
    v = DEEPEST if allowed >= len(_sorted_magnitudes()) else _depth_for_count(allowed)
    return float(min(max(v, at_least), DEEPEST))
