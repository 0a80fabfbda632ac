"""SGM identification of a batch of scenes (You et al. 2022, Algorithm 1).

Per scene: main star I = the valid detection nearest the principal point; its neighbor graph G_I
(detections within r) and w_I by the database's Prim MST; the dynamic Δw search (:mod:`.search`);
every detection of G_I, the main star included, is named through the vertex correspondence of the
best match, never through the candidate's main-star label (≈ 7 % of main stars have a twin graph,
conventions §7 pitfall 2). Detections outside the circle and unmatched vertices get −1.

Not in the paper (:class:`Config`): ``vertex_check_deg`` (off) unnames vertices whose edges disagree
with the database graph; ``leftover_tol_deg`` (on) names the members of G_I the match left unnamed
from the attitude of the matched stars; ``verify`` (on, :mod:`.verify`) fails a scene rather than
mis-identify it; ``verify_rename`` names what the verification left unnamed and verifies again;
``verify_retries`` strikes out a rejected match and resumes the search (:mod:`.search`,
"Resumption"), so the verification joins Algorithm 1's acceptance test.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.base import check_scenes
from jstarid.algorithms.sgm.config import Config
from jstarid.algorithms.sgm.graph import image_graph
from jstarid.algorithms.sgm.search import (
    SearchOutcome,
    advance_search,
    reject_best,
    search_outcome,
    start_search,
)
from jstarid.algorithms.sgm.subgraph import subgraph_search
from jstarid.algorithms.sgm.verify import verify_ids
from jstarid.attitude import estimate_attitude
from jstarid.camera_fit import MAX_TOL_PX, check_identification, rescale_scenes
from jstarid.finishing import finish
from jstarid.metrics import by_distance_to_principal_point, nearest_to_principal_point
from jstarid.runtime import map_batch, on_every_device, padded_indices, release_staging
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Identification, Scene
from jstarid.sky_index import build_sky_index

__all__ = ["Diagnostics", "identify", "scene_graphs", "searchable_graphs"]


class Diagnostics(NamedTuple):
    """Per-scene internals of :func:`identify` (host NumPy arrays, batch axis first).

    Attributes:
        n_candidates: (B,) int32 database graphs examined (``n_matched + n_pruned``).
        overflow: (B,) bool, the scene or its neighbor graph exceeded its capacity.
        n_matched: (B,) spectral matchings run. n_pruned: (B,) candidates excluded by the bound.
        n_rejected: (B,) matches the post-match verification rejected.
        n_i: (B,) vertices of the image neighbor graph. w_i: (B,) its MST weight (deg).
        main: (B,) detection index of the main star.
        usable: (B,) the scene entered the search (a detection, no overflow, ≥ ``min_stars``).
        match_ok: (B,) Algorithm 1 accepted a match (δ ≤ ε_δ), before the verification.
        best: (B,) database row of the accepted match (−1 none); best_main: its catalog main star.
        error: (B,) its matching error δ (deg, eq. 5). level: (B,) the Δw level it was found at.
        main_contested: (B,) failed only because a close rival contests the main star's name.
        cut: (B,) bool, with ``Config.subgraph``: the accepted database graph had more radius
            partners than its cut graph holds (:func:`.subgraph.partner_vertices`); ``None`` with
            the paper's search.
    """

    n_candidates: np.ndarray
    overflow: np.ndarray
    n_matched: np.ndarray
    n_pruned: np.ndarray
    n_rejected: np.ndarray
    n_i: np.ndarray
    w_i: np.ndarray
    main: np.ndarray
    usable: np.ndarray
    match_ok: np.ndarray
    best: np.ndarray
    best_main: np.ndarray
    error: np.ndarray
    level: np.ndarray
    main_contested: np.ndarray
    cut: np.ndarray | None = None


@functools.partial(stored_jit, static_argnames=("camera", "radius_deg", "capacity", "main_rank"))
def scene_graphs(xy, valid, *, camera, radius_deg: float, capacity: int, main_rank: int = 0):
    """Image neighbor graphs of a batch.

    Args:
        xy: (B, N, 2) centroids (px). valid: (B, N) bool.
        camera: static :class:`~jstarid.camera.Camera`. radius_deg: r (deg). capacity: static K.
        main_rank: static; the main star is the valid detection nearest the principal point (0, the
            paper's choice) or the ``main_rank``-th nearest after it (``Config.subgraph_main_stars``).

    Returns:
        :class:`~jstarid.algorithms.sgm.graph.ImageGraph` of (B, …) arrays, with ``main`` (B,)
        int32 main-star detection and ``any`` (B,) bool (the scene has such a detection).
    """
    if main_rank == 0:
        main = nearest_to_principal_point(xy, valid, camera)
        has = jnp.any(valid, axis=-1)
    else:
        main = by_distance_to_principal_point(xy, valid, camera)[:, main_rank]
        has = jnp.sum(valid, axis=-1) > main_rank
    vecs = camera.unproject(xy)
    g = jax.vmap(image_graph, in_axes=(0, 0, 0, None, None))(vecs, valid, main, radius_deg,
                                                             capacity)
    return g._replace(main=main.astype(jnp.int32), any=has)


def searchable_graphs(db, scenes: Scene, config: Config, main_rank: int = 0):
    """The scenes' image graphs (:func:`scene_graphs`, as NumPy arrays) and which ones Algorithm 1
    searches: (B,) bool, a detection, no overflow, at least ``config.min_stars`` vertices."""
    g = jax.tree.map(np.asarray, scene_graphs(scenes.xy, scenes.valid, camera=db.camera,
                                              radius_deg=float(db.radius_deg), capacity=int(db.capacity),
                                              main_rank=main_rank))
    return g, g.any & ~g.overflow & (g.n >= config.min_stars)


def identify(db, scenes: Scene, config: Config | None = None, *, diagnostics: bool = False,
             with_attitude: bool = True):
    """Identify the stars of the main star's neighbor circle in every scene.

    Args:
        db: :class:`~jstarid.algorithms.sgm.database.Database` (built with the same ``radius_deg``).
        scenes: (B, N) :class:`~jstarid.scene.Scene` from ``db.camera``.
        config: :class:`Config` (its database fields must match ``db``); ``None`` → the paper's
            defaults plus the extensions that are on by default.
        diagnostics: also return the per-scene :class:`Diagnostics`.
        with_attitude: also solve Wahba from the identified stars (``Identification.attitude``).

    Returns:
        :class:`~jstarid.scene.Identification`: ``ids`` (B, N) int32 catalog rows of the verified
        detections of the neighbor circle (−1 elsewhere; every id −1 where ``ok`` (B,) is False), or
        with ``diagnostics`` a ``(result, Diagnostics)`` tuple (the diagnostics of the first
        pass). With ``config.fit_focal`` also ``focal_scale`` (B,), the fitted focal length /
        the camera's (NaN where not fitted).

    Extensions (``Config.main_stars``, ``Config.finishing``; off in ``Config.paper()``;
    ``main_stars`` is 1, off, by default): the scenes left unsolved are searched again with the next
    main stars; then the finishing stage (:func:`jstarid.finishing.finish`) tries the scenes still
    unsolved under focal lengths 1–2 % off (up to Δw = ``focal_search_dw_max_deg``: the graph's
    edges are angles, and a scale error of 2 % moves the circle's edge stars by 0.1°, past the
    verification's tolerance) and checks every solved scene's names against a joint fit of attitude
    and focal length; the scenes the ladder solved are then named again under the fitted focal
    length (:func:`_name_at_fitted_focal`) and kept only where their whole circle is named
    (:func:`_whole_circles_only`).

    Raises:
        ValueError: ``config.radius_deg`` differs from the database's.
    """
    config = Config() if config is None else config
    check_scenes(scenes)
    if abs(config.radius_deg - db.radius_deg) > 1e-12:
        raise ValueError(f"config.radius_deg={config.radius_deg} but the database was built with "
                         f"r={db.radius_deg}")
    out = _identify(db, scenes, config, diagnostics=diagnostics, with_attitude=with_attitude)
    result, diag = out if diagnostics else (out, None)
    if scenes.batch_size:
        result = _next_main_stars(db, scenes, result, config, with_attitude=with_attitude)
    cap = config.focal_search_dw_max_deg
    retry = config if cap is None else dataclasses.replace(config, dw_max_deg=min(cap, config.dw_max_deg))
    result, laddered = finish(
        result, scenes, config.finishing,
        rerun=lambda moved, rows: _identify(db, moved, retry, with_attitude=with_attitude),
        camera=db.camera, star_vectors=jnp.asarray(db.catalog.unit_vectors, jnp.float32),
        star_mags=db.catalog.mag, max_tol_px=camera_check_cap_px(config, db.camera))
    if scenes.batch_size and config.finishing.fit_focal:
        renames = config.verify and config.verify_rename and config.leftover_tol_deg is not None
        if renames and np.any(laddered):
            result = _name_at_fitted_focal(db, scenes, result, laddered & np.asarray(result.ok), config)
        if not with_attitude:
            result = dataclasses.replace(result, attitude=None)
    if config.focal_search_whole_circle and not config.subgraph and np.any(laddered):
        result = _whole_circles_only(db, scenes, result, laddered & np.asarray(result.ok), config)
    release_staging()
    return (result, diag) if diagnostics else result


def _next_main_stars(db, scenes: Scene, result: Identification, config: Config, *,
                     with_attitude: bool) -> Identification:
    """``result`` with its unsolved scenes searched again, main star by main star
    (``Config.main_stars``, or ``Config.subgraph_main_stars`` with the subgraph search): the scenes
    still unsolved after main star k − 1 are searched with the k-th detection nearest the principal
    point as the main star, in a batch padded to a power of two, so that the calls share their
    compilations (neither the first search nor these fit a camera)."""
    n_main = config.subgraph_main_stars if config.subgraph else config.main_stars
    if n_main == 1:
        return result
    ids, ok = np.array(result.ids), np.array(result.ok)
    att = None if result.attitude is None else np.array(result.attitude)
    n_valid = np.asarray(scenes.valid).sum(1)
    for main_rank in range(1, n_main):
        todo = np.nonzero(~ok & (n_valid > main_rank))[0]
        if not todo.size:
            break
        sub = _identify(db, scenes[padded_indices(todo)], config, with_attitude=with_attitude,
                        main_rank=main_rank)
        ids[todo], ok[todo] = np.asarray(sub.ids)[:todo.size], np.asarray(sub.ok)[:todo.size]
        if att is not None:
            att[todo] = np.asarray(sub.attitude)[:todo.size]
    return dataclasses.replace(result, ids=jnp.asarray(ids), ok=jnp.asarray(ok),
                               attitude=None if att is None else jnp.asarray(att))


def _camera_check(db, scenes: Scene, result: Identification, config: Config) -> Identification:
    """:func:`jstarid.camera_fit.check_identification` with SGM's settings (``Config.finishing``)."""
    return check_identification(jnp.asarray(db.catalog.unit_vectors, jnp.float32), db.camera, scenes,
                                result, max_scale_error=config.finishing.max_focal_error,
                                max_tol_px=camera_check_cap_px(config, db.camera), star_mags=db.catalog.mag,
                                studentized=config.finishing.studentized)


def _name_at_fitted_focal(db, scenes: Scene, result: Identification, take: np.ndarray,
                          config: Config) -> Identification:
    """``result`` with the scenes ``take`` (B,) bool (solved by the focal-length ladder and kept by
    the camera check) renamed under their fitted focal length: the members of the image circle left
    unnamed are named from the attitude (:func:`_name_leftovers`), verified (:func:`_verify`) and
    checked by the camera fit again; a scene whose renaming fails keeps its names.

    Why: the ladder's factors are 1 % apart, and under the factor that found a scene its edge stars
    sit up to 0.05° from their predicted directions, past what the leftover naming and the
    verification accept, although the camera check then fits the focal length to a fraction of
    that. At the paper's lost-star level σ = 0.5 px, 27 of the 29 scenes the ladder answered came
    back with part of the circle unnamed (1–2 stars and a fitted scale within 0.2 % of 1 in the six
    examined; every name right): answered incompletely, they count against eq. 9. Renamed, the
    level's identification rate went from 98.92 to 99.41 % (experiments/RESULTS.md).
    """
    rows = np.flatnonzero(take)
    if not rows.size:
        return result
    padded, moved, g = _graphs_at_fitted_focal(db, scenes, result, rows, config)
    nominal, _ = searchable_graphs(db, scenes[padded], config)
    g = _with_members_of(g, nominal)
    given = Identification(ids=jnp.asarray(np.asarray(result.ids)[padded]),
                           ok=jnp.asarray(np.asarray(result.ok)[padded]), attitude=None)
    renamed = _rename_and_reverify(db, moved, given, g, config)
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

    def merged(old, new):
        return None if old is None else jnp.asarray(old).at[at].set(jnp.asarray(new)[src])

    return Identification(ids=merged(result.ids, again.ids), ok=result.ok,
                          attitude=merged(result.attitude, again.attitude),
                          focal_scale=merged(result.focal_scale, again.focal_scale),
                          distortion_k1=merged(result.distortion_k1, again.distortion_k1))


def _graphs_at_fitted_focal(db, scenes: Scene, result: Identification, rows: np.ndarray, config: Config):
    """The scenes ``rows`` (padded to a power of two, :func:`_padded`) as seen under the focal length
    ``result`` fitted them (``focal_scale``; the nominal one where it is NaN or not fitted):
    ``(padded rows, moved scenes, their image graphs)``."""
    padded = padded_indices(rows)
    scale = np.ones(padded.size, np.float32)
    if result.focal_scale is not None:
        scale = np.nan_to_num(np.asarray(result.focal_scale, np.float32)[padded], nan=1.0)
    moved = rescale_scenes(scenes[padded], db.camera, scale)
    g, _ = searchable_graphs(db, moved, config)
    return padded, moved, g


def _with_members_of(g, other):
    """Image graphs ``g`` (NumPy) with the members of ``other``'s circles (same scenes, same main
    stars) that ``g`` lacks appended as further masked-in members (for the leftover naming, which
    reads ``members`` and ``mask`` only).

    Why: :func:`_name_at_fitted_focal` names the circle under the fitted focal length, but the
    paper's criterion draws it under the camera's: a star 0.002° inside r under the camera's focal
    length falls outside under a fitted scale of 0.998 and would stay unnamed (2 of the 18 scenes
    answered incompletely at lost stars, σ = 0.5 px)."""
    held = np.where(g.mask, g.members, -2)
    extra = other.mask & ~np.any(other.members[:, :, None] == held[:, None, :], axis=2)
    return g._replace(members=np.concatenate([g.members, other.members], axis=1),
                      mask=np.concatenate([g.mask, extra], axis=1))


def _whole_circles_only(db, scenes: Scene, result: Identification, take: np.ndarray,
                        config: Config) -> Identification:
    """``result`` with those of the scenes ``take`` (B,) bool (solved by the focal-length ladder) that
    leave a star of their image circle unnamed turned into failures
    (``Config.focal_search_whole_circle``). The circle is drawn under the fitted focal length; an
    unnamed member counts as a star left unnamed where a catalog star not named in the scene lies
    within ``leftover_tol_deg`` (``verify_cap_deg`` where that is off) of its direction under the
    attitude of the names; the others are false stars or stars the catalog does not hold.

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
    rows = np.flatnonzero(take)
    if not rows.size:
        return result
    padded, moved, g = _graphs_at_fitted_focal(db, scenes, result, rows, config)
    given = Identification(ids=jnp.asarray(np.asarray(result.ids)[padded]),
                           ok=jnp.asarray(np.asarray(result.ok)[padded]), attitude=None)
    tol = config.leftover_tol_deg if config.leftover_tol_deg is not None else config.verify_cap_deg
    # a star left unnamed is one the leftover naming would name: an unnamed member with an unnamed
    # catalog star within tol of its direction
    nameable = _name_leftovers(db, moved, given, g, dataclasses.replace(config, leftover_tol_deg=tol))
    partial = rows[np.any(nameable != np.asarray(given.ids), axis=1)[:rows.size]]
    return _failed(result, partial) if partial.size else result


def _failed(result: Identification, rows: np.ndarray) -> Identification:
    """``result`` with the scenes ``rows`` failed: ids −1, ``ok`` False, NaN attitude and fits."""
    def cleared(x, value):
        return None if x is None else jnp.asarray(x).at[rows].set(value)

    return Identification(ids=cleared(result.ids, -1), ok=cleared(result.ok, False),
                          attitude=cleared(result.attitude, jnp.nan),
                          focal_scale=cleared(result.focal_scale, jnp.nan),
                          distortion_k1=cleared(result.distortion_k1, jnp.nan))


def camera_check_cap_px(config: Config, camera) -> float:
    """Largest radius (px) within which the camera check (``Config.fit_focal``) keeps a name: SGM's
    own verification cap ``verify_cap_deg`` in pixels, never below the check's default
    (:data:`jstarid.camera_fit.MAX_TOL_PX`).

    Why: the check keeps a name within 6 σ̂ of the fit, clipped to 10 px by default, while SGM's
    verification was tuned to accept residuals up to 0.3° (3.5 × the residual RMS at the paper's
    σ = 3 px: 15.2 px on ``sgm2022``). At σ = 3 px a right name lies beyond 10 px in ≈ 0.4 % of
    the draws: the 10 px clip took back 104 right names of 1,000 scenes and so failed their scenes
    on the paper's criterion (1,000 scenes, accuracy of eq. 9: 70.6 % without the check, 66.0 %
    with the 10 px clip, 70.1 % with this cap; none wrong in any of them).
    """
    cap = math.tan(math.radians(config.verify_cap_deg)) * camera.f_px
    return max(MAX_TOL_PX, float(cap))


def _identify(db, scenes: Scene, config: Config, *, diagnostics: bool = False, with_attitude: bool = True,
              main_rank: int = 0):
    """:func:`identify` without the focal-length extensions and the next main stars (the paper's
    search and the verification), on scenes already checked, with the ``main_rank``-th detection
    nearest the principal point as the main star."""
    if config.subgraph:
        return _identify_subgraph(db, scenes, config, diagnostics=diagnostics,
                                  with_attitude=with_attitude, main_rank=main_rank)
    g, usable = searchable_graphs(db, scenes, config, main_rank=main_rank)
    state = advance_search(db, g, start_search(db, g, usable, config), config)
    res = search_outcome(state, config, g.mask.shape[1])

    def resume(res, redo):  # strike out the rejected J* and let Algorithm 1 go on
        nonlocal state
        retry = np.zeros(res.ok.shape, bool)
        retry[redo] = True
        state = advance_search(db, g, reject_best(state, res, redo), config, retry)
        return search_outcome(state, config, g.mask.shape[1])

    result, res, contested_main = _names_with_retries(db, scenes, g, res, config, resume)
    if with_attitude:
        att, _, have = estimate_attitude(db.catalog, db.camera, scenes, result)
        att = jnp.where((have & result.ok)[:, None, None], att, jnp.nan)
        result = Identification(ids=result.ids, ok=result.ok, attitude=att)
    if diagnostics:
        ok = res.ok
        matched, pruned = res.n_matched, res.n_pruned
        diag = Diagnostics(
            n_candidates=(matched + pruned).astype(np.int32),
            overflow=g.overflow | np.asarray(scenes.overflow), n_matched=matched,
            n_pruned=pruned, n_rejected=res.n_rejected, n_i=g.n, w_i=g.w, main=g.main,
            usable=usable, match_ok=ok, best=res.best,
            best_main=np.where(ok, db.main[np.clip(res.best, 0, None)], -1), error=res.error,
            level=res.level, main_contested=contested_main)
        return result, diag
    return result


def _identify_subgraph(db, scenes: Scene, config: Config, *, diagnostics: bool = False,
                       with_attitude: bool = True, main_rank: int = 0):
    """:func:`_identify` with ``Config.subgraph`` (:mod:`.subgraph`): each scene's ranked accepted
    candidates are named and verified in order (up to ``verify_retries`` more after a rejection), with
    the ``main_rank``-th detection nearest the principal point as the main star (the batch padded
    to a power of two, so that the calls share their compilations).
    """
    b = scenes.batch_size
    if not b:
        empty = Identification(ids=jnp.asarray(np.asarray(scenes.valid, np.int32) * 0 - 1),
                               ok=jnp.zeros((0,), bool), attitude=None)
        return (empty, None) if diagnostics else empty
    sub_scenes = scenes[padded_indices(np.arange(b))]
    g, usable = searchable_graphs(db, sub_scenes, config, main_rank=main_rank)
    ranked = subgraph_search(db, g, usable, config)
    sub, outcome = _verify_ranked(db, sub_scenes, g, ranked, config)
    result = Identification(ids=jnp.asarray(np.asarray(sub.ids)[:b]), ok=jnp.asarray(np.asarray(sub.ok)[:b]),
                            attitude=None)
    if with_attitude:
        att, _, have = estimate_attitude(db.catalog, db.camera, scenes, result)
        att = jnp.where((have & result.ok)[:, None, None], att, jnp.nan)
        result = Identification(ids=result.ids, ok=result.ok, attitude=att)
    if diagnostics:
        return result, _subgraph_diagnostics(db, sub_scenes, g, usable, ranked, outcome, b)
    return result


def _names_with_retries(db, scenes: Scene, g, res: SearchOutcome, config: Config, next_outcome):
    """:func:`_names_from_match`, then, for the matches the verification rejected (``verify_retries``
    times at most), the search's next answer: ``next_outcome(res, redo)`` → the
    :class:`~.search.SearchOutcome` with the scenes ``redo`` (R,) moved on. Not when only the main
    star's name was contested: another graph cannot settle that.

    Returns:
        ``(result, res, contested_main)``: the :class:`~jstarid.scene.Identification`, the last
        outcome and (B,) bool, failed only because the main star's name is contested.
    """
    result, contested = _names_from_match(db, scenes, g, res, config)
    contested = contested.copy()  # a view of a device array is read-only
    if not config.verify:
        return result, res, contested
    for _ in range(config.verify_retries):
        retry = res.ok & ~np.asarray(result.ok) & ~contested
        if not np.any(retry):
            break
        redo = np.nonzero(retry)[0]
        res = next_outcome(res, redo)
        sub, sub_contested = _names_from_match(db, scenes, g, res, config, rows=redo)
        result = _merge(result, sub, redo)
        contested[redo] = sub_contested
    return result, res, contested


def _outcome_at(ranked: dict, pick: np.ndarray, n_rejected: np.ndarray) -> SearchOutcome:
    """The :class:`~.search.SearchOutcome` of the candidate ``pick`` (B,) of each scene's ranking
    (none where ``pick`` is past the ranking's end)."""
    at = np.arange(pick.size)
    inside = pick < ranked["ok"].shape[1]
    pick = np.minimum(pick, ranked["ok"].shape[1] - 1)
    ok = ranked["ok"][at, pick] & inside
    n_tried = np.sum(np.isfinite(ranked["error"]), axis=1).astype(np.int32)
    return SearchOutcome(ok=ok, best=np.where(ok, ranked["rows"][at, pick], -1).astype(np.int32),
                         rank=np.where(ok, pick, -1).astype(np.int32),
                         match=np.where(ok[:, None], ranked["match"][at, pick], -1),
                         error=ranked["error"][at, pick], n_matched=n_tried,
                         n_pruned=np.zeros(pick.size, np.int32), n_rejected=n_rejected,
                         level=np.where(ok, 0, -1).astype(np.int32))


def _verify_ranked(db, scenes: Scene, g, ranked: dict, config: Config):
    """Name and verify each scene's best accepted candidate; a rejected one gives way to the next
    in the ranking (:func:`_names_with_retries`). Returns ``(result, outcome)``."""
    b = ranked["ok"].shape[0]
    pick = np.zeros(b, np.int64)
    n_rejected = np.zeros(b, np.int32)

    def next_in_ranking(res, redo):
        pick[redo] += 1
        n_rejected[redo] += 1
        return _outcome_at(ranked, pick, n_rejected)

    result, res, _ = _names_with_retries(db, scenes, g, _outcome_at(ranked, pick, n_rejected), config,
                                         next_in_ranking)
    return result, res


def _subgraph_diagnostics(db, scenes: Scene, g, usable, ranked: dict, res: SearchOutcome,
                          n: int) -> Diagnostics:
    """:class:`Diagnostics` of the first ``n`` rows of a subgraph search (``level`` 0 when accepted)."""
    best_err = np.min(ranked["error"], axis=1)
    at = np.arange(res.ok.size)
    return Diagnostics(
        n_candidates=np.sum(ranked["rows"] >= 0, axis=1).astype(np.int32)[:n],
        overflow=(g.overflow | np.asarray(scenes.overflow))[:n], n_matched=res.n_matched[:n],
        n_pruned=res.n_pruned[:n], n_rejected=res.n_rejected[:n], n_i=g.n[:n], w_i=g.w[:n],
        main=g.main[:n], usable=usable[:n], match_ok=res.ok[:n], best=res.best[:n],
        best_main=np.where(res.ok, db.main[np.clip(res.best, 0, None)], -1)[:n],
        error=np.where(res.ok, res.error, best_err)[:n], level=res.level[:n],
        main_contested=np.zeros(n, bool),
        cut=(res.ok & ranked["cut"][at, np.maximum(res.rank, 0)])[:n])


def _names_from_match(db, scenes: Scene, g: dict, res: dict, config: Config,
                      rows: np.ndarray | None = None) -> Identification:
    """Every step after the search: names from the correspondence, vertex check, leftover naming,
    verification and renaming (``Config``).

    Args:
        rows: optional (R,) scene rows to process (the result then has R rows), padded to a power of
            two so that the compiled verification serves every retry with a few shapes.

    Returns:
        ``(result, main_ambiguous)``: :class:`~jstarid.scene.Identification` and (B,) bool, the scenes
        failed only because their main star's name is contested (:func:`.verify.verify_ids`).
    """
    if rows is not None:
        padded = padded_indices(rows)
        sub, amb = _names_from_match(db, scenes[padded], jax.tree.map(lambda v: v[padded], g),
                                     jax.tree.map(lambda v: v[padded], res), config)
        return sub[:rows.size], amb[:rows.size]
    if config.vertex_check_deg is not None:
        res = dict(res)
        res.match, res.ok = _check_vertices(g.adj, db.adj, res, config)
    b, n_det = scenes.valid.shape
    ids = np.full((b, n_det), -1, np.int32)
    sc, vert = np.nonzero(res.match >= 0)
    det = g.members[sc, vert]
    ids[sc, det] = db.members[res.best[sc], res.match[sc, vert]]
    ok = res.ok
    result = Identification(ids=jnp.asarray(ids), ok=jnp.asarray(ok), attitude=None)
    if config.leftover_tol_deg is not None and np.any(ok):
        ids = _name_leftovers(db, scenes, result, g, config)
        result = Identification(ids=jnp.asarray(ids), ok=result.ok, attitude=None)
    main_ambiguous = np.zeros(b, bool)
    if config.verify and np.any(ok):
        result, main_ambiguous = _verify(db, scenes, result, g.main, config)
        if config.verify_rename and config.leftover_tol_deg is not None and np.any(result.ok):
            result = _rename_and_reverify(db, scenes, result, g, config)
    return result, main_ambiguous


def _merge(result: Identification, sub: Identification, rows: np.ndarray) -> Identification:
    """``result`` with the scenes ``rows`` replaced by ``sub``'s (R rows, in that order)."""
    return Identification(ids=jnp.asarray(result.ids).at[rows].set(sub.ids),
                          ok=jnp.asarray(result.ok).at[rows].set(sub.ok), attitude=None)


def _verify(db, scenes: Scene, result: Identification, main, config: Config):
    """:func:`.verify.verify_ids` with the settings of ``config`` → ``(Identification,
    main_ambiguous)``, the latter (B,) NumPy bool.

    Only the scenes ``result`` claims are verified (padded to a power of two, so that a few compiled
    shapes serve every call): the verification fails every other scene, with no names, anyway.
    """
    ok = np.asarray(result.ok)
    b, n_det = scenes.valid.shape
    ids = np.full((b, n_det), -1, np.int32)
    verified, main_ambiguous = np.zeros(b, bool), np.zeros(b, bool)
    rows = np.flatnonzero(ok)
    if rows.size:
        padded = padded_indices(rows)
        tables, settings = _verify_inputs(db, config)
        named = np.asarray(result.ids)[padded]
        # identify names only the neighbor graph's members (at most its capacity K): the ambiguity
        # tests then run on K rows, not on every detection slot; more names (a caller's own) → all
        n_named = int(np.max(np.sum(named >= 0, axis=1), initial=0))
        max_named = int(db.capacity) if n_named <= db.capacity else None
        sub = scenes[padded]
        out = map_batch(
            _verify_scenes, (sub.xy, sub.mag, sub.valid, jnp.asarray(named), jnp.asarray(ok[padded]),
                             jnp.asarray(np.asarray(main)[padded])),
            tables, static={**settings, "max_named": max_named})
        sub_ids, sub_ok, sub_amb = (np.asarray(x)[:rows.size] for x in out)
        ids[rows], verified[rows], main_ambiguous[rows] = sub_ids, sub_ok, sub_amb
    return Identification(ids=jnp.asarray(ids), ok=jnp.asarray(verified), attitude=None), main_ambiguous


def _verify_inputs(db, config: Config):
    """``(tables, settings)`` of :func:`.verify.verify_ids` (``max_named`` excepted): ``(cat, cat_mag,
    cells)`` placed on every device once per database, and a dict of the keyword arguments.
    """
    cat_np = np.asarray(db.catalog.unit_vectors, np.float64)
    # every catalog star within the field's half diagonal of any boresight in a cell (frame coverage)
    index = build_sky_index(cat_np, db.camera.half_diagonal_rad,
                            key=f"sgm-frame-{db.catalog.fingerprint}")
    tables = on_every_device(db, "verify", lambda: (
        jnp.asarray(cat_np, jnp.float32), jnp.asarray(db.catalog.mag, jnp.float32),
        index.device_arrays()[0]))
    settings = dict(camera=db.camera, grid=index.grid,
                    k=float(config.verify_k), floor_deg=float(config.verify_floor_deg),
                    cap_deg=float(config.verify_cap_deg),
                    amb_k=float(config.verify_ambiguity_k),
                    amb_deg=float(config.verify_ambiguity_deg),
                    partner_joint=bool(config.verify_partner_joint),
                    partner_k=float(config.verify_partner_k),
                    mag_sigma=float(config.verify_magnitude_sigma or 0.0),
                    rms_z=float(config.verify_rms_z),
                    min_matched=int(config.min_matched),
                    min_coverage=float(config.verify_min_coverage),
                    n_near=int(min(2 * db.capacity, cat_np.shape[0])))
    return tables, settings


def _verify_scenes(xy, mag, valid, ids, ok, main, cat, cat_mag, cells, **settings):
    """:func:`.verify.verify_ids` with the scenes first, as :func:`jstarid.runtime.map_batch` splits them."""
    return verify_ids(cat, cat_mag, cells, xy, mag, valid, ids, ok, main, **settings)


def _rename_and_reverify(db, scenes: Scene, verified: Identification, g, config: Config):
    """``Config.verify_rename``: :func:`_name_leftovers` on the verified names, then :func:`_verify` again
    on the scenes it changed; where that fails, the first result stands. Returns an
    :class:`~jstarid.scene.Identification` with the same ``ok`` as ``verified``.
    """
    before = np.asarray(verified.ids)
    ids = _name_leftovers(db, scenes, verified, g, config)
    changed = np.any(ids != before, axis=1)
    if not np.any(changed):
        return verified
    # verified again: only the scenes the renaming changed (the others keep their names)
    proposal = Identification(ids=jnp.asarray(ids), ok=jnp.asarray(np.asarray(verified.ok) & changed),
                              attitude=None)
    again, _ = _verify(db, scenes, proposal, g.main, config)
    take = changed & np.asarray(again.ok)
    ids = np.where(take[:, None], np.asarray(again.ids), before)
    return Identification(ids=jnp.asarray(ids), ok=verified.ok, attitude=None)


def _check_vertices(adj_i, db_adj, res, config: Config):
    """Unname matched vertices whose median edge residual exceeds ``config.vertex_check_deg``.

    Args:
        adj_i: (B, K, K) image adjacencies (deg). db_adj: (D, K, K) database adjacencies (deg).
        res: :class:`.search.SearchOutcome` (``match``, ``best``, ``ok``). config: :class:`Config`.

    Returns:
        ``(match, ok)``: (B, K) the kept correspondence (−1 elsewhere), (B,) bool.
    """
    match, ok = res.match.copy(), res.ok.copy()
    rows = np.nonzero(ok)[0]
    if rows.size == 0:
        return match, ok
    m = match[rows]
    used = m >= 0
    mj = np.clip(m, 0, None)
    a_j = db_adj[res.best[rows][:, None, None], mj[:, :, None], mj[:, None, :]]
    d = np.abs(adj_i[rows] - a_j)
    both = used[:, :, None] & used[:, None, :]
    both &= ~np.eye(m.shape[1], dtype=bool)[None]
    d = np.where(both, d, np.nan)
    with warnings.catch_warnings():  # all-NaN rows (unmatched vertices) are expected
        warnings.simplefilter("ignore", RuntimeWarning)
        resid = np.nanmedian(d, axis=2)
    bad = used & ~(resid <= config.vertex_check_deg)
    m = np.where(bad, -1, m)
    match[rows] = m
    ok[rows] = np.sum(m >= 0, axis=1) >= config.min_matched
    match[~ok] = -1
    return match, ok


def _name_leftovers(db, scenes: Scene, result: Identification, g: dict, config: Config):
    """(B, N) int32 ids: ``result.ids`` plus, in every successful scene, each unnamed image-graph member
    whose ICRS direction (``Cᵀ v``, attitude of the matched stars) lies within
    ``config.leftover_tol_deg`` of a catalog star not yet named in that scene.
    """
    ids = np.array(result.ids)
    att, _, have = estimate_attitude(db.catalog, db.camera, scenes, result, min_stars=3)
    att, have = np.asarray(att, np.float64), np.asarray(have) & np.asarray(result.ok)
    vec = np.asarray(db.camera.unproject(scenes.xy), np.float64)  # (B, N, 3) camera frame
    cat = np.asarray(db.catalog.unit_vectors, np.float64)
    cos_tol = np.cos(np.radians(config.leftover_tol_deg))
    for s in np.nonzero(have)[0]:
        mem = g.members[s][g.mask[s]]
        todo = mem[ids[s, mem] < 0]
        if todo.size == 0:
            continue
        sky = np.matmul(vec[s, todo], att[s])  # rows: Cᵀ v, ICRS
        dots = np.matmul(sky, cat.T)  # (n_todo, catalog)
        best = np.argmax(dots, axis=1)
        used = set(ids[s][ids[s] >= 0].tolist())
        for det, row, dot in zip(todo, best, dots[np.arange(todo.size), best], strict=True):
            if dot >= cos_tol and int(row) not in used:
                ids[s, det] = row
                used.add(int(row))
    return ids
