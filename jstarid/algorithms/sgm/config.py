"""SGM settings (You et al. 2022, Table 1) plus the static sizes of the JAX implementation."""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax

__all__ = ["Config", "Tuning"]


class Tuning(NamedTuple):
    """SGM's sweepable tolerances (:func:`~jstarid.algorithms.sgm.tuning.grid_identifications`
    takes a grid of each as an array axis; scalars here by default).

    Attributes:
        c: edge-similarity adjustor of eq. 2 (1/deg).
        max_error_deg: ε_δ, matching-error threshold of Algorithm 1 (deg).
    """

    c: jax.Array | float
    max_error_deg: jax.Array | float


@dataclasses.dataclass(frozen=True)
class Config:
    """Frozen, hashable SGM configuration. Angles in degrees, as in the paper (conventions §7).

    Attributes:
        radius_deg: r, radius of the neighbor circle (deg).
        dw0_deg: Δw₀, initial half-width of the rough-search window on w (deg).
        dw_step_deg: h_Δw, growth of Δw per step of Algorithm 1 (deg).
        dw_max_deg: Δw_max, largest Δw searched (deg).
        c: edge-similarity adjustor of eq. 2 (1/deg).
        max_error_deg: ε_δ, matching-error threshold of Algorithm 1 (deg, eq. 5).
        neighbor_capacity: static vertex capacity of a database neighbor graph (main star
            included); ``None`` chooses it from the data (largest graph, rounded up to
            ``size_bucket``). The image graph uses the same capacity; a scene with more detections
            inside its neighbor circle fails (flagged, never truncated silently).
        chunk_size: candidate ranks per scene in the first step of the batched search (each later
            step takes twice as many, up to 512).
        power_iterations: number of power-iteration steps for the principal eigenvector (the
            largest number when ``power_tol`` > 0). In a one-off measurement, 30 gave the same
            correspondence as 400 steps on all 12,732 (image, candidate) pairs of 40 σ = 2 px
            scenes within ±1° of w_I (so did 20; 60 was the previous default).
        power_tol: stop the power iteration of a pair once no entry of its unit vector changes by
            more than this in a step (0: always ``power_iterations`` steps). Pairs are matched one
            after the other, so each stops on its own: 1e-4 made identification ≈ 1.9× faster and
            gave the same ids, J* and δ as 0 on 448 scenes at σ = 0.5–3 px (one-off measurement).
        prune: not in the paper, and it does not change the outcome: skip the spectral matching
            of candidates whose matching error provably exceeds ε_δ, or — once a match with
            δ* ≤ ε_δ is known — provably exceeds δ* (:mod:`.bound`; such a candidate can never be
            returned by Algorithm 1: :func:`.search.advance_search`). ``False`` matches every
            candidate (diagnostics such as ``error`` of failed scenes then cover every candidate).
        prune_max_skip: candidates whose vertex count differs from the image graph's by more than
            this are not bounded (always matched); the bound's cost grows with it.
        min_stars: fewest vertices (main star included) an image neighbor graph needs; fewer → fail.
            Not in the paper (which never meets tiny graphs): a 1- or 2-vertex graph matches almost
            anything.
        min_matched: fewest matched vertex pairs for a candidate to count; a candidate with a
            smaller graph gets an infinite error (eq. 5 divides by min(n_I, n_J), which would let a
            1-vertex database graph match any image with error 0).
        memory_budget_mb: bound on the affinity matrices held at once by one matching call (MiB).
        size_bucket: graph sizes are padded up to a multiple of this, to bound recompilation. A
            pair's matching costs ∝ (p·q)² in the padded sizes, so a smaller bucket runs faster but
            compiles more kernels (``bench_sgm.py --batch 1000 --set size_bucket=…``, session 22,
            each run beside a default one: 4 gave +3–11 % scenes/s at σ = 1 px and +12–18 % at 3 px
            for a first call 1.5× as long; 16 gave −26 % / −34 %). 8 suits interactive batches; 4
            pays for itself over runs of several thousand noisy scenes in one process.
        vertex_check_deg: not in the paper (``None`` = off, the paper's behaviour). When set, after
            the best match every matched image vertex whose median edge residual
            ``|A_I(i,k) − A_J(π(i),π(k))|`` over the other matched vertices exceeds this (deg) is left
            unnamed (−1), and the scene fails if fewer than ``min_matched`` vertices stay named.
            Greedy binarization always pairs min(n_I, n_J) vertices, so a star that crossed the
            circle boundary (or a false star) is otherwise paired with a leftover database vertex
            and named wrongly.
        leftover_tol_deg: not in the paper; 0.3° by default (``None`` = off, the paper's
            behaviour). Detections inside the image neighbor circle left unnamed by the match
            (typically a star that crossed the circle boundary under position noise, so it is not in
            G_J) are named by the attitude solved from the matched stars: the nearest catalog star
            within this angle (deg), if not already used in the scene; the verification step then
            checks them like every other name. Measured with ``reproduce_sgm.py --n-stars 100
            --sigmas 0 1.5 3 --experiments position lost`` (same scenes, verification on): accuracy
            79.0 → 90.9 % (position, 1.5 px), 72.7 → 74.2 % (3 px), 84.7 → 88.4 % (lost, 1.5 px),
            62.4 → 72.5 % (lost, 3 px); one mis-identified scene of 600 in each run.
        verify: not in the paper; on by default (``False`` = the paper's behaviour). After the match
            (and the optional steps above) every named star is checked against the attitude fitted
            from the named stars (:mod:`.verify`): stars whose residual exceeds
            ``verify_k`` × the robust residual RMS (clipped to [``verify_floor_deg``,
            ``verify_cap_deg``]) are unnamed, and so is a star with a rival catalog star within
            ``max(3·tol, verify_ambiguity_deg)`` unless ``d_alt² − d_own² ≥ (verify_ambiguity_k·s)²``.
            The scene fails when the main star is unnamed, fewer than ``min_matched`` stars or fewer
            than half of the named stars remain. Trades mis-identifications for failures.
        verify_k: tolerance in units of the robust residual RMS (3.5: a true star exceeds it with
            probability exp(−3.5²) ≈ 5·10⁻⁶).
        verify_floor_deg: smallest tolerance (deg); 0.02° ≈ 1 px of the sgm2022 camera.
        verify_cap_deg: largest tolerance (deg); 0.3° ≈ 3.5 × the residual RMS at σ = 3 px (the
            paper's largest noise), so a wrong attitude cannot widen the tolerance further.
        verify_ambiguity_k: margin of the ambiguity guard in robust-RMS units: the kept name is at
            least exp(``verify_ambiguity_k²``) times likelier than the rival under isotropic Gaussian
            noise (3.0: ≈ 8,100×). A clean swap fails for any value ≥ 0 (its own residual ≈ the pair's
            separation, the rival's ≈ the noise); the margin also catches swaps the noise blurs, at
            the cost of unnaming true stars of nearly indistinguishable pairs (incomplete scenes).
            Measured by replaying the verification on the raw matches of 1,400 scenes (7 noisy
            levels of the session-4 200-star Table 2 run, σ 1–3 px, with the joint test and the
            frame coverage): 2.0 left 3 scenes mis-identified (a detection of a close pair that
            drifted 2.7–3.1 σ towards the other star, likelihood ratio ≈ 30–300) and 1,133 correct;
            2.5 left none and 1,079 correct (the other 54 incomplete: one star of a close pair
            unnamed); 3.0 none and 1,011 correct. A mis-identification is worse than an unnamed
            star, so 2.5 until session 11. Then 3.0 (e^9; worst-case error of a near-tie decision
            with the true σ Φ(−√(2·9)) = 1.1·10⁻⁵, against 2·10⁻⁴ at 2.5): with the partner rule and
            the high-side s most close-pair names are decided by other tests, and the full-size lost
            run's one mis-identification (σ = 2.5 px, main star row 1001: a detection 3.4 σ from its
            own star, 1.3 px from the absent lost star, 5.6 nats with the true σ) passed the single
            test's 6.25-nat margin. ``diagnose_sgm.py --experiment lost --sigma 2.5 --batches 3``:
            194 correct + 1 mis-identified → 193 correct, 0; the README's sampled Table 2 (4,200
            scenes) moved by at most one scene per level (3 at lost 3 px), MA 88.85 / 88.02 / 88.75
            → 88.91 / 87.94 / 88.87 %, none mis-identified either way.
        verify_ambiguity_deg: smallest window of the ambiguity guard (deg).
        verify_partner_joint: when a rival star of a named detection has a detection of its own
            (within the tolerance, nearer to the rival than to any other catalog star, named after
            the rival or unnamed), passing the joint exchange test alone with the margin
            ``verify_partner_k`` also keeps the name (:mod:`.verify` step 3); ``False`` = the
            single and joint tests must both pass. Session 7, ``reproduce_sgm.py --n-stars 200``
            (4,200 scenes, the README's Table 2): MA 88.68 / 89.21 / 88.13 → 91.14 / 90.99 /
            90.28 %, ALN 73.22 / 74.73 / 68.16 → 78.92 / 78.14 / 73.48 % (position / lost / fake),
            no mis-identified scene either way. The first version of the rule (session 6: margin
            ``verify_ambiguity_k``, no nearest-star condition) reached ALN 86.10 / 87.57 / 80.77 %
            but mis-identified 2 of those scenes.
        verify_partner_k: margin of the partner rule's exchange test in robust-RMS units (3.5:
            the names are ≥ e^12.25 times likelier than the exchange). It replaces two tests of
            margin ``verify_ambiguity_k`` by one, so it asks for more; with 2.5 a pair 0.067°
            apart at σ = 1 px whose detections had drifted past each other passed it by 6.28 nats
            for the wrong names. The partner path only adds names; the rule also counts a kept
            other detection at its own name's cost in the joint test (module :mod:`.verify`). 3.0 on the
            README's 4,200 Table 2 scenes: ALN 83.33 / 83.15 / 78.02 % (3.5: 78.92 / 78.14 /
            73.48 %), no mis-identification either. 3.5 because, with the true σ, the wrong names
            of a pair d RMS units apart beat the right ones by 2d² + 2d·Z nats (Z standard normal),
            so they pass a margin m with probability at most Φ(−√(2m)), reached at d = √(m/2): 1.1·10⁻⁵
            at m = 9, 3.7·10⁻⁷ at 12.25 (a Monte-Carlo check agreed), and a full-size run makes tens
            of thousands of such decisions.
        verify_rms_z: the ambiguity margins' s (:func:`.verify._upper_rms`) is the kept residuals'
            RMS over the lower Φ(−z) quantile of their χ² (2n − 3 degrees of freedom), so it comes
            out below the true RMS with probability Φ(−z): 16 % at 1.0. 2.0 (2.3 %) with the margin
            2.5 also removes the mis-identification above, but on the sampled Table 2 it cost 3 MA
            points (85.71 / 85.61 / 86.14 %) and 4.5–6.6 ALN points: a larger
            ``verify_ambiguity_k`` buys the same safety far more cheaply.
        verify_magnitude_sigma: not used by default (``None``; SGM is magnitude-free). When set, the
            ambiguity tests add each hypothesis' magnitude cost ``(m_obs − V)² / (2σ²)`` with this
            σ (mag). On the session-6 replay with σ = 0.3 and the first partner rule (the scenes had no
            magnitude noise, so this is an upper bound): correct scenes at σ = 3 px 170 → 178
            (position), 163 → 168 (lost), 164 → 174 (fake), none mis-identified.
        verify_rename: not in the paper; on by default (needs ``verify`` and ``leftover_tol_deg``).
            After the verification, the detections of the image graph it left unnamed are named again
            from the verified attitude (the ``leftover_tol_deg`` rule) and the scene is verified again,
            so every new name passes the same tests; a scene the second verification rejects keeps
            the first one's result. Why: the match can pair a detection with the wrong database
            vertex (seen noise-free in the full-size run: a 39-vertex graph whose δ = 0.34° passed
            ε_δ with one detection named after a star 2.2° from its own); the verification unnames
            it, but the leftover naming ran before, when it was still named, so the scene stayed
            incomplete.
        verify_retries: not in the paper; on by default (needs ``verify``). When the verification
            rejects a scene's match, that candidate J* is struck out, as if its δ exceeded ε_δ, and
            Algorithm 1 goes on where it stopped — the next best candidate of the same Δw prefix
            with δ ≤ ε_δ, else the next levels — and the new answer is verified in turn; at most
            this many times per scene (0 = the scene fails at the first rejection). A scene
            failed only because a close rival star contests its main star's name (the match passed
            every other test) is not searched on: another graph cannot settle that. The
            verification thus becomes part of Algorithm 1's acceptance test (δ ≤ ε_δ and
            verified), and nothing is matched twice (:class:`.search.SearchState`). Why: ε_δ = 0.4°
            admits wrong graphs at small Δw before the right one, whose w_J a lost star or noise
            moved further from w_I, is reached. Noise-free with one lost star, ``python
            experiments/diagnose_sgm.py --experiment lost --sigma 0 --n-stars 800``: 3 failed
            scenes with ``verify_retries=0``, 1 with 3. Full size (``reproduce_sgm.py``), one lost
            star: failures 0.53 → 0.16 % at σ = 0, 1.12 → 0.79 % at 0.5 px.
        verify_min_coverage: the frame-coverage test of the verification (0 = off): at least this
            fraction of the catalog stars that the verified attitude projects inside the frame (inset
            by the tolerance) must have a detection within the tolerance. 0.4 as in RpNet
            (``rpnet.Config.min_coverage``). Measured on the 8 mis-identified scenes of the session-4
            200-star Table 2 run: the 2 wrong small-graph matches covered 11–12 % of the frame, the
            6 close-pair swaps and the correct scenes 97–100 %.
    """

    radius_deg: float = 6.0
    dw0_deg: float = 0.1
    dw_step_deg: float = 0.1
    dw_max_deg: float = 6.0
    c: float = 1.74
    max_error_deg: float = 0.4
    neighbor_capacity: int | None = None
    chunk_size: int = 16
    power_iterations: int = 30
    power_tol: float = 1e-4
    prune: bool = True
    prune_max_skip: int = 8
    min_stars: int = 3
    min_matched: int = 3
    memory_budget_mb: int = 1024
    size_bucket: int = 8
    vertex_check_deg: float | None = None
    leftover_tol_deg: float | None = 0.3
    verify: bool = True
    verify_k: float = 3.5
    verify_floor_deg: float = 0.02
    verify_cap_deg: float = 0.3
    verify_ambiguity_k: float = 3.0
    verify_ambiguity_deg: float = 0.2
    verify_partner_joint: bool = True
    verify_partner_k: float = 3.5
    verify_magnitude_sigma: float | None = None
    verify_rms_z: float = 1.0
    verify_rename: bool = True
    verify_retries: int = 3
    verify_min_coverage: float = 0.4

    def __post_init__(self):
        if not 0 < self.radius_deg < 90:
            raise ValueError(f"radius_deg must be in (0, 90), got {self.radius_deg}")
        if self.dw0_deg < 0 or self.dw_step_deg <= 0 or self.dw_max_deg < self.dw0_deg:
            raise ValueError("need 0 ≤ dw0_deg ≤ dw_max_deg and dw_step_deg > 0")
        if self.c <= 0 or self.max_error_deg < 0:
            raise ValueError("c must be > 0 and max_error_deg ≥ 0")
        if self.neighbor_capacity is not None and self.neighbor_capacity < 2:
            raise ValueError("neighbor_capacity must be ≥ 2")
        if self.power_tol < 0 or self.prune_max_skip < 0:
            raise ValueError("power_tol and prune_max_skip must be ≥ 0")
        if min(self.chunk_size, self.power_iterations, self.size_bucket, self.memory_budget_mb) < 1:
            raise ValueError("chunk_size, power_iterations, size_bucket, memory_budget_mb must be ≥ 1")
        if self.min_stars < 1 or self.min_matched < 1:
            raise ValueError("min_stars and min_matched must be ≥ 1")
        if self.verify_retries < 0:
            raise ValueError(f"verify_retries must be ≥ 0, got {self.verify_retries}")
        if (self.verify_k <= 0 or not 0 < self.verify_floor_deg <= self.verify_cap_deg
                or self.verify_ambiguity_k < 0 or self.verify_ambiguity_deg < 0
                or self.verify_partner_k < 0 or self.verify_rms_z < 0
                or not 0 <= self.verify_min_coverage <= 1
                or (self.verify_magnitude_sigma is not None and self.verify_magnitude_sigma <= 0)):
            raise ValueError("need verify_k > 0, 0 < verify_floor_deg ≤ verify_cap_deg, "
                             "non-negative ambiguity settings, verify_min_coverage in [0, 1] "
                             "and verify_magnitude_sigma None or > 0")

    @property
    def n_levels(self) -> int:
        """Number of Δw values Algorithm 1 visits: Δw₀ + l·h for l = 0 … n_levels − 1 (≤ Δw_max)."""
        return int(math.floor((self.dw_max_deg - self.dw0_deg) / self.dw_step_deg + 1e-9)) + 1

    @property
    def dw_last_deg(self) -> float:
        """The largest Δw Algorithm 1 searches (deg)."""
        return self.dw0_deg + (self.n_levels - 1) * self.dw_step_deg

    @classmethod
    def paper(cls, **overrides) -> Config:
        """The paper's algorithm alone (Table 1 parameters, none of our extensions that change
        the outcome): no post-match verification (``verify``) and no leftover naming
        (``leftover_tol_deg``). The branch and bound (``prune``) stays: it changes only the work.
        What a plain re-implementation of the paper (``experiments/sgm_numpy_reference.py``)
        returns, id for id."""
        return cls(**{"verify": False, "leftover_tol_deg": None, **overrides})

    def tuning(self) -> Tuning:
        """This config's sweepable tolerances as a :class:`Tuning` of scalars."""
        return Tuning(c=float(self.c), max_error_deg=float(self.max_error_deg))

    def database_fields(self) -> dict:
        """The fields that shape the database (its cache key, with the catalog fingerprint)."""
        return {"radius_deg": float(self.radius_deg), "neighbor_capacity": self.neighbor_capacity,
                "size_bucket": int(self.size_bucket)}
