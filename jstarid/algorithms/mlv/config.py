"""Multilayer-voting settings (MLV, Sensors 2021): a frozen, hashable dataclass, Table 1 defaults."""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import numpy as np

from jstarid.camera import tolerance_scales
from jstarid.finishing import Finishing

__all__ = ["Config", "Tuning"]

#: The settings that are centroid errors expressed as angles or feature bins (:meth:`Config.for_camera`).
_PIXEL_TOLERANCES = ("dv2", "eps_deg", "side_tol_deg", "residual_min_deg", "residual_max_deg",
                     "ambiguity_deg")


class Tuning(NamedTuple):
    """Per-scene tolerances that do not change array shapes (traced, not static): one compilation serves
    a grid of Th1/Th2/ε as a batch axis (:func:`~jstarid.algorithms.mlv.identify` takes scalars or (B,)
    arrays; :meth:`Config.tuning` gives the config's scalars).

    Attributes:
        th1, th2: int32 tolerances Th1, Th2 of eq. 7 (bins).
        eps_rad: float32 verification tolerance ε of eq. 8 (rad).
        side_tol_rad: float32 side tolerance of the vertex-matching extension (rad).
    """

    th1: jax.Array
    th2: jax.Array
    eps_rad: jax.Array
    side_tol_rad: jax.Array


@dataclasses.dataclass(frozen=True)
class Config:
    """Multilayer-voting parameters (Sensors 2021, 21, 3084; docs/conventions.md §7). Evidence for the
    defaults the paper leaves open: docs/design/mlv.md.

    Paper parameters (Table 1):
        n_stars: N, the brightest detections (and, in the database, the brightest catalog stars per
            boresight) that form the C(N, 3) triangle units. Paper: 10. At most 12: verification tests
            all 2^N subsets per scene.
        dv1: Δv1, discretization unit of the largest singular value v1 (eq. 4). Paper: 5e-5.
        dv2: Δv2, discretization unit of the second singular value v2 (eq. 4). Paper: 5e-4.
        ver_min: smallest verified cluster that counts as a success. Paper: 3.
        n_boresights: database boresights, evenly on the sphere (Fibonacci lattice). Paper: 100,000.

    Choices the paper leaves open:
        th1, th2: tolerances Th1, Th2 of eq. 7 on the *discretized* features (bins); a centroid error
            of σ px moves v̂1 by ≈ 1 bin and v̂2 by < 1 bin per px.
        eps_deg: verification tolerance ε on pair angles (eq. 8, deg); a pair angle's error is
            ≈ √2·σ px, and the attitude check pays back the looseness of 0.2°.
        candidate_capacity: K, the candidate buffer of a triangle in the first pass. A triangle with
            more is flagged (``Diagnostics.candidate_overflow``) and
            :func:`~jstarid.algorithms.mlv.identify` recomputes the chunk with a doubled K up to
            ``max_candidate_capacity``. ``None``: from the database
            (:func:`~jstarid.algorithms.mlv.identify.candidate_buffers`: 256, or where every
            triangle votes the power of two above 99 % of its own triangles' windows).
        max_candidate_capacity: the most candidates a triangle may match and still vote (extension;
            the count of those that do not is in the diagnostics). A narrow field's database packs
            hundreds of triangles into one window (``tetra3_test``: a median of 790, a tenth of its
            triangles over 1,024); one matching more than 1,024 spreads its vote over thousands of
            stars, and letting every such triangle vote cost the narrow twin 40 % of its
            throughput for the same identification rate (docs/design/mlv.md). ``None`` (the paper:
            every triangle votes): the most candidates any of the database's own triangles'
            windows holds, at least 1,024; a query beyond even that is warned about.
        candidate_pool: P, one shared candidate buffer per scene for all its triangles (``None``:
            :func:`~jstarid.algorithms.mlv.identify.candidate_buffers`). Scenes with more candidates
            are recomputed with a doubled P, up to T·K: P changes the speed, never the result.
        batch_chunk: scenes per compiled call (one host synchronisation each, for the buffer checks).
        map_batch: scenes vmapped together inside a call (``jax.lax.map`` over groups), so the
            (group, P) candidate arrays stay in the CPU cache. Speed only.
        require_unique_cluster: when different largest clusters tie, name only the detections common
            to all (failing below ``ver_min``) instead of taking the first.
        database_roll_deg: camera roll (deg) of every database boresight; ``None``: boresight k gets
            the roll k·(golden angle), so neighbouring boresights see the field in many orientations.

    Extensions (all on; off in :meth:`paper`):
        vertex_match: check each candidate triangle's three side angles against the observed ones
            within ``side_tol_deg`` and vote for the *corresponding* star only (the paper votes for all
            three at each vertex, Fig. 3); the third shape parameter removes most wrong candidates.
        side_tol_deg: side tolerance of ``vertex_match`` (deg), as ε.
        min_votes: a detection needs this many votes to have a candidate.
        attitude_check: after verification, predict every member from the attitude of the others
            (leave-one-out) and keep it only when its candidate is the nearest catalog star within
            ``residual_sigmas`` × (the scene's estimated centroid noise), clipped to
            [``residual_min_deg``, ``residual_max_deg``], no other catalog star is within
            ``ambiguity_deg``, and it is the detection nearest its star's predicted position. Why: close
            pairs swapping ids and false stars next to catalog stars.
        residual_sigmas, residual_min_deg, residual_max_deg: the attitude-check tolerance.
        outlier_sigmas, outlier_min_others: the attitude check's outlier test
            (:func:`~jstarid.algorithms.mlv.verify.attitude_check`): a member with at least
            ``outlier_min_others`` others must also lie within ``outlier_sigmas`` × the noise scale of
            the *other* members (so it cannot inflate its own tolerance); 0 turns it off.
        ambiguity_deg: a second catalog star this close to a member's predicted position makes it
            ambiguous (dropped).
        field_check: under the final cluster's attitude, at least ``field_check_fraction`` of the N
            brightest catalog stars predicted in the frame need a detection within
            ``residual_max_deg``. Why: a three-member cluster can be one chance triangle match.
        finishing: the finishing stage (:class:`jstarid.finishing.Finishing`): the focal-length
            ladder and the camera check. Why: the triangle features are angles, and 1 % of focal
            length moves them past Th1, Th2; a focal length off by 1–2 % names edge stars after
            other stars.
    """

    n_stars: int = 10
    dv1: float = 5e-5
    dv2: float = 5e-4
    ver_min: int = 3
    n_boresights: int = 100_000
    th1: int = 1
    th2: int = 1
    eps_deg: float = 0.2
    candidate_capacity: int | None = None
    max_candidate_capacity: int | None = 1024
    candidate_pool: int | None = None
    batch_chunk: int = 500
    map_batch: int = 50
    require_unique_cluster: bool = True
    database_roll_deg: float | None = None
    vertex_match: bool = True
    side_tol_deg: float = 0.2
    min_votes: int = 1
    attitude_check: bool = True
    residual_sigmas: float = 4.0
    residual_min_deg: float = 0.05
    residual_max_deg: float = 0.2
    outlier_sigmas: float = 3.0
    outlier_min_others: int = 5
    ambiguity_deg: float = 0.2
    field_check: bool = True
    field_check_fraction: float = 0.5
    finishing: Finishing = Finishing()

    def __post_init__(self):
        if not 3 <= int(self.n_stars) <= 12:
            raise ValueError(f"n_stars must be in [3, 12] (2^N subsets), got {self.n_stars}")
        for name in ("dv1", "dv2", "eps_deg", "side_tol_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive finite number, got {value}")
        if int(self.th1) < 0 or int(self.th2) < 0:
            raise ValueError("th1 and th2 must be ≥ 0")
        if int(self.ver_min) < 2:
            raise ValueError(f"ver_min must be ≥ 2, got {self.ver_min}")
        if self.candidate_pool is not None and int(self.candidate_pool) < 1:
            raise ValueError("candidate_pool must be ≥ 1 or None")
        for name in ("candidate_capacity", "max_candidate_capacity"):
            if getattr(self, name) is not None and int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be ≥ 1 or None")
        if int(self.batch_chunk) < 1 or int(self.map_batch) < 1:
            raise ValueError("batch_chunk and map_batch must be ≥ 1")
        if int(self.n_boresights) < 1:
            raise ValueError("n_boresights must be ≥ 1")
        object.__setattr__(self, "finishing", Finishing.coerce(self.finishing))

    @property
    def side_tol_rad(self) -> float:
        """Side tolerance in radians."""
        return math.radians(self.side_tol_deg)

    @property
    def eps_rad(self) -> float:
        """ε in radians."""
        return math.radians(self.eps_deg)

    @classmethod
    def paper(cls, **overrides) -> Config:
        """The paper's algorithm alone (Table 1): no vertex matching, attitude, field or camera check,
        no focal search, and every triangle votes (``max_candidate_capacity=None``)."""
        return cls(**{"vertex_match": False, "attitude_check": False, "field_check": False,
                      "finishing": Finishing.off(), "max_candidate_capacity": None,
                      **overrides})

    @classmethod
    def for_camera(cls, camera, **overrides) -> Config:
        """The defaults, with every tolerance that is really a centroid error following ``camera``.

        With ``(pixel, field) =`` :func:`jstarid.camera.tolerance_scales` (1 and 1 on the papers'
        cameras, so ``Config()`` there): Δv2, ε, the side tolerance and the attitude check's
        residual bounds and ambiguity radius scale by ``pixel`` (a pixel moves a pair angle, and v2,
        by one pixel's angle), Δv1 by ``pixel × field`` (v1 ≈ √3 − (v2² + v3²)/(2√3), so a pixel
        moves it by that angle times the triangle's size). On the narrow twin (15.8″/px, 7.6°
        diagonal): ×0.31 and ×0.12 — without them every triangle of a scene matched more than
        1,024 database triangles and half the scenes failed (docs/design/mlv.md).

        Args:
            camera: the :class:`~jstarid.Camera`.
            **overrides: fields to set after scaling.
        """
        pixel, field = tolerance_scales(camera)
        base = cls()
        scaled = {name: getattr(base, name) * pixel for name in _PIXEL_TOLERANCES}
        scaled["dv1"] = base.dv1 * pixel * field
        if pixel == 1.0 and field == 1.0:
            scaled = {}  # exactly the published values
        return dataclasses.replace(base, **{**scaled, **overrides})

    def tuning(self) -> Tuning:
        """This config's traced tolerances as a :class:`Tuning` of scalars (Th1, Th2 in bins; ε and the side
        tolerance in rad).
        """
        # float32 degrees → radians in float32, as a (B,) grid of degrees would be converted
        def rad(deg):
            return float(np.deg2rad(np.float32(deg)))

        return Tuning(th1=int(self.th1), th2=int(self.th2), eps_rad=rad(self.eps_deg),
                      side_tol_rad=rad(self.side_tol_deg))

    def database_fields(self) -> dict:
        """The settings that shape the database, its cache key (not Δv1, Δv2: they only shape the lookup
        keys computed when the cached triangle table is loaded).
        """
        return {"n_stars": int(self.n_stars), "dv1": float(self.dv1), "dv2": float(self.dv2),
                "n_boresights": int(self.n_boresights),
                "database_roll_deg": self.database_roll_deg}
