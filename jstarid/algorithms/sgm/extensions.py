"""The steps :func:`~jstarid.algorithms.sgm.identify` runs after Algorithm 1 (not in the paper).

In the order they run, each a ``Config`` field and off in ``Config.paper()``:

1. :func:`next_main_stars` (``main_stars``, ``subgraph.main_stars``): the scenes left unsolved are
   searched again with the next detection nearest the principal point as the main star.
2. :func:`finishing_stage` (``finishing``): the stage MLV and RpNet share
   (:func:`jstarid.finishing.finish`): the scenes still unsolved are tried under focal lengths
   1–2 % off (the focal-length ladder), and every solved scene's names are checked against a joint
   fit of attitude and focal length (the camera check).
3. :func:`name_at_fitted_focal` (``finishing.fit_focal`` with ``verify.rename``): the scenes the
   ladder solved are named again under the focal length the camera check fitted.
4. :func:`whole_circles_only` (``ladder.whole_circle``): of those, only the scenes whose
   whole circle is named stay solved.
5. :func:`confirmed_by_the_frame` (``finishing.max_false_match``): a scene stays solved only where
   its false-match probability — of its names, or of the frame named from its attitude — is small.
6. :func:`search_lost` (``finishing.hypotheses``): the scenes whose claim steps 2–5 took back are
   searched over their detections' triangles, as step 2 searches the unsolved ones.

Each step takes the pass it may run again as ``search(scenes, config, main_rank=0) ->
Identification``: Algorithm 1 with names and verification (``identify``'s first step).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jstarid import finishing
from jstarid.algorithms.sgm.config import Config
from jstarid.algorithms.sgm.graph import ImageGraph, searchable_graphs
from jstarid.algorithms.sgm.naming import name_leftovers, rename_and_reverify
from jstarid.camera_fit import MAX_TOL_PX, check_identification, rescale_scenes
from jstarid.finishing import finish
from jstarid.runtime import padded_indices
from jstarid.runtime.padding import MIN_CALL_SIZE
from jstarid.scene import Identification, Scene

__all__ = ["Search", "camera_check_cap_px", "confirmed_by_the_frame", "finishing_stage", "search_lost",
           "name_at_fitted_focal", "next_main_stars", "whole_circles_only", "with_members_of"]

#: One pass of Algorithm 1 with names and verification: ``search(scenes, config, main_rank=0)``.
Search = Callable[..., Identification]


def next_main_stars(scenes: Scene, result: Identification, config: Config, search: Search) -> Identification:
    """``result`` with its unsolved scenes searched again, main star by main star
    (``Config.main_stars``, or ``Config.subgraph.main_stars`` with the subgraph search): the scenes
    still unsolved after main star k − 1 are searched with the k-th detection nearest the principal
    point as the main star, in a batch padded to a power of two, so that the calls share their
    compilations (neither the first search nor these fit a camera).

    Why: a main star that is no catalog star (a false star, a planet near the centre) cannot be
    matched, and with the paper's one main star its scene fails (``Config.main_stars``).
    """
    n_main = config.subgraph.main_stars if config.subgraph.on else config.main_stars
    if n_main == 1 or not scenes.batch_size:
        return result
    ids, ok = np.array(result.ids), np.array(result.ok)
    att = None if result.attitude is None else np.array(result.attitude)
    n_valid = np.asarray(scenes.valid).sum(1)
    for main_rank in range(1, n_main):
        todo = np.nonzero(~ok & (n_valid > main_rank))[0]
        if not todo.size:
            break
        sub = search(scenes[todo], config, main_rank=main_rank)  # padded with empty scenes there
        ids[todo], ok[todo] = np.asarray(sub.ids)[:todo.size], np.asarray(sub.ok)[:todo.size]
        if att is not None:
            att[todo] = np.asarray(sub.attitude)[:todo.size]
    return dataclasses.replace(result, ids=jnp.asarray(ids), ok=jnp.asarray(ok),
                               attitude=None if att is None else jnp.asarray(att))


def finishing_stage(db, scenes: Scene, result: Identification, config: Config, search: Search, *,
                    with_attitude: bool) -> tuple[Identification, np.ndarray, np.ndarray]:
    """:func:`jstarid.finishing.finish` with SGM's settings → ``(result, laddered, claimed)``: (B,) bool
    the scenes the focal-length ladder solved, and those SGM or the ladder claimed
    (:attr:`jstarid.finishing.Finished.claimed`, for :func:`search_lost`).

    Why a ladder: the graph's edges are angles, and a scale error of 2 % moves the circle's edge
    stars by 0.1°, past the verification's tolerance. Its searches stop at Δw =
    ``ladder.dw_max_deg``: a scene the rescaled camera explains is found at small Δw, and the
    scenes left are mostly ones no focal length solves (``Config.ladder.dw_max_deg``). The
    camera check keeps names out to :func:`camera_check_cap_px`. Without ``with_attitude`` the
    attitude the camera check fits is dropped.
    """
    cap = config.ladder.dw_max_deg
    retry = config if cap is None else dataclasses.replace(config, dw_max_deg=min(cap, config.dw_max_deg))
    finished = finish(
        result, scenes, config.finishing, rerun=lambda moved, rows: search(moved, retry),
        camera=db.camera, star_vectors=jnp.asarray(db.catalog.unit_vectors, jnp.float32),
        star_mags=db.catalog.mag, max_tol_px=camera_check_cap_px(config, db.camera), confirm=False)
    result, laddered = finished.result, finished.laddered
    if scenes.batch_size and config.finishing.fit_focal and not with_attitude:
        result = dataclasses.replace(result, attitude=None)
    return result, laddered, finished.claimed


def camera_check_cap_px(config: Config, camera) -> float:
    """Largest radius (px) within which the camera check (``Config.fit_focal``) keeps a name: SGM's
    own verification cap ``verify.cap_deg`` in pixels, never below the check's default
    (:data:`jstarid.camera_fit.MAX_TOL_PX`).

    Why: the check keeps a name within 6 σ̂ of the fit, clipped to 10 px by default, while SGM's
    verification was tuned to accept residuals up to 0.3° (3.5 × the residual RMS at the paper's
    σ = 3 px: 15.2 px on ``sgm2022``). At σ = 3 px a right name lies beyond 10 px in ≈ 0.4 % of
    the draws: the 10 px clip took back 104 right names of 1,000 scenes and so failed their scenes
    on the paper's criterion (1,000 scenes, accuracy of eq. 9: 70.6 % without the check, 66.0 %
    with the 10 px clip, 70.1 % with this cap; none wrong in any of them).
    """
    cap = math.tan(math.radians(config.verify.cap_deg)) * camera.f_px
    return max(MAX_TOL_PX, float(cap))


def _camera_check(db, scenes: Scene, result: Identification, config: Config) -> Identification:
    """:func:`jstarid.camera_fit.check_identification` with SGM's settings (``Config.finishing``)."""
    return check_identification(jnp.asarray(db.catalog.unit_vectors, jnp.float32), db.camera, scenes,
                                result, max_scale_error=config.finishing.max_focal_error,
                                max_tol_px=camera_check_cap_px(config, db.camera), star_mags=db.catalog.mag,
                                studentized=config.finishing.studentized)


def name_at_fitted_focal(db, scenes: Scene, result: Identification, laddered: np.ndarray,
                         config: Config) -> Identification:
    """``result`` with the scenes the focal-length ladder solved (``laddered`` (B,) bool) and the
    camera check kept renamed under their fitted focal length: the members of the image circle left
    unnamed are named from the attitude (:func:`.naming.name_leftovers`), verified
    (:func:`.naming.verify_claims`) and checked by the camera fit again; a scene whose renaming
    fails keeps its names. On with the camera check and ``verify.rename`` (with ``verify`` and
    ``leftover_tol_deg``).

    Why: the ladder's factors are 1 % apart, and under the factor that found a scene its edge stars
    sit up to 0.05° from their predicted directions, past what the leftover naming and the
    verification accept, although the camera check then fits the focal length to a fraction of
    that. At the paper's lost-star level σ = 0.5 px, 27 of the 29 scenes the ladder answered came
    back with part of the circle unnamed (1–2 stars and a fitted scale within 0.2 % of 1 in the six
    examined; every name right): answered incompletely, they count against eq. 9. Renamed, the
    level's identification rate went from 98.92 to 99.41 % (experiments/RESULTS.md).
    """
    renames = config.verify.on and config.verify.rename and config.leftover_tol_deg is not None
    if not (scenes.batch_size and config.finishing.fit_focal and renames):
        return result
    rows = np.flatnonzero(laddered & np.asarray(result.ok))
    if not rows.size:
        return result
    padded, moved, g = _graphs_at_fitted_focal(db, scenes, result, rows, config)
    nominal, _ = searchable_graphs(db, scenes[padded], config)
    g = with_members_of(g, nominal)
    given = Identification(ids=jnp.asarray(np.asarray(result.ids)[padded]),
                           ok=jnp.asarray(np.asarray(result.ok)[padded]), attitude=None)
    renamed = rename_and_reverify(db, moved, given, g, config)
    n_given = np.sum(np.asarray(given.ids) >= 0, 1)
    more = np.sum(np.asarray(renamed.ids) >= 0, 1) > n_given
    if not np.any(more[:rows.size]):
        return result
    again = _camera_check(db, scenes[padded], dataclasses.replace(renamed, ok=renamed.ok & more), config)
    # kept only where the camera check keeps more names than the first answer had
    better = (np.asarray(again.ok) & (np.sum(np.asarray(again.ids) >= 0, 1) > n_given))[:rows.size]
    if not np.any(better):
        return result
    at, src = rows[better], np.flatnonzero(better)

    def merged(old, new):  # on the host: no program per row count
        if old is None:
            return None
        out = np.array(old)
        out[at] = np.asarray(new)[src]
        return jax.device_put(out)

    return Identification(ids=merged(result.ids, again.ids), ok=result.ok,
                          attitude=merged(result.attitude, again.attitude),
                          focal_scale=merged(result.focal_scale, again.focal_scale),
                          distortion_k1=merged(result.distortion_k1, again.distortion_k1))


def _graphs_at_fitted_focal(db, scenes: Scene, result: Identification, rows: np.ndarray, config: Config):
    """The scenes ``rows`` (padded to a coarse size ≥ ``MIN_CALL_SIZE``,
    :func:`jstarid.runtime.padded_indices` with ``coarse``) as seen under the focal length
    ``result`` fitted them (``focal_scale``; the nominal one where it is NaN or not fitted):
    ``(padded rows, moved scenes, their image graphs)``."""
    padded = padded_indices(rows, floor=MIN_CALL_SIZE, coarse=True)
    scale = np.ones(padded.size, np.float32)
    if result.focal_scale is not None:
        scale = np.nan_to_num(np.asarray(result.focal_scale, np.float32)[padded], nan=1.0)
    moved = rescale_scenes(scenes[padded], db.camera, scale)
    g, _ = searchable_graphs(db, moved, config)
    return padded, moved, g


def with_members_of(g: ImageGraph, other: ImageGraph) -> ImageGraph:
    """Image graphs ``g`` (NumPy) with the members of ``other``'s circles (same scenes, same main
    stars) that ``g`` lacks appended as further masked-in members (for the leftover naming, which
    reads ``members`` and ``mask`` only).

    Why: :func:`name_at_fitted_focal` names the circle under the fitted focal length, but the
    paper's criterion draws it under the camera's: a star 0.002° inside r under the camera's focal
    length falls outside under a fitted scale of 0.998 and would stay unnamed (2 of the 18 scenes
    answered incompletely at lost stars, σ = 0.5 px)."""
    held = np.where(g.mask, g.members, -2)
    extra = other.mask & ~np.any(other.members[:, :, None] == held[:, None, :], axis=2)
    return g._replace(members=np.concatenate([g.members, other.members], axis=1),
                      mask=np.concatenate([g.mask, extra], axis=1))


def whole_circles_only(db, scenes: Scene, result: Identification, laddered: np.ndarray,
                       config: Config) -> Identification:
    """``result`` with those of the scenes the focal-length ladder solved (``laddered`` (B,) bool)
    that leave a star of their image circle unnamed turned into failures
    (``Config.ladder.whole_circle``; not with ``subgraph``). The circle is drawn under the
    fitted focal length; an unnamed member counts as a star left unnamed where a catalog star not
    named in the scene lies within ``leftover_tol_deg`` (``verify.cap_deg`` where that is off) of
    its direction under the attitude of the names; the others are false stars or stars the catalog
    does not hold.

    Why: the ladder is a fallback for a focal length that is not the camera's, and a scene it solves
    under the right focal length is named whole, as a scene Algorithm 1 solves at once is (edges
    that are angles fit again). Where part of the circle stays unnamed the fallback has found the
    attitude but not the scene the paper's criterion asks for, and answered it would count against
    eq. 9 (correct / (total − failed)): at the paper's lost-star level σ = 3 px the ladder answered
    169 of the 561 scenes Algorithm 1 left, 152 of them with part of the circle unnamed, which took
    the level's eq. 9 accuracy from 71.30 to 69.09 % (experiments/RESULTS.md). A false star is not
    asked for: counted, it failed the ladder's answers of the scenes whose false star falls inside
    the circle (28 % of them in the paper's fake-star experiment).
    """
    if not config.ladder.whole_circle or config.subgraph.on:
        return result
    rows = np.flatnonzero(laddered & np.asarray(result.ok))
    if not rows.size:
        return result
    padded, moved, g = _graphs_at_fitted_focal(db, scenes, result, rows, config)
    given = Identification(ids=jnp.asarray(np.asarray(result.ids)[padded]),
                           ok=jnp.asarray(np.asarray(result.ok)[padded]), attitude=None)
    tol = config.leftover_tol_deg if config.leftover_tol_deg is not None else config.verify.cap_deg
    # a star left unnamed is one the leftover naming would name: an unnamed member with an unnamed
    # catalog star within tol of its direction
    nameable = name_leftovers(db, moved, given, g, dataclasses.replace(config, leftover_tol_deg=tol))
    partial = rows[np.any(nameable != np.asarray(given.ids), axis=1)[:rows.size]]
    return result.failed(partial) if partial.size else result


def confirmed_by_the_frame(db, scenes: Scene, result: Identification, config: Config) -> Identification:
    """The finishing stage's false-match test (:func:`jstarid.finishing.confirmed_by_the_frame`,
    ``Finishing.max_false_match``), run after SGM's own steps, which change the names: a claim stands
    only where its names, or the whole frame named from its attitude within
    :func:`camera_check_cap_px`, make a coincidence unlikely.

    Why (SGM): three or four points fit some catalog graph within SGM's tolerances wherever the
    catalog is dense enough, and a circle that holds only three or four detections is all SGM looks
    at. On a 10° × 7.5° camera with stars to V 5.7 (five or six per frame) the defaults claimed 22 of
    300 frames of 8 random points, and 14 of 21 claims with 10 false detections per scene were wrong
    (docs/design/sgm.md, ``max_false_match``). A claim of five wrong names at 10 false detections,
    which the camera check kept, got P = 1 from the frame too (experiments/false_match.py on
    ``challenge6``).
    """
    return finishing.confirmed_by_the_frame(result, scenes, config.finishing, stars=db.catalog,
                                            camera=db.camera, tol_px=camera_check_cap_px(config, db.camera))


def search_lost(db, scenes: Scene, result: Identification, claimed: np.ndarray, config: Config, *,
                with_attitude: bool) -> Identification:
    """The finishing stage's last step (:func:`jstarid.finishing.search_lost`), run after SGM's own
    steps: the scenes whose claim the camera check, SGM's steps after it or the confirmation took back
    (``claimed`` (B,) bool, from :func:`finishing_stage`) searched over their detections' triangles.

    Why: on a sparse field among clutter SGM's main star and its circle are often false detections;
    a claim that the checks take back leaves the scene as unsolved as one SGM never claimed, which
    the stage's first step searches. Without ``with_attitude`` the search's attitudes are dropped.
    """
    result, _ = finishing.search_lost(result, scenes, config.finishing, claimed, camera=db.camera,
                                      star_vectors=jnp.asarray(db.catalog.unit_vectors, jnp.float32),
                                      star_mags=db.catalog.mag, stars=db.catalog,
                                      max_tol_px=camera_check_cap_px(config, db.camera))
    return result if with_attitude else dataclasses.replace(result, attitude=None)
