"""The finishing stage every algorithm ends with: the hypothesis search, the focal-length ladder and
the camera check.

An algorithm names stars under the nominal camera from the pattern of its brightest detections.
The steps after it make the answer hold on a cluttered frame and on a camera whose focal length is
not quite the datasheet's; they are the same for every algorithm, so they are written once here
and configured by one nested config, :class:`Finishing` (``Config.finishing`` of MLV, RpNet and SGM):

0. **Hypothesis search** (``hypotheses``): the scenes the algorithm left unsolved are searched over
   every triangle of their brightest ``hypotheses`` detections, each verified against the frame
   (:mod:`jstarid.hypotheses`), and a crowded scene still unsolved again over its brightest
   ``crowded_hypotheses``; a claim must pass the false-match test. Where false detections as
   bright as the stars outnumber them, the algorithm's pattern is mostly false; five stars anywhere
   among the detections are enough here. A sparse field's deep catalog is searched over its
   brightest star per sky cell (:func:`jstarid.triangle_index.stars_that_fit`); skipped where a
   denser field's catalog has too many triangles per frame
   (:func:`jstarid.triangle_index.index_problem`; the papers' wide cameras): such fields hold dozens
   of stars.
1. **Focal-length ladder** (``focal_search``): the scenes the algorithm left unsolved are tried again
   as if the focal length were each factor × the camera's, in order
   (:func:`jstarid.camera_fit.search_focal`). Features that are angles (triangle singular values,
   MST weights, pair distances, network patterns) move past their tolerances when the focal length
   is off by 1–2 %; a ladder of 1 % steps brings those scenes back.
2. **Camera check** (``fit_focal``): every solved scene's names are checked against a joint fit of
   the attitude and the focal length (:func:`jstarid.camera_fit.check_identification`); names the
   fit cannot explain are taken back, a scene whose fit fails is unclaimed, and the fitted
   ``focal_scale`` (and ``distortion_k1``) is reported.
2b. **Names a neighbour explains as well** (``rival_odds``): after the check, a name stands only
   where its star explains the detection, in position and brightness, ``rival_odds`` times better
   than any other catalog star within the check's radius (:mod:`jstarid.rival_stars`): the
   detection of one star of a close pair lands within the radius of the other.
3. **The false-match probability decides** (``max_false_match``): every claim gets the probability
   that a wrong attitude confirms as many detections (:mod:`jstarid.false_match`), of its own names
   or, where those leave it doubtful, of the whole frame named from its attitude; a claim stands at
   P ≤ ``max_false_match``, and P is ``Identification.false_match`` (:func:`confirmed_by_the_frame`).
   Three or four points fit some catalog pattern within the tolerances wherever the catalog is dense
   enough, and a handful of false detections can pass an algorithm's own verification; a right
   attitude predicts the frame's other stars, a wrong one confirms only what chance puts near a
   catalog star.

4. **Claims taken back, searched** (``hypotheses``): the scenes the algorithm (or the ladder) claimed
   and a later step took back are searched as step 0 searches the unsolved ones
   (:func:`search_lost`); among clutter such a claim was mostly false detections.

An algorithm calls :func:`finish` with a ``rerun`` function (its own identification on moved
centroids) and its catalog's rows; its own steps after the stage (SGM names the scenes the ladder
solved again under the fitted focal length) read :attr:`Finished.laddered`; one whose own steps after
the stage change the names (SGM) passes ``confirm=False`` and calls :func:`confirmed_by_the_frame`
and :func:`search_lost` after them.
``Finishing.off()`` is the papers' algorithms: none of the steps.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import warnings
from collections.abc import Callable, Mapping
from typing import NamedTuple

import jax
import numpy as np

from jstarid.camera_fit import MAX_TOL_PX, check_identification, search_focal
from jstarid.completion import name_from_attitude
from jstarid.config_tree import nested
from jstarid.false_match import SMALLEST_P, false_match_probability, with_names_attitude
from jstarid.hypotheses import SearchOutcome, solve_unsolved
from jstarid.rival_stars import without_rivalled_names
from jstarid.runtime import padded_indices
from jstarid.runtime.padding import MIN_CALL_SIZE
from jstarid.scene import Identification, Scene
from jstarid.triangle_index import TooManyTriangles

__all__ = ["Finished", "Finishing", "StarTable", "confirmed_by_the_frame", "finish", "search_lost"]

CLAIM_CHUNKS = (16, 256)  # claims per call of their names' false-match probability (≈ 0.02 ms a claim)
FRAME_CHUNKS = (MIN_CALL_SIZE, 64)  # claims per call of the frame's naming, whose cost follows the
# padded claims (experiments/RESULTS.md, Throughput): a few run in the smallest call every kernel
# has, many in the largest (a call of 4 saved a few padded namings but compiled them once more)
LADDER_STEP = 0.01  # the ladder's step: MLV's features tolerate about 1 % of focal length


@dataclasses.dataclass(frozen=True)
class Finishing:
    """Settings of the finishing stage (frozen, hashable; a field of each algorithm's ``Config``).

    Attributes:
        focal_search: focal-length factors under which the scenes still unsolved are tried again, in
            order; ``()`` turns the ladder off. Each must lie in (0.5, 2).
        fit_focal: check every solved scene's names against a joint fit of the attitude and the
            focal length, and report ``focal_scale``.
        max_focal_error: the largest relative focal-length correction a solved scene may need
            (``|s − 1|``, in [0, 0.5)); beyond it the scene fails.
        studentized: the check's radius allows for the scatter of its own σ̂ over few names
            (:func:`jstarid.camera_fit.studentized_k`); SGM's default, off for MLV and RpNet.
        hypotheses: the brightest detections whose every triangle the hypothesis search tries on a
            scene still unsolved (C(n, 3) triangles; ≈ 0.1 s a scene at 48 on 2 cores); 0 turns the
            search off.
        crowded_hypotheses: a scene with more valid detections than ``hypotheses`` that the search
            leaves unsolved is searched again over its ``crowded_hypotheses`` brightest (C(96, 3) =
            142,880 triangles: the clutter sweep at 80 false detections runs at 1–2 frames/s on 2
            cores, a 6° camera's deep catalog slower; only such scenes pay it): where false
            detections as bright as the stars number 80, the 48 brightest hold five of a frame's
            stars about one time in twenty (docs/design/hypotheses.md). 0 (or ≤ ``hypotheses``): no
            second pass.
        hypothesis_eps_px: the search's side and confirmation tolerance (px at the focal length).
        hypothesis_false_match: the largest false-match probability a claim of the search may have.
            Stricter than a single pattern's 1e-3: the search picks the best of thousands of
            hypotheses, and a probe found one wrong six-name claim at P = 1.5e-4
            (docs/design/hypotheses.md).
        rival_odds: after the check, a name stands only where its star explains the detection at
            least this many times better than any other catalog star within the check's radius
            (step 2b, :mod:`jstarid.rival_stars`); 0 turns the step off, else ≥ 1.
        false_per_frame: step 2b's other rival is no star at all: a false detection (hot pixel,
            cosmic ray, satellite) where a catalog star too faint or too crowded out to be detected
            lies. This is the number of them a frame is expected to hold, spread over the frame
            (the prior of that rival; :mod:`jstarid.rival_stars`); 0: not asked.
        max_false_match: the largest false-match probability
            (:func:`jstarid.false_match.false_match_probability`) at which a claim stands (step 3):
            loose enough for a right claim in a frame of only three or four stars, where P cannot
            get small, strict enough for a coincidence, which the frame leaves near 1
            (docs/design/false_match.md). SGM, whose circle of few names meets random points more
            often, keeps 1e-3. 1 turns the step off (a sweep still reports the names' P).
    """

    focal_search: tuple[float, ...] = (0.99, 1.01, 0.98, 1.02)
    fit_focal: bool = True
    max_focal_error: float = 0.1
    studentized: bool = False
    hypotheses: int = 48
    crowded_hypotheses: int = 96
    hypothesis_eps_px: float = 3.0
    hypothesis_false_match: float = 1e-5
    rival_odds: float = 20.0
    false_per_frame: float = 1.0
    max_false_match: float = 1e-2

    def __post_init__(self):
        object.__setattr__(self, "focal_search", tuple(float(f) for f in self.focal_search))
        if any(not (math.isfinite(f) and 0.5 < f < 2.0) for f in self.focal_search):
            raise ValueError(f"focal_search factors must lie in (0.5, 2), got {self.focal_search}")
        if not 0.0 <= self.max_focal_error < 0.5:
            raise ValueError(f"max_focal_error must be in [0, 0.5), got {self.max_focal_error}")
        if not (isinstance(self.hypotheses, int) and (self.hypotheses == 0 or 4 <= self.hypotheses <= 64)):
            raise ValueError(f"hypotheses must be 0 (off) or an integer in [4, 64], got {self.hypotheses}")
        if not (isinstance(self.crowded_hypotheses, int) and 0 <= self.crowded_hypotheses <= 128):
            raise ValueError(f"crowded_hypotheses must be an integer in [0, 128] (0: no second pass), got "
                             f"{self.crowded_hypotheses}")
        if not (math.isfinite(self.hypothesis_eps_px) and 0 < self.hypothesis_eps_px <= 10):
            raise ValueError(f"hypothesis_eps_px must be in (0, 10] px, got {self.hypothesis_eps_px}")
        if not 0 < self.hypothesis_false_match <= 0.1:
            raise ValueError(f"hypothesis_false_match must be in (0, 0.1], got {self.hypothesis_false_match}")
        if not (math.isfinite(self.rival_odds) and (self.rival_odds == 0 or self.rival_odds >= 1)):
            raise ValueError(f"rival_odds must be 0 (off) or a number ≥ 1, got {self.rival_odds}")
        if not (math.isfinite(self.false_per_frame) and self.false_per_frame >= 0):
            raise ValueError(f"false_per_frame must be a number ≥ 0, got {self.false_per_frame}")
        if not 0 < self.max_false_match <= 1:
            raise ValueError(f"max_false_match must be in (0, 1], got {self.max_false_match}")

    @classmethod
    def coerce(cls, value: Finishing | Mapping) -> Finishing:
        """``value`` itself, or a :class:`Finishing` from a mapping of its fields (a config read from
        JSON or ``--set``; :func:`jstarid.config_tree.nested`).

        Raises:
            TypeError: anything else, or a mapping with a field :class:`Finishing` lacks.
        """
        return nested(cls, value, "finishing")

    def reaching(self, max_error: float, step: float = LADDER_STEP) -> Finishing:
        """These settings with the ladder extended in steps of ``step`` out to ``1 ± max_error`` (after its
        own factors) and the check allowing that correction: a camera whose field of view is known
        to ±10 % (``jstarid solve --fov-max-error``). Returned as they are when the ladder is off
        or already reaches that far."""
        if not self.focal_search:
            return self
        reach = max(abs(f - 1.0) for f in self.focal_search)
        if max_error <= reach:
            return self
        n = int(math.floor(max_error / step + 1e-9))
        wider = tuple(round(1.0 + sign * k * step, 6) for k in range(1, n + 1) for sign in (-1, 1))
        return dataclasses.replace(
            self, focal_search=self.focal_search + tuple(f for f in wider if abs(f - 1.0) > reach + 1e-9),
            max_focal_error=max(self.max_focal_error, max_error))

    @classmethod
    def off(cls, **overrides) -> Finishing:
        """No hypothesis search, ladder, check or false-match test: the papers' algorithms."""
        return cls(**{"focal_search": (), "fit_focal": False, "hypotheses": 0, "rival_odds": 0.0,
                      "max_false_match": 1.0, **overrides})


class Finished(NamedTuple):
    """What :func:`finish` returns.

    Attributes:
        result: the :class:`~jstarid.scene.Identification` after the ladder and the check
            (``focal_scale`` and ``distortion_k1`` set where the check ran).
        laddered: (B,) bool NumPy, the scenes the first pass left unsolved and the ladder solved
            (before the check, which may unclaim some of them).
        searched: (B,) bool NumPy, the scenes the hypothesis search solved (before the check).
        search_overflow: (B,) bool NumPy, scenes the search could not finish: more hypotheses than
            it verifies (:class:`jstarid.hypotheses.SearchOutcome`).
        claimed: (B,) bool NumPy, the scenes the algorithm or the ladder claimed (before the check):
            where a later step takes such a claim back, :func:`search_lost` searches the scene.
    """

    result: Identification
    laddered: np.ndarray
    searched: np.ndarray
    search_overflow: np.ndarray
    claimed: np.ndarray


def finish(result: Identification, scenes: Scene, config: Finishing, *,
           rerun: Callable[[Scene, np.ndarray], Identification], camera, star_vectors, star_mags=None,
           max_tol_px: float = MAX_TOL_PX, confirm: bool = True) -> Finished:
    """Run the finishing stage on an algorithm's first answer.

    Args:
        result: the algorithm's :class:`~jstarid.scene.Identification` of ``scenes`` (ids (B, N)).
        scenes: (B, N) :class:`~jstarid.scene.Scene` from ``camera``.
        config: the :class:`Finishing` settings.
        rerun: ``rerun(moved, rows) -> Identification``: the algorithm on centroids moved as a
            rescaled focal length would see them; ``rows`` (R,) their indices in ``scenes`` (for
            per-scene settings such as a grid's tolerances).
        camera: the nominal :class:`~jstarid.camera.Camera`.
        star_vectors: (M, 3) ICRS unit vectors of the catalog rows the ids name.
        star_mags: (M,) their V magnitudes (mag); given, the check first takes back names far
            brighter than their star, and step 2b weighs brightness. Step 3 needs them where it
            decides (new names of the frame must agree in brightness).
        max_tol_px: the check's largest radius (px); an algorithm whose own verification accepts
            larger residuals passes its cap (SGM); also step 3's naming radius.
        confirm: run steps 3 and 4 here (False: the caller runs :func:`confirmed_by_the_frame` and
            :func:`search_lost` itself, after steps of its own).

    Returns:
        :class:`Finished`.
    """
    b = scenes.batch_size
    if config.max_false_match < 1 and confirm and star_mags is None:
        raise ValueError("the false-match test (Finishing.max_false_match < 1) needs star_mags")
    laddered, searched, search_overflow = (np.zeros(b, bool) for _ in range(3))
    # the rows as steps 2b and 3 read them (hashed once: the key of their sky indexes)
    decides = config.rival_odds or config.max_false_match < 1
    stars = _table(star_vectors, star_mags) if b and decides else None
    if b and config.hypotheses:
        result, searched, search_overflow = _search(result, scenes, config, camera, star_vectors, star_mags)
        if search_overflow.any():
            warnings.warn(f"{int(search_overflow.sum())} scene(s): the hypothesis search found more "
                          "hypotheses than it verifies and left the rest (Finished.search_overflow; "
                          "fewer detections, Finishing.hypotheses, search less)", stacklevel=3)
    if b and config.focal_search:
        unsolved = ~np.asarray(result.ok)
        result = search_focal(rerun, result, scenes, camera, config.focal_search)
        laddered = unsolved & np.asarray(result.ok)
    claimed = np.asarray(result.ok) & ~searched
    if b and config.fit_focal:
        result = check_identification(star_vectors, camera, scenes, result,
                                      max_scale_error=config.max_focal_error, max_tol_px=max_tol_px,
                                      star_mags=star_mags, studentized=config.studentized)
        if config.rival_odds:
            result = without_rivalled_names(result, scenes, stars=stars, camera=camera,
                                            false_per_frame=config.false_per_frame,
                                            odds=config.rival_odds, max_tol_px=max_tol_px,
                                            max_scale_error=config.max_focal_error)
    if b and config.max_false_match < 1 and confirm:
        result = confirmed_by_the_frame(result, scenes, config, stars=stars, camera=camera, tol_px=max_tol_px)
    if b and confirm:
        result, again = search_lost(result, scenes, config, claimed, camera=camera, star_vectors=star_vectors,
                                    star_mags=star_mags, max_tol_px=max_tol_px, stars=stars)
        searched = searched | again
    return Finished(result=result, laddered=laddered, searched=searched, search_overflow=search_overflow,
                    claimed=claimed)


def search_lost(result: Identification, scenes: Scene, config: Finishing, claimed, *, camera, star_vectors,
                star_mags=None, max_tol_px: float = MAX_TOL_PX,
                stars=None) -> tuple[Identification, np.ndarray]:
    """Step 4: the scenes whose claim a later step took back, searched as step 0 searches the unsolved.

    An algorithm's claim that the camera check, the rival test or the confirmation takes back was
    never searched (step 0 searches what the algorithm left unsolved): among clutter, its pattern
    was mostly false detections — the same frames step 0 solves when the algorithm claims nothing.
    The search's claims then pass the check, the rival test and the confirmation like any.
    :func:`finish` runs this step last; an algorithm with steps of its own after the stage (SGM)
    calls it after them, with :attr:`Finished.claimed`.

    Args:
        result: (B, N) :class:`~jstarid.scene.Identification` after the stage's other steps.
        scenes: (B, N) :class:`~jstarid.scene.Scene` from ``camera``.
        config: the :class:`Finishing` settings (``hypotheses`` 0: nothing is searched).
        claimed: (B,) bool, the scenes claimed before the check (:attr:`Finished.claimed`).
        camera, star_vectors, star_mags, max_tol_px: as in :func:`finish`.
        stars: the rows as a :class:`StarTable` (default: built from ``star_vectors`` and
            ``star_mags``).

    Returns:
        ``(result, solved)``: ``result`` with the scenes the search solved filled in, and (B,) bool
        NumPy, those scenes.
    """
    b = scenes.batch_size
    solved = np.zeros(b, bool)
    rows = np.flatnonzero(np.asarray(claimed, bool) & ~np.asarray(result.ok))
    if not (config.hypotheses and rows.size):
        return result, solved
    take = padded_indices(rows, floor=MIN_CALL_SIZE)  # a few sizes: each compiles the search
    part, moved = result[take].failed(np.arange(take.size)), scenes[take]
    # the copies that pad the call are not searched (each search costs ≈ 0.1 s a frame)
    outcome = _search(part, moved, config, camera, star_vectors, star_mags, rows=np.arange(rows.size))
    if not outcome.solved[:rows.size].any():
        return result, solved
    stars = stars if stars is not None else _table(star_vectors, star_mags)
    part = outcome.result
    if config.fit_focal:
        part = check_identification(star_vectors, camera, moved, part,
                                    max_scale_error=config.max_focal_error, max_tol_px=max_tol_px,
                                    star_mags=star_mags, studentized=config.studentized)
        if config.rival_odds:
            part = without_rivalled_names(part, moved, stars=stars, camera=camera, odds=config.rival_odds,
                                          false_per_frame=config.false_per_frame,
                                          max_tol_px=max_tol_px, max_scale_error=config.max_focal_error)
    part = confirmed_by_the_frame(part, moved, config, stars=stars, camera=camera, tol_px=max_tol_px)
    won = np.asarray(part.ok)[:rows.size]
    solved[rows[won]] = True
    return (result.with_rows(rows[won], part[np.flatnonzero(won)]) if won.any() else result), solved


def _search(result, scenes, config: Finishing, camera, star_vectors, star_mags, rows=None) -> SearchOutcome:
    """Step 0 (:func:`jstarid.hypotheses.solve_unsolved`), or the result as it is where the catalog has
    too many triangles per frame (a wide or deep field: many stars per frame, which the algorithms'
    own patterns find among clutter). ``rows``: the scenes to search, as in ``solve_unsolved``."""
    try:
        return solve_unsolved(result, scenes, star_vectors=star_vectors, camera=camera,
                              n_use=config.hypotheses, eps_px=config.hypothesis_eps_px, min_confirm=1,
                              max_false_match=config.hypothesis_false_match, star_mags=star_mags,
                              n_crowded=config.crowded_hypotheses, rows=rows)
    except TooManyTriangles:
        nothing = np.zeros(scenes.batch_size, bool)
        return SearchOutcome(result, nothing, nothing)


class StarTable(NamedTuple):
    """The catalog rows an algorithm names, as :func:`jstarid.completion.name_from_attitude` reads a
    :class:`~jstarid.catalog.Catalog`: unit vectors, magnitudes and a fingerprint (the key of its sky
    index)."""

    unit_vectors: np.ndarray
    mag: np.ndarray
    fingerprint: str

    @classmethod
    def of(cls, star_vectors, star_mags) -> StarTable:
        """The table of (M, 3) ICRS unit vectors and their (M,) V magnitudes (mag)."""
        vectors = np.ascontiguousarray(star_vectors, np.float32)
        mags = np.asarray(star_mags, np.float32)
        digest = hashlib.sha1(vectors.tobytes() + np.ascontiguousarray(mags).tobytes()).hexdigest()[:20]
        return cls(vectors, mags, f"stars-{digest}")


def _table(star_vectors, star_mags) -> StarTable:
    """The :class:`StarTable` of the finishing stage's catalog rows (NaN magnitudes where none are
    given: brightness then does not count)."""
    if star_mags is None:
        star_mags = np.full(np.shape(star_vectors)[0], np.nan, np.float32)
    return StarTable.of(star_vectors, star_mags)


def confirmed_by_the_frame(result: Identification, scenes: Scene, config: Finishing, *, stars, camera,
                           tol_px: float) -> Identification:
    """Step 3: every claim's false-match probability, and the claims it leaves doubtful failed.

    P of the claim's own names (:func:`jstarid.false_match.false_match_probability`: could a wrong
    attitude confirm as many of the scene's detections?) decides where it is at most
    ``config.max_false_match``. Elsewhere — three or four names, or names at a large residual — the
    frame is named from the claim's attitude (:func:`jstarid.completion.name_from_attitude`,
    within ``tol_px``) and the smaller of the two P counts: a right attitude predicts the frame's
    other stars, a wrong one confirms only what chance puts near a catalog star. (Taking the
    smaller of two bounds at most doubles the chance of a coincidence; the threshold is far from
    where that matters, docs/design/false_match.md.) The scene keeps its own names; the frame's
    only decide. Only the doubtful claims are named again (the frame's naming costs about
    4 ms a scene on 2 cores; P of the names 0.02 ms).

    Args:
        result: (B, N) :class:`~jstarid.scene.Identification` (``attitude`` may be ``None``: the
            names' Wahba attitude is used).
        scenes: (B, N) :class:`~jstarid.scene.Scene` from ``camera``.
        config: the :class:`Finishing` settings.
        stars: the catalog rows ``result.ids`` names: a :class:`~jstarid.catalog.Catalog` or a
            :class:`StarTable`.
        camera: the nominal :class:`~jstarid.camera.Camera`.
        tol_px: the naming radius (px).

    Returns:
        ``result`` with ``false_match`` (B,) set (1 where not claimed) and the claims above
        ``config.max_false_match`` failed (ids −1, ``ok`` False, NaN attitude and fits);
        ``result`` itself where ``max_false_match`` is 1 (nothing to decide:
        :func:`jstarid.false_match.of_solutions` reports the names' P).
    """
    b = scenes.batch_size
    if config.max_false_match >= 1:  # nothing to decide (Finishing.off()): a sweep reports the names' P
        return result
    p = np.ones(b)
    rows = np.flatnonzero(np.asarray(result.ok))
    if rows.size:
        p[rows] = _probability(result, scenes, rows, stars, camera)
        doubtful = rows[p[rows] > config.max_false_match]
        if doubtful.size:
            framed = _probability(result, scenes, doubtful, stars, camera, frame_px=tol_px,
                                  max_scale_error=config.max_focal_error)
            p[doubtful] = np.minimum(p[doubtful], framed)
    lost = rows[p[rows] > config.max_false_match]
    kept = np.maximum(p, SMALLEST_P).astype(np.float32)
    out = dataclasses.replace(result, false_match=jax.device_put(kept))
    return out.failed(lost) if lost.size else out


def _probability(result, scenes, rows, stars, camera, *, frame_px=None, max_scale_error=0.0) -> np.ndarray:
    """(R,) the false-match probability of the claims ``rows``: of their own names, or (``frame_px``)
    of the frame named from their attitude within it, the focal length fitted within
    ``max_scale_error`` (1 where that naming unclaims the scene).

    The claims run in calls of a few fixed sizes (:data:`CLAIM_CHUNKS`, or :data:`FRAME_CHUNKS` for
    the frame's naming: the smallest that holds them all, else the largest), not padded to the
    power of two of their count: how many claims a batch has, and how many of them are doubtful,
    changes from batch to batch, and every new size compiled about 20 programs in a fresh batch of
    a size met before."""
    sizes = CLAIM_CHUNKS if frame_px is None else FRAME_CHUNKS
    chunk = next((size for size in sizes if size >= rows.size), sizes[-1])
    p = np.ones(rows.size)
    for lo in range(0, rows.size, chunk):
        part = rows[lo:lo + chunk]
        padded = np.concatenate([part, np.full(chunk - part.size, part[0])])
        moved = scenes[padded]
        given = with_names_attitude(result[padded], moved, stars, camera)
        if frame_px is not None:
            given = name_from_attitude(stars, camera, moved, given, tol_px=frame_px,
                                       max_scale_error=max_scale_error)
        p_part = false_match_probability(moved, given, stars.unit_vectors, camera)
        p[lo:lo + part.size] = np.where(np.asarray(given.ok), p_part, 1.0)[:part.size]
    return p
