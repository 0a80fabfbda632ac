"""RpNet settings: frozen, hashable dataclasses with the paper's defaults (Xu et al. 2019; conventions §7).

:class:`Training` (Table 3 hyper-parameters, the noise families of §II-C) and :class:`Config` (input,
guide catalog, network, training, identification of §II-E). What shapes the trained network enters
:meth:`Config.database_fields`, the key of the cached checkpoint; identification settings do not.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jstarid.camera import radius_that_fits, tolerance_scales
from jstarid.detection_model import DetectionModel
from jstarid.finishing import Finishing
from jstarid.runtime.static import static_config

__all__ = ["Config", "GUIDE_ORDERS", "Training", "Tuning"]

GUIDE_ORDERS = ("centre", "brightness")

#: Fewer guides of the published V ≤ 6 catalog than this in a camera's frame (on average) make
#: :meth:`Config.for_camera` switch to guides thinned per sky cell (a narrow, deep field).
MIN_GUIDES_PER_FRAME = 6.0
#: The published guide catalog's density: 5,044 stars of V ≤ 6 on 41,253 deg² (per deg²).
PAPER_GUIDE_DENSITY = 5044 / 41253
#: Guides per sky cell and the cells' size (≈ 3 guides' worth of frame area each) in that case.
GUIDES_PER_CELL = 2
#: Guide triples on such a camera (the 12 brightest detections, and the pool pass across them);
#: one pair per triple. On the narrow twin the further triples and pairs named no more frames.
NARROW_GUIDE_TRIPLES = 4
#: Detections simulated per training scene for a camera with per-cell guides (brightest first).
DEEP_SIM_CAPACITY = 128
#: Largest classifier layer (hidden width × classes) :meth:`Config.for_camera` keeps, ≈ 1.25 × the
#: published 512 × 5,044; a longer guide list halves the hidden width until it fits, so that
#: training keeps its cost (quick: ≈ 5 minutes on 2 cores). On the narrow twin a width of 128
#: instead of 256 trained no faster (5 min 23 s against 5 min 11 s) to 77.9 % instead of 81.9 %.
MAX_CLASSIFIER_WEIGHTS = 3_200_000
#: Finest cell grid for per-cell guides (cells per cube-face side): at most 6 · 32² · 2 = 12,288
#: guides, whatever the field (a 2° field would otherwise ask for ≈ 97,000).
MAX_GUIDE_CELL_GRID = 32
#: Longest D_sn / D_nn (bins each) :meth:`Config.for_camera` makes: the bin follows the pixel scale,
#: but on a fine camera (``2° × 4096 px``: 1.8″/px) that would give 571 bins and an input layer
#: that doubles the DAE's step cost; 256 keeps the published pattern's resolution (ρ / e = 200
#: levels of distance) and more. The papers' cameras, ``tetra3_test`` and the narrow twin are below it.
MAX_INPUT_BINS = 256


class Tuning(NamedTuple):
    """The identification settings that compiled identification reads as traced values: changing any of
    them (a sweep, a weight grid) reuses the compilation. Built by :meth:`Config.tuning`; the fields mean
    what the :class:`Config` fields of the same name mean.

    Attributes:
        pair_tol_px: () float32 px; ``inf`` when ``Config.pair_tol_px`` is None (test off).
        match_tol_px, anchor_radius_px, match_sigmas, match_tol_min_px, pair_sigmas, trim_sigmas:
            () float32 (px, px, σ, px, σ, σ). outlier_ratio: () float32.
        min_verified: () int32. min_coverage: () float32 fraction.
        position_weights, probability_weights: (3,) float32 (Table 5).
    """

    pair_tol_px: jax.Array
    match_tol_px: jax.Array
    anchor_radius_px: jax.Array
    match_sigmas: jax.Array
    match_tol_min_px: jax.Array
    pair_sigmas: jax.Array
    trim_sigmas: jax.Array
    outlier_ratio: jax.Array
    min_verified: jax.Array
    min_coverage: jax.Array
    position_weights: jax.Array
    probability_weights: jax.Array


# Config fields that compiled identification never reads as compile-time constants: the traced
# thresholds, and the host loop's chunking and pass counts (passed to the kernels separately).
_NOT_COMPILED = (*Tuning._fields, "n_pair_trials", "batch_chunk", "train_detection")


@dataclasses.dataclass(frozen=True)
class Training:
    """Training hyper-parameters (paper Table 3) and the on-the-fly noise families (§II-C).

    Table 3 (PGN = denoising autoencoder, PCN = classifier): learning rate, epochs, batch 512,
    L2 = 1e-4, weight decay (PGN no, PCN yes), early stop (PGN no, PCN yes). The paper names neither
    optimizer nor schedule; read as: Adam, a penalty ``l2 · ½‖W‖²`` on the kernels, "weight decay" =
    cosine learning-rate decay to 1 %, "early stop" = keep the classifier with the best held-out
    accuracy (docs/design/rpnet.md). Data are drawn on the fly: an "epoch" is ``K × 320`` samples, and
    ``*_steps = None`` means ``epochs × K × 320 / batch``.

    Attributes:
        dae_lr, dae_epochs, dae_steps: PGN learning rate (1e-4), epochs (15), explicit step count.
        clf_lr, clf_epochs, clf_steps: PCN learning rate (1e-3), epochs (10), explicit step count.
        batch_size: samples per step (512); a multiple of 4 (the four noise families, one quarter each).
        l2: L2 penalty coefficient (1e-4) on the dense kernels.
        clf_lr_decay: cosine decay of the PCN learning rate ("weight decay: yes").
        early_stop: keep the PCN parameters with the best held-out accuracy.
        eval_every: steps between held-out evaluations (progress bar, early stop).
        eval_size: held-out samples (a multiple of 4), drawn once from a separate key.
        position_sigmas_px: position-noise family levels (0.2–1.6 px, step 0.2; §II-C.1).
        magnitude_sigmas: magnitude-noise family levels (mag; §II-C.2), simulated from a V 7.0 list.
        max_missing: missing-star family, 1..max_missing stars removed (§II-C.3).
        max_false: false-star family, 1..max_false stars within ρ of the guide star (§II-C.4).
        false_mag_range: false-star magnitudes, uniform (0–6 mag in the paper).
        sim_capacity: detections kept per simulated training scene (brightest first).
        pool_batches: ``None``: a fresh batch every step (the paper-like stream); n: draw n batches once
            and cycle through them (CPU runs and tests, where simulation would dominate).
        seed: PRNG seed of the training run (data, initialisation).
    """

    dae_lr: float = 1e-4
    dae_epochs: float = 15.0
    dae_steps: int | None = None
    clf_lr: float = 1e-3
    clf_epochs: float = 10.0
    clf_steps: int | None = None
    batch_size: int = 512
    l2: float = 1e-4
    clf_lr_decay: bool = True
    early_stop: bool = True
    eval_every: int = 500
    eval_size: int = 2048
    position_sigmas_px: tuple[float, ...] = (0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6)
    magnitude_sigmas: tuple[float, ...] = (0.323, 0.484, 0.646, 0.807, 0.969)
    max_missing: int = 5
    max_false: int = 5
    false_mag_range: tuple[float, float] = (0.0, 6.0)
    sim_capacity: int = 96
    pool_batches: int | None = None
    seed: int = 0

    def __post_init__(self):
        if self.batch_size % 4 or self.eval_size % 4:
            raise ValueError("batch_size and eval_size must be multiples of 4 (one quarter per family)")

    def steps(self, n_guides: int) -> tuple[int, int]:
        """(DAE steps, classifier steps) for a guide catalog of ``n_guides`` stars."""
        epoch = n_guides * 320 / self.batch_size  # 320 noise samples per guide star (§II-C)
        dae = self.dae_steps if self.dae_steps is not None else math.ceil(self.dae_epochs * epoch)
        clf = self.clf_steps if self.clf_steps is not None else math.ceil(self.clf_epochs * epoch)
        return int(dae), int(clf)

    @classmethod
    def paper(cls) -> Training:
        """Table 3 scale: 15 + 10 epochs of K × 320 samples, batch 512."""
        return cls()

    @classmethod
    def quick(cls) -> Training:
        """A smoke-scale run (minutes on a CPU for K = 5,044 guides): the paper's losses, families and
        optimiser; 3,000 + 3,000 steps of 256 samples (≈ 1.5 M samples vs 41 M) and a 10× higher DAE
        learning rate (1e-3) so that the short run gets somewhere. Not expected to reach paper accuracy.
        """
        return cls(dae_lr=1e-3, dae_steps=3000, clf_steps=3000, batch_size=256, eval_every=250,
                   eval_size=1024)


@dataclasses.dataclass(frozen=True)
class Config:
    """RpNet parameters (Xu et al. 2019, IEEE Access 7, 92 193; docs/conventions.md §7). Evidence for the
    defaults of the extensions: docs/design/rpnet.md.

    Initial input (§II-A, eq. 3):
        rho_deg: pattern radius ρ (6°).
        m: number of nearest guiding neighbour stars kept (10).
        e_deg: discretization factor e (0.03°); D_sn uses bins of e, D_nn bins of 2e, each
            ⌊ρ/e⌋ = 200 long, so the input has 2⌊ρ/e⌋ = 400 entries.

    Guide catalog (§II-A):
        guide_mag_limit: faintest guide star (V 6.0).
        guide_min_sep_deg: guides closer than this to a brighter guide are dropped (0 = keep every
            catalog star; the catalog's own close-pair removal, ``double_sep_deg``, already applies).
        guides_per_cell, guide_cell_grid: (extension, narrow deep fields) keep only the
            ``guides_per_cell`` brightest guides of each cell of a cube map with ``guide_cell_grid``
            cells per face side (:func:`jstarid.sky_index.cell_of`), so that the guides cover the sky
            evenly and are the locally brightest stars (0 = off, the paper's magnitude cut alone).
        guide_order: which detections are the guides S1, S2, S3 and the later triples: ``"centre"``
            (the paper's eq. 7: nearest the principal point) or ``"brightness"`` (extension: brightest
            first, for guides thinned per cell, which are the brightest stars around).
        guide_in_frame: (extension) training puts the guide at a uniformly random position of the
            frame and drops its neighbours outside the frame (a pattern the frame cuts), instead of
            the paper's guide at the principal point with its whole circle in view.
        sim_by_family: (extension, wide fields) the three noise families without magnitude noise
            draw their scenes from the stars to the camera's limit only, the magnitude family alone
            from the deeper simulation list (:mod:`.data`): the same scenes in distribution (a star
            fainter than the limit is never detected without magnitude noise) at a third of the
            candidate stars per scene (a 40° frame: 1,042 of V ≤ 7 in the median).

    Network (Table 1, Table 2):
        gen_widths: star pattern generator widths (512, 1024): FC1 400→512, ReLU, FC2 512→1024.
            The decoder mirrors it: 1024→512, ReLU, 512→400.
        clf_width: classifier hidden width (512): FC3 1024→512, BN, ReLU, FC4 512→K.

    Training: :class:`Training` (Table 3), ``Training.paper()`` or ``Training.quick()``.
        train_detection: (extension) how the training scenes detect their stars. ``None``: the
            paper's hard cut at the camera's ``mag_limit``, the four families' knobs alone (§II-C).
            ``"sensor"``: the camera's :meth:`~jstarid.DetectionModel.from_sensor` model, or a given
            :class:`~jstarid.DetectionModel` (e.g. one fitted to the camera's real frames): every
            family's scene is drawn from it — completeness falling off past the threshold, noise and
            bias growing with magnitude (no blends) — with the family's knob on top (position σ and
            magnitude σ as floors, the missing and false stars as they are), keeping as many of its
            brightest detections as the paper's scene of the same key holds (:mod:`.data`). Why: a
            real frame's patterns hold stars fainter than the catalog and lose some near the
            threshold. Off by default: on the frames measured it gained nothing
            (docs/design/rpnet.md).

    Identification (§II-E, eqs. 9–11, Table 5):
        n_candidates: candidates per guide (3 in the paper: 27 candidate pairs).
        position_weights: po_i of the three detections nearest the centre (0.45, 0.30, 0.25).
        probability_weights: pr_j of the three candidates by rank (0.60, 0.25, 0.15).
        pair_tol_px: extension: keep a candidate pair only when its catalog angle agrees with the
            observed angle within this many px (via f_px), besides the paper's field-of-view test
            (eq. 10). ``None`` = the paper's test only.
        match_tol_px: after the confident pair fixes the attitude, a detection is named when a catalog
            star projects within this distance (px) and neither a second star nor another detection
            competes (first pass; also the bound of the last pass and of the pair's own detections).
        anchor_radius_px: first naming pass: a detection is named by its angular distances to the two
            pair stars (roll-free, within ``match_tol_px``) among catalog stars within this radius (px)
            of where the pair attitude puts it (must exceed the roll error × distance from the pair).
        n_refine: naming / Wahba refit passes at ``match_tol_px`` (a close pair fixes the roll poorly;
            each pass reaches farther stars).
        match_sigmas, match_tol_min_px: last pass: tolerance ``match_sigmas · σ̂`` (σ̂ = residual RMS per
            axis of the fit on every name) clipped to [``match_tol_min_px``, ``match_tol_px``]; the
            floor keeps a tight radius at low noise, so a false star is not named after an undetected
            catalog star.
        name_isolation: (extension) last pass: a detection is named only when the second-nearest
            catalog star lies beyond ``name_isolation`` × the tolerance (1 = the nearest star within
            the tolerance wins). At 3 px a star 7–9 px from its detection, beyond the 6.5 px cap,
            left the detection to a neighbour 1–6 px away: 3 wrong names in the demo's 200 scenes
            at 3 px, none at 1.5 (docs/design/rpnet.md).
        trim_sigmas, outlier_ratio: robust refit before the last pass (one step of least trimmed
            squares): fit the better half of the names, then every name within ``trim_sigmas`` × that
            fit's median-based σ̂ (:func:`.identify.noise_sigma`); it replaces the fit on all names when
            its RMS σ̂ is ``outlier_ratio`` times smaller (wrong names inflate the residuals; with clean
            noise the two agree and the plain fit is kept).
        pair_sigmas: the confident pair's two detections (named by the network, not by proximity) keep
            their names out to ``pair_sigmas · σ̂`` (clipped like the last pass), no further: a false
            star classified as an undetected guide star lies many σ̂ away at low noise.
        min_verified: fewest named detections (the pair included) for the scene to count as identified;
            below it the scene fails (ok = False, ids = −1). 5: the pair plus three confirmations.
        min_coverage: extension: the named detections must be at least this fraction of the catalog
            stars (V ≤ the catalog limit) the final attitude projects inside the frame (inset by
            ``match_tol_px``); 0 = off. 0.4: separates correct scenes (≥ 0.5) from wrong matches
            (≤ 0.31). A scene flagged ``overflow`` (brightest detections kept) counts at most as many
            catalog stars as it kept detections.
        n_pair_trials: extension: admissible pairs tried by decreasing score until one is confirmed
            (1 = the paper's single pair); later pairs only on the unconfirmed scenes, so the cost grows
            with the failure rate.
        n_guide_triples: extension: when no pair of S1–S3 is confirmed, the next three detections by
            distance from the centre (ranks 4–6, 7–9, …) go through steps 2–5, up to this many triples
            (1 = S1–S3 only), on the unconfirmed scenes only. 12 covers the ≈ 30–38 detections of a
            typical ``rpnet2019`` scene.
        n_pool_pairs: extension: after the triples, on the scenes still unconfirmed, this many of the
            best pairs of candidates of any two of the 3 · ``n_guide_triples`` nearest detections (eq. 11
            without position weights) are verified in score order (0 = off).
        finishing: the finishing stage (:class:`jstarid.finishing.Finishing`): the focal-length
            ladder and the camera check. With ``finishing.fit_focal`` (extension) the naming passes
            also fit the focal length with the attitude, so a camera whose focal length is off by a
            few % names its stars, not others; the ladder (``finishing.focal_search``) helps because
            the network reads a pattern of angles, and a focal length off by 2 % moves the outer
            stars of the pattern by ≈ 1.5 bins. A retry's solution needs 6 names.
        network_bf16: run the network's matmuls on bfloat16 operands with float32 accumulation
            (parameters stay float32). ``None``: bfloat16 where the hardware has it
            (:func:`.model.native_bf16`: GPU or TPU, or AVX512-BF16 / AMX-BF16 CPU flags), else
            float32 (emulated bfloat16 is slower); ``True`` / ``False`` force one.
        batch_chunk: scenes per compiled identification call; the network runs on all of them at once
            (3 × chunk inputs per matmul).
        name_chunk: scenes vmapped together in the naming steps (``lax.map`` groups; memory
            ≈ name_chunk × n_pair_trials × N × local stars floats per intermediate, kept in cache).
    """

    rho_deg: float = 6.0
    m: int = 10
    e_deg: float = 0.03
    guide_mag_limit: float = 6.0
    guide_min_sep_deg: float = 0.0
    guides_per_cell: int = 0
    guide_cell_grid: int = 0
    guide_order: str = "centre"
    guide_in_frame: bool = False
    sim_by_family: bool = False
    gen_widths: tuple[int, int] = (512, 1024)
    clf_width: int = 512
    training: Training = Training()
    train_detection: DetectionModel | str | None = None
    n_candidates: int = 3
    position_weights: tuple[float, float, float] = (0.45, 0.30, 0.25)
    probability_weights: tuple[float, float, float] = (0.60, 0.25, 0.15)
    pair_tol_px: float | None = 5.0
    match_tol_px: float = 6.5
    anchor_radius_px: float = 60.0
    n_refine: int = 3
    match_sigmas: float = 3.5
    match_tol_min_px: float = 1.5
    name_isolation: float = 1.5
    pair_sigmas: float = 8.0
    trim_sigmas: float = 6.0
    outlier_ratio: float = 1.5
    min_verified: int = 5
    min_coverage: float = 0.4
    n_pair_trials: int = 3
    n_guide_triples: int = 12
    n_pool_pairs: int = 8
    finishing: Finishing = Finishing()
    network_bf16: bool | None = None
    batch_chunk: int = 512
    name_chunk: int = 64

    def __post_init__(self):
        if not self.name_isolation >= 1.0:
            raise ValueError(f"name_isolation must be ≥ 1, got {self.name_isolation}")
        if not 0 < self.e_deg < self.rho_deg:
            raise ValueError(f"need 0 < e < ρ, got e={self.e_deg}, ρ={self.rho_deg}")
        if self.m < 1:
            raise ValueError(f"m must be ≥ 1, got {self.m}")
        if not 0.0 <= self.min_coverage <= 1.0:
            raise ValueError(f"min_coverage must be in [0, 1], got {self.min_coverage}")
        if min(self.match_sigmas, self.pair_sigmas, self.trim_sigmas) <= 0 or self.outlier_ratio < 1:
            raise ValueError("match_sigmas, pair_sigmas, trim_sigmas must be > 0 and outlier_ratio ≥ 1")
        if not 1 <= self.n_pair_trials <= 27:
            raise ValueError(f"n_pair_trials must be in [1, 27], got {self.n_pair_trials}")
        object.__setattr__(self, "finishing", Finishing.coerce(self.finishing))
        if self.n_pool_pairs < 0:
            raise ValueError(f"n_pool_pairs must be ≥ 0, got {self.n_pool_pairs}")
        if self.n_guide_triples < 1:
            raise ValueError(f"n_guide_triples must be ≥ 1, got {self.n_guide_triples}")
        if self.guide_order not in GUIDE_ORDERS:
            raise ValueError(f"guide_order must be one of {GUIDE_ORDERS}, got {self.guide_order!r}")
        if self.guides_per_cell < 0 or (self.guides_per_cell > 0) != (self.guide_cell_grid > 0):
            raise ValueError("guides_per_cell and guide_cell_grid must both be > 0 (thinning per cell) "
                             f"or both 0, got {self.guides_per_cell} and {self.guide_cell_grid}")
        if not (self.train_detection is None or self.train_detection == "sensor"
                or isinstance(self.train_detection, DetectionModel)):
            raise ValueError("train_detection must be None, 'sensor' or a DetectionModel, got "
                             f"{self.train_detection!r}")
        if isinstance(self.train_detection, DetectionModel):
            self.train_detection.validate()
        if self.n_candidates != 3 or len(self.position_weights) != 3 or len(self.probability_weights) != 3:
            raise ValueError("the weight search uses three detections and three candidates (Table 5)")

    def tuning(self) -> Tuning:
        """The traced identification settings (:class:`Tuning`) as device arrays."""
        f32 = functools.partial(jnp.asarray, dtype=jnp.float32)
        return Tuning(
            pair_tol_px=f32(jnp.inf if self.pair_tol_px is None else self.pair_tol_px),
            match_tol_px=f32(self.match_tol_px), anchor_radius_px=f32(self.anchor_radius_px),
            match_sigmas=f32(self.match_sigmas), match_tol_min_px=f32(self.match_tol_min_px),
            pair_sigmas=f32(self.pair_sigmas), trim_sigmas=f32(self.trim_sigmas),
            outlier_ratio=f32(self.outlier_ratio), min_verified=jnp.asarray(self.min_verified, jnp.int32),
            min_coverage=f32(self.min_coverage),
            position_weights=f32(self.position_weights), probability_weights=f32(self.probability_weights))

    def compiled(self) -> Config:
        """This config with every field compiled identification does not read statically reset to its
        default: the kernels' static argument, so configs differing only in :class:`Tuning` (or host-loop
        settings) share one compilation.
        """
        # of the finishing stage the kernels read only whether the naming passes fit the focal length
        return dataclasses.replace(static_config(self, _NOT_COMPILED),
                                   finishing=Finishing(fit_focal=self.finishing.fit_focal))

    @property
    def n_bins(self) -> int:
        """⌊ρ/e⌋, the length of D_sn and of D_nn (200 at the defaults)."""
        return int(math.floor(self.rho_deg / self.e_deg + 1e-9))

    @property
    def input_size(self) -> int:
        """2⌊ρ/e⌋, the length of the initial input S_ori (400 at the defaults)."""
        return 2 * self.n_bins

    @classmethod
    def quick(cls, **overrides) -> Config:
        """Paper network and input with the :meth:`Training.quick` schedule."""
        return cls(training=Training.quick(), **overrides)

    @classmethod
    def for_camera(cls, camera, **overrides) -> Config:
        """The defaults with the pattern following ``camera``; ``Config()`` on the papers' cameras.

        * ρ: :func:`jstarid.camera.radius_that_fits` — the published 6° where it fits the inscribed
          half field, else 0.9 × that half field (``tetra3_test``: 3.8°). Why: a pattern the frame
          cuts depends on the roll and on where S1–S3 sit, which the network never saw in training
          (guide at the principal point, §II-C).
        * e (eq. 3's bin) × ``pixel`` of :func:`jstarid.camera.tolerance_scales`: a bin stays
          ≈ 2.2 px, as on the paper's camera (0.03° at 50″/px), but no finer than ρ /
          :data:`MAX_INPUT_BINS` (2° × 4096 px: 4.8 px).
        * A field wider than the papers' (``field`` of :func:`~jstarid.camera.tolerance_scales`
          above 1: a diagonal over 35°) simulates three of the four noise families from the
          stars to its limit only (``sim_by_family``): a whole 40° frame holds many stars.

        * A narrow field (fewer than :data:`MIN_GUIDES_PER_FRAME` of the published V ≤ 6 guides in
          a frame on average, e.g. the narrow twin's 6.1° × 4.6°: 3.4) gets guides from the whole
          catalog depth, the :data:`GUIDES_PER_CELL` brightest of each sky cell, with cells of about
          a third of the frame's area (≈ 6 guides per frame, anywhere on the sky); the guides are
          then the brightest detections (``guide_order="brightness"``) and sit anywhere in the frame,
          so training places them anywhere (``guide_in_frame``) and simulates
          :data:`DEEP_SIM_CAPACITY` detections; a classifier over more than
          :data:`MAX_CLASSIFIER_WEIGHTS` weights gets half the hidden width; identification tries
          :data:`NARROW_GUIDE_TRIPLES` triples of one pair each (docs/design/rpnet.md).

        The identification tolerances are in pixels already. ``overrides`` are set after (e.g.
        ``training=Training.quick()``).
        """
        base = cls()
        pixel, field = tolerance_scales(camera)
        changed = {"rho_deg": radius_that_fits(camera, base.rho_deg)}
        if pixel != 1.0:
            changed["e_deg"] = max(base.e_deg * pixel, changed["rho_deg"] / MAX_INPUT_BINS)
        area = camera.fov_x_deg * camera.fov_y_deg  # deg² (flat-sky approximation)
        narrow = PAPER_GUIDE_DENSITY * area < MIN_GUIDES_PER_FRAME
        if narrow:
            # a cube face spans 90° at its centre: cells there ≈ area / 3 (smaller towards corners)
            grid = min(MAX_GUIDE_CELL_GRID, max(1, round(90.0 / math.sqrt(area / 3.0))))
            n_guides = 6 * grid * grid * GUIDES_PER_CELL
            width = base.clf_width
            while width > 64 and width * n_guides > MAX_CLASSIFIER_WEIGHTS:
                width //= 2
            changed.update(guide_mag_limit=float(camera.mag_limit), guides_per_cell=GUIDES_PER_CELL,
                           guide_cell_grid=grid, guide_order="brightness", guide_in_frame=True,
                           clf_width=width, n_pair_trials=1, n_guide_triples=NARROW_GUIDE_TRIPLES)
        elif field > 1.0:
            changed["sim_by_family"] = True
        config = dataclasses.replace(base, **{**changed, **overrides})
        if narrow and config.training.sim_capacity < DEEP_SIM_CAPACITY:
            config = dataclasses.replace(config, training=dataclasses.replace(
                config.training, sim_capacity=DEEP_SIM_CAPACITY))
        return config

    @classmethod
    def paper(cls, **overrides) -> Config:
        """The paper's algorithm alone: paper network, input and Table 3 training, none of our extensions
        (no pair-angle test, one confident pair, S1–S3 only, no pool of pairs, no coverage test, no
        camera fit or focal-length retries).
        """
        return cls(**{"pair_tol_px": None, "n_pair_trials": 1, "n_guide_triples": 1,
                      "n_pool_pairs": 0, "min_coverage": 0.0, "finishing": Finishing.off(),
                      "name_isolation": 1.0,
                      **overrides})

    def database_fields(self) -> dict:
        """The settings that shape the trained network (identification-time ones left out)."""
        keep = ("rho_deg", "m", "e_deg", "guide_mag_limit", "guide_min_sep_deg", "gen_widths", "clf_width")
        out = {k: getattr(self, k) for k in keep}
        # the extensions enter only when on, so that the published settings keep their cache keys
        for name in ("guides_per_cell", "guide_cell_grid", "guide_in_frame", "sim_by_family"):
            if getattr(self, name):
                out[name] = getattr(self, name)
        out["training"] = dataclasses.asdict(self.training)
        if self.train_detection is not None:  # the camera is in the checkpoint's key already
            model = (self.train_detection if isinstance(self.train_detection, str)
                     else dataclasses.asdict(self.train_detection))
            out["train_detection"] = {"model": model, "kept": "the paper's count"}  # data.py's rule
        return out

    def training_detection(self, camera) -> DetectionModel | None:
        """The detection model the training scenes are drawn from on ``camera`` (``None``: the paper's)."""
        if self.train_detection == "sensor":
            return DetectionModel.from_sensor(camera)
        return self.train_detection

    def fingerprint(self) -> str:
        """Short hash of :meth:`database_fields` (recorded in checkpoints, to refuse a mismatch)."""
        return hashlib.sha256(json.dumps(self.database_fields(), sort_keys=True).encode()).hexdigest()[:16]
