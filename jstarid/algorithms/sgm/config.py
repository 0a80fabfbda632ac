"""SGM settings (You et al. 2022, Table 1) plus the static sizes of the JAX implementation."""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar, NamedTuple

import jax
import numpy as np

from jstarid.camera import radius_that_fits, tolerance_scales
from jstarid.config_tree import Switched, nested, value_at, with_fields
from jstarid.finishing import Finishing

__all__ = ["Config", "Ladder", "Matching", "Screen", "Subgraph", "Tuning", "Verify", "with_tuning"]

# Angles that are really centroid errors (or sums of them: the MST weight window), so they scale
# with the pixel's angle (Config.for_camera); c, in 1/deg, scales inversely.
_PIXEL_TOLERANCES = ("dw0_deg", "dw_step_deg", "dw_max_deg", "max_error_deg", "leftover_tol_deg",
                     "verify.floor_deg", "verify.cap_deg", "verify.ambiguity_deg",
                     "ladder.dw_max_deg", "screen.tol_deg", "subgraph.tol_deg")


class Tuning(NamedTuple):
    """SGM's sweepable tolerances (:func:`~jstarid.algorithms.sgm.tuning.grid_identifications` takes a
    grid of each as an array axis; scalars by default).

    Attributes:
        c: edge-similarity adjustor of eq. 2 (1/deg).
        max_error_deg: ε_δ, matching-error threshold of Algorithm 1 (deg).
    """

    c: jax.Array | float
    max_error_deg: jax.Array | float


@dataclasses.dataclass(frozen=True)
class Matching:
    """How Algorithm 1's rough search and spectral matching spend their work (none of these changes
    which J* is found, beyond the power iteration's convergence).

    Attributes:
        chunk_size: candidate ranks per scene in the search's first step (doubling per step, ≤ 512).
        power_iterations: largest number of power-iteration steps (30: the same correspondences as 400).
        power_tol: stop a pair's power iteration once no entry of its unit vector moves more than this
            in a step (0: never early).
        prune: extension that changes only the work: skip matching candidates whose δ provably exceeds
            ε_δ or a δ* ≤ ε_δ already found (:mod:`.bound`); ``False`` matches every candidate;
            ``None`` (default): on exactly when the screen is off (:attr:`Config.pruning`). Why: the
            screen leaves ≈ 0.5 % of the candidates at σ = 3 px, and bounding those cost more than
            matching them (experiments/RESULTS.md, Throughput).
        prune_max_skip: candidates whose vertex count differs from the image graph's by more than this
            get only the edge bound (the row bound's cost grows with it).
        memory_budget_mb: bound on the affinity matrices held at once by one matching call (MiB).
    """

    chunk_size: int = 16
    power_iterations: int = 30
    power_tol: float = 1e-4
    prune: bool | None = None
    prune_max_skip: int = 8
    memory_budget_mb: int = 1024

    def __post_init__(self):
        if self.power_tol < 0 or self.prune_max_skip < 0:
            raise ValueError("power_tol and prune_max_skip must be ≥ 0")
        if min(self.chunk_size, self.power_iterations, self.memory_budget_mb) < 1:
            raise ValueError("chunk_size, power_iterations and memory_budget_mb must be ≥ 1")


@dataclasses.dataclass(frozen=True)
class Screen(Switched):
    """The triangle screen (extension, :mod:`.screen`): before it is matched, a candidate must pass a
    rotation about the main star that brings at least ``fraction`` of the smaller graph's vertices onto
    the other's; a candidate that fails is struck out as if its δ exceeded ε_δ. Why: under noise 94 %
    of the matched candidates fail by far (δ ≈ 5–7.5 ε_δ) and the exact bounds cannot exclude them
    (docs/design/sgm.md).

    Attributes:
        on: screen the candidates (off in :meth:`Config.paper`).
        tol_deg: position tolerance of one star (deg; 0.25° ≈ 3 σ of a star's offset from the main
            star at σ = 3 px on ``sgm2022``, two centroid errors of 0.059°; scales with the pixel).
        fraction: share of the smaller graph's vertices the best rotation must explain (0.6: true
            graphs ≥ 0.89 at σ = 3 px, wrong ones 0.44 at their 90th percentile).
        partners: database neighbors of nearest radius tried per image neighbor.
        hypotheses: image neighbors (the first in vertex order, i.e. the brightest) tried as the one
            that fixes the rotation.
    """

    on: bool = True
    tol_deg: float = 0.25
    fraction: float = 0.6
    partners: int = 4
    hypotheses: int = 8

    def __post_init__(self):
        if self.tol_deg <= 0 or not 0 <= self.fraction <= 1 or self.partners < 1 or self.hypotheses < 1:
            raise ValueError("need screen tol_deg > 0, fraction in [0, 1], partners ≥ 1 and "
                             "hypotheses ≥ 1")


@dataclasses.dataclass(frozen=True)
class Subgraph(Switched):
    """The magnitude-robust search (extension, :mod:`.subgraph`): database graphs found by the image
    neighbors' radii instead of the MST weight, screened, and matched with unmatched vertices allowed on
    both sides — for frames whose detections do not stop at the catalog's magnitude limit (real ones:
    the image and database graphs of the real test frames share 9–12 stars while each holds others;
    RESULTS, Real images).

    Attributes:
        on: search this way instead of the paper's rough search and matching (``Config.FRAME_SETTINGS``
            turns it on for detections from real frames).
        tol_deg: radius tolerance of the rough search (deg; scales with the pixel). Tight, because a
            tight vote is rare by chance (0.04°: 0.03° on ``tetra3_test``, where the real frames'
            radii agree within 0.005° and the true graph ranks 0–5th of 15,563; at 0.08° it ranked
            200–300th); a true star whose radius misses it costs one vote. The outlier removal uses
            ``Screen.tol_deg``.
        candidates: database graphs of most radius votes screened per image graph.
        matchings: of those, the ones of most screen support matched spectrally.
        main_stars: a scene left unsolved is searched again with the next detection nearest the
            principal point as its main star, up to this many main stars (a detection that is no
            catalog star — a fainter star, a hot pixel — cannot be matched).
    """

    on: bool = False
    tol_deg: float = 0.04
    candidates: int = 256
    matchings: int = 8
    main_stars: int = 3

    def __post_init__(self):
        if self.tol_deg <= 0 or min(self.candidates, self.matchings, self.main_stars) < 1:
            raise ValueError("need subgraph tol_deg > 0 and candidates, matchings, main_stars ≥ 1")


@dataclasses.dataclass(frozen=True)
class Verify(Switched):
    """The verification of every named star against the named stars' attitude (extension,
    :mod:`.verify`); the scene fails when the main star is unnamed or fewer than
    ``Config.min_matched`` or half remain.

    Attributes:
        on: verify (``False``: the paper).
        k: residual tolerance in robust-RMS units (3.5: a true star exceeds it with probability
            exp(−3.5²) ≈ 5·10⁻⁶).
        floor_deg, cap_deg: bounds of the tolerance (deg): 0.02° ≈ 1 px of the sgm2022 camera;
            0.3° ≈ 3.5 × the residual RMS at the paper's largest noise, σ = 3 px.
        ambiguity_k: margin k of the ambiguity guard (robust-RMS units s): a star with a rival catalog
            star within ``max(3·tol, ambiguity_deg)`` keeps its name only when
            ``d_alt² − d_own² ≥ (k·s)²``, e^{k²} times likelier (3.0: a near-tie errs with probability
            ≤ Φ(−√(2k²)) ≈ 1.1·10⁻⁵).
        ambiguity_deg: smallest window of the ambiguity guard (deg).
        partner_joint: the partner rule (:mod:`.verify` step 3): a name whose rival has a detection
            of its own is also kept by the joint exchange test alone, with margin ``partner_k``;
            ``False``: both tests.
        partner_k: margin of the partner rule (robust-RMS units); one test instead of two, so larger:
            at 3.5 wrong names pass with probability ≤ Φ(−√24.5) ≈ 4·10⁻⁷ per decision.
        magnitude_sigma: ``None`` (SGM is magnitude-free); when set, the ambiguity tests add each
            hypothesis' magnitude cost ``(m_obs − V)² / (2σ²)`` with this σ (mag).
        rms_z: the ambiguity margins' s (:func:`.verify._upper_rms`) is too small with probability
            Φ(−z) (16 % at 1.0).
        rename: detections the verification unnamed are named again from the verified attitude and the
            scene verified again, keeping the first result if that fails (needs
            ``Config.leftover_tol_deg``). Why: a wrongly paired detection is unnamed only after the
            leftover naming.
        retries: a rejected match is struck out and Algorithm 1 resumes (:class:`.search.SearchState`),
            at most this many times per scene (0 = fail at the first rejection); not when only a close
            rival contests the main star. Why: ε_δ = 0.4° admits wrong graphs at small Δw before the
            right one.
        min_coverage: fraction of the catalog stars the verified attitude projects inside the frame
            (inset by ``cap_deg``) that need a detection within ``cap_deg`` (0 = off); 0.4 as in
            RpNet.
    """

    on: bool = True
    k: float = 3.5
    floor_deg: float = 0.02
    cap_deg: float = 0.3
    ambiguity_k: float = 3.0
    ambiguity_deg: float = 0.2
    partner_joint: bool = True
    partner_k: float = 3.5
    magnitude_sigma: float | None = None
    rms_z: float = 1.0
    rename: bool = True
    retries: int = 3
    min_coverage: float = 0.4

    def __post_init__(self):
        if self.retries < 0:
            raise ValueError(f"verify retries must be ≥ 0, got {self.retries}")
        if (self.k <= 0 or not 0 < self.floor_deg <= self.cap_deg or self.ambiguity_k < 0
                or self.ambiguity_deg < 0 or self.partner_k < 0 or self.rms_z < 0
                or not 0 <= self.min_coverage <= 1
                or (self.magnitude_sigma is not None and self.magnitude_sigma <= 0)):
            raise ValueError("need verify k > 0, 0 < floor_deg ≤ cap_deg, non-negative ambiguity "
                             "settings, min_coverage in [0, 1] and magnitude_sigma None or > 0")


@dataclasses.dataclass(frozen=True)
class Ladder:
    """SGM's own settings for the focal-length ladder's searches (the ladder itself:
    ``Config.finishing``).

    Attributes:
        dw_max_deg: Δw_max of those searches (deg; ``None``: ``Config.dw_max_deg``). Why: a scene the
            rescaled camera explains is found at small Δw, and the scenes left are mostly ones no
            focal length solves, which would search every level four more times (300 scenes at
            f × 0.98, σ = 0.5 px: 260 → 271 solved for 1.3 × the time at 1°, 288 for 2.5 × at 6°;
            at the true focal length and σ = 3 px, 266 → 269 at 1.3 ×).
        whole_circle: extension, on (not with ``Subgraph.on``): a scene the ladder solved is kept only
            where every star of its image circle is named (a member with no unnamed catalog star
            within ``Config.leftover_tol_deg`` of its direction is not asked for: a false star); the
            others fail. Why: a fallback that finds the attitude but not the whole circle answers a
            scene the paper's criterion counts as not identified, and answered it lowers eq. 9's
            accuracy (lost stars, σ = 3 px: 152 of the ladder's 169 answers, 71.30 → 69.09 %).
    """

    dw_max_deg: float | None = 1.0
    whole_circle: bool = True


@dataclasses.dataclass(frozen=True)
class Config:
    """Frozen, hashable SGM configuration. Angles in degrees, as in the paper (conventions §7).

    The top-level fields are the paper's (Table 1, Algorithm 1) and the static sizes of the JAX
    implementation; each extension is a group of its own (:class:`Screen`, :class:`Subgraph`,
    :class:`Verify`, :class:`Ladder`, the shared :class:`~jstarid.finishing.Finishing`), and
    :meth:`paper` turns off those that change the outcome. A group's field is set by its dotted name
    (``--set verify.retries=0``, :func:`jstarid.config_tree.replace_at`); a bool given for a group
    switches it (``--set screen=false``). Evidence for the defaults: docs/design/sgm.md.

    Attributes:
        radius_deg: r, radius of the neighbor circle (deg).
        dw0_deg, dw_step_deg, dw_max_deg: Δw₀ (initial half-width of the rough-search window on w),
            h_Δw (its growth per step of Algorithm 1) and Δw_max (largest Δw searched), deg.
        c: edge-similarity adjustor of eq. 2 (1/deg).
        max_error_deg: ε_δ, matching-error threshold of Algorithm 1 (deg, eq. 5).
        min_stars: fewest vertices (main star included) an image graph needs; fewer → fail (a 1- or
            2-vertex graph matches anything).
        min_matched: fewest matched vertex pairs for a candidate to count; fewer → infinite error
            (eq. 5 divides by min(n_I, n_J): a 1-vertex graph would match with error 0).
        neighbor_capacity: static vertex capacity of the database and image graphs (main star
            included); ``None``: the largest database graph rounded up to ``size_bucket``. A scene with
            more detections in its circle fails (flagged, never truncated).
        size_bucket: graph sizes are padded to a multiple of this, to bound recompilation (a pair costs
            ∝ (p·q)² in padded sizes; 4 runs faster but compiles more kernels).
        max_database_mb: bound on the database's adjacency matrices (MiB): a camera and catalog
            that need more are refused before anything is built (:func:`.database.camera_problem`).
        matching: :class:`Matching`, the search's work (chunks, power iteration, pruning, memory).
        screen: :class:`Screen`, the triangle screen (extension, on).
        subgraph: :class:`Subgraph`, the magnitude-robust search (extension, off).
        main_stars: extension, off (1, the paper's one main star): a scene the search leaves
            unsolved is searched again with the next detection nearest the principal point as its
            main star, up to this many main stars (not with ``subgraph``, which has
            ``Subgraph.main_stars``). For a main star that is no catalog star (a false star, a
            planet near the centre), and for what the screen strikes out: without it, Algorithm
            1 also succeeds where only a neighbor's database graph, holding nearly the same stars,
            passes ε_δ (the spectral correspondence need not pair the two main stars), which the
            screen's rotation about the two main stars rejects. Off by default: an unsolved scene
            is searched over the whole Δw window again (3.2× the identify time at σ = 3 px), and its
            answer around another main star can leave part of the circle unnamed where the
            focal-length ladder would have named it all (experiments/RESULTS.md, "Table 2, full
            size, current default, on the same scenes").
        vertex_check_deg: extension, off (``None``): a matched vertex whose median edge residual
            ``|A_I(i,k) − A_J(π(i),π(k))|`` over the other matched vertices exceeds this (deg) is
            unnamed; the scene fails below ``min_matched``. Why: greedy binarization pairs even a star
            that crossed the circle boundary.
        leftover_tol_deg: extension, 0.3° (``None`` = off): members of the image circle the match left
            unnamed (typically a star that crossed the boundary, not in G_J) are named after the nearest
            unused catalog star within this angle (deg) under the matched stars' attitude; verified too.
        verify: :class:`Verify`, the verification of every name (extension, on).
        finishing: extension: the finishing stage (:class:`jstarid.finishing.Finishing`): the
            focal-length ladder (at f × 0.98 the verification, which fits the attitude alone, loses
            one scene in ten that the true focal length solves) and the camera check, whose radius
            is studentized for SGM (``studentized=True``: 6 σ̂ becomes 10.0 σ̂ over 12 names; the
            plain radius took back right names 3–4 px out at σ = 1 px, where σ̂ of a dozen names
            came out at half σ) and capped at ``verify.cap_deg``
            (:func:`~jstarid.algorithms.sgm.extensions.camera_check_cap_px`); a claim stands only
            at false-match probability ≤ 1e-3 (``max_false_match``; stricter than MLV's and
            RpNet's 1e-2: three or four points fit some catalog graph within SGM's tolerances, and
            its circle is all it looks at; a 10° camera with five or six stars per frame claimed
            22 of 300 frames of random points without it;
            :func:`~jstarid.algorithms.sgm.extensions.confirmed_by_the_frame`).
        ladder: :class:`Ladder`, SGM's settings for the ladder's searches.
    """

    # what :func:`jstarid.engine.default_config` sets for detections from real frames, which do not
    # stop at the catalog's magnitude limit (``frames=True``); dotted names of nested fields
    FRAME_SETTINGS: ClassVar[dict] = {"subgraph.on": True}

    radius_deg: float = 6.0
    dw0_deg: float = 0.1
    dw_step_deg: float = 0.1
    dw_max_deg: float = 6.0
    c: float = 1.74
    max_error_deg: float = 0.4
    min_stars: int = 3
    min_matched: int = 3
    neighbor_capacity: int | None = None
    size_bucket: int = 8
    max_database_mb: int = 1024
    matching: Matching = Matching()
    screen: Screen = Screen()
    subgraph: Subgraph = Subgraph()
    main_stars: int = 1
    vertex_check_deg: float | None = None
    leftover_tol_deg: float | None = 0.3
    verify: Verify = Verify()
    finishing: Finishing = Finishing(studentized=True, max_false_match=1e-3)
    ladder: Ladder = Ladder()

    def __post_init__(self):
        for name, cls in (("matching", Matching), ("screen", Screen), ("subgraph", Subgraph),
                          ("verify", Verify), ("finishing", Finishing), ("ladder", Ladder)):
            object.__setattr__(self, name, nested(cls, getattr(self, name), name))
        if not 0 < self.radius_deg < 90:
            raise ValueError(f"radius_deg must be in (0, 90), got {self.radius_deg}")
        if self.dw0_deg < 0 or self.dw_step_deg <= 0 or self.dw_max_deg < self.dw0_deg:
            raise ValueError("need 0 ≤ dw0_deg ≤ dw_max_deg and dw_step_deg > 0")
        if self.c <= 0 or self.max_error_deg < 0:
            raise ValueError("c must be > 0 and max_error_deg ≥ 0")
        if self.neighbor_capacity is not None and self.neighbor_capacity < 2:
            raise ValueError("neighbor_capacity must be ≥ 2")
        if min(self.size_bucket, self.max_database_mb) < 1:
            raise ValueError("size_bucket and max_database_mb must be ≥ 1")
        if self.min_stars < 1 or self.min_matched < 1 or self.main_stars < 1:
            raise ValueError("min_stars, min_matched and main_stars must be ≥ 1")
        dw_max = self.ladder.dw_max_deg
        if dw_max is not None and not dw_max >= self.dw0_deg:
            raise ValueError(f"ladder.dw_max_deg must be ≥ dw0_deg or None, got {dw_max}")

    @property
    def n_levels(self) -> int:
        """Number of Δw values Algorithm 1 visits: Δw₀ + l·h for l = 0 … n_levels − 1 (≤ Δw_max)."""
        return int(math.floor((self.dw_max_deg - self.dw0_deg) / self.dw_step_deg + 1e-9)) + 1

    @property
    def dw_last_deg(self) -> float:
        """The largest Δw Algorithm 1 searches (deg)."""
        return self.dw0_deg + (self.n_levels - 1) * self.dw_step_deg

    @property
    def pruning(self) -> bool:
        """Whether the search bounds candidates before matching them: ``matching.prune``, or where
        it is ``None``, not ``screen.on``."""
        prune = self.matching.prune
        return (not self.screen.on) if prune is None else bool(prune)

    @classmethod
    def paper(cls, **overrides) -> Config:
        """The paper's algorithm alone: no ``verify``, no ``leftover_tol_deg``, no triangle
        ``screen``, no ``subgraph`` search, no focal-length search or fit, no confirmation by the
        frame (pruning stays on: it changes only the work); returns, id for id, what
        :mod:`~jstarid.algorithms.sgm.reference` returns.

        Args:
            **overrides: fields to set after (a nested field by its dotted name, through a mapping:
                ``Config.paper(**{"verify.on": True})``).
        """
        return with_fields(cls(), {"verify.on": False, "leftover_tol_deg": None, "screen.on": False,
                                   "subgraph.on": False, "finishing": Finishing.off(), "main_stars": 1,
                                   **overrides})

    @classmethod
    def for_camera(cls, camera, **overrides) -> Config:
        """The defaults, with the circle and every tolerance that is really a centroid error following
        ``camera``; ``Config()`` on the papers' cameras.

        * r: :func:`jstarid.camera.radius_that_fits` — the published 6° where it fits the half field,
          else 0.9 × the half field (``tetra3_test``: 3.8°). Why: a circle that the frame cuts gives
          image graphs no database graph matches (§3.1).
        * With ``pixel`` from :func:`jstarid.camera.tolerance_scales` (1 on the papers' cameras):
          Δw₀, h_Δw, Δw_max, ε_δ and the verification's angles scale by ``pixel`` (a pixel moves
          every edge, and so the MST weight and eq. 5's error, by one pixel's angle), c of eq. 2
          by ``1 / pixel`` (it turns an edge difference into a similarity: one pixel keeps its
          weight).

        Args:
            camera: the :class:`~jstarid.Camera`.
            **overrides: fields to set after scaling (a nested field by its dotted name, through a
                mapping: ``**{"verify.retries": 0}``).
        """
        base = cls()
        pixel, _ = tolerance_scales(camera)
        changed = {"radius_deg": radius_that_fits(camera, base.radius_deg)}
        if pixel != 1.0:
            changed.update({name: value_at(base, name) * pixel for name in _PIXEL_TOLERANCES})
            changed["c"] = base.c / pixel
        return with_fields(base, {**changed, **overrides})

    def tuning(self) -> Tuning:
        """This config's sweepable tolerances as a :class:`Tuning` of scalars."""
        return Tuning(c=float(self.c), max_error_deg=float(self.max_error_deg))

    def database_fields(self) -> dict:
        """The fields that shape the database (its cache key, with the catalog fingerprint)."""
        return {"radius_deg": float(self.radius_deg), "neighbor_capacity": self.neighbor_capacity,
                "size_bucket": int(self.size_bucket)}


def with_tuning(config: Config, tuning: Tuning) -> Config:
    """``config`` with c and ε_δ taken from ``tuning`` (scalars, or arrays holding one value).

    SGM's search reads both on the host (its stop rule and the matching kernel's c), so one
    ``identify`` call serves one value of each; a grid is a batch axis of
    :func:`~jstarid.algorithms.sgm.tuning.grid_identifications` instead.

    Raises:
        ValueError: a field holding several values.
    """
    values = {}
    for name, value in zip(Tuning._fields, tuning, strict=True):
        distinct = np.unique(np.asarray(value, np.float64))
        if distinct.size != 1:
            raise ValueError(f"SGM's identify takes one {name} per call, got {distinct.size} values; "
                             "run a grid with sgm.tuning.grid_identifications (or js.grid)")
        values[name] = float(distinct[0])
    return dataclasses.replace(config, **values)
