"""SGM identification of a batch of scenes: You et al. 2022, Algorithm 1, then our extensions.

:func:`identify` is the paper's pipeline followed by our steps:

1. **Algorithm 1** (:func:`_algorithm1`), per scene: the main star I (the valid detection nearest
   the principal point), its neighbor graph G_I (the detections within r) and its MST weight w_I
   (:func:`.graph.searchable_graphs`); the rough search (eq. 1, a k-vector over the database's
   sorted w_J) and the dynamic Δw search, every candidate matched spectrally (eqs. 2–5) until
   J* = argmin δ (eq. 6) passes ε_δ (:mod:`.search`); the names of G_I through J*'s vertex
   correspondence (:mod:`.naming`), then the verification (ours, :mod:`.verify`), which joins
   Algorithm 1's acceptance test: a rejected J* is struck out and the search goes on.
2. **Extensions** (:mod:`.extensions`; ``Config`` fields, all off in ``Config.paper()``), in order:
   the next main stars, the finishing stage every algorithm shares (focal-length ladder and camera
   check), the ladder's scenes named again under the fitted focal length, those kept only
   where their whole circle is named, and scenes of few names kept only where the frame confirms them.

With ``Config.subgraph`` the pass searches the image graph as a subgraph of the database graphs
(:func:`_subgraph_pass`, :mod:`.subgraph`) instead of by its MST weight; the rest is the same.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.base import check_scenes
from jstarid.algorithms.sgm.config import Config, Tuning, with_tuning
from jstarid.algorithms.sgm.diagnostics import Diagnostics, search_diagnostics, subgraph_diagnostics
from jstarid.algorithms.sgm.extensions import (
    confirmed_by_the_frame,
    finishing_stage,
    name_at_fitted_focal,
    next_main_stars,
    search_lost,
    whole_circles_only,
)
from jstarid.algorithms.sgm.graph import searchable_graphs
from jstarid.algorithms.sgm.naming import attitude_from_names, names_from_ranking, names_with_retries
from jstarid.algorithms.sgm.search import advance_search, reject_best, search_outcome, start_search
from jstarid.algorithms.sgm.subgraph import subgraph_search
from jstarid.runtime import coarse_size, release_staging
from jstarid.runtime.padding import MIN_CALL_SIZE
from jstarid.scene import Identification, Scene, pad_with_empty

__all__ = ["Diagnostics", "identify"]

#: the largest pass padded in steps of 4 (:func:`~jstarid.runtime.coarse_size`); larger passes pad
#: to a power of two, where empty scenes would cost more than a compilation saves (docs/design/sgm.md)
PADDED_PASS_LIMIT = 1024


def identify(db, scenes: Scene, config: Config | None = None, *, tuning: Tuning | None = None,
             diagnostics: bool = False, with_attitude: bool = True):
    """Identify the stars of the main star's neighbor circle in every scene.

    Algorithm 1 (You et al. 2022) with names and verification runs on every scene first; then our
    extensions, in order (:mod:`.extensions`): :func:`~.extensions.next_main_stars`,
    :func:`~.extensions.finishing_stage`, :func:`~.extensions.name_at_fitted_focal`,
    :func:`~.extensions.whole_circles_only`, :func:`~.extensions.confirmed_by_the_frame`,
    :func:`~.extensions.search_lost`.

    Args:
        db: :class:`~jstarid.algorithms.sgm.database.Database` (built with the same ``radius_deg``).
        scenes: (B, N) :class:`~jstarid.scene.Scene` from ``db.camera``.
        config: :class:`Config` (its database fields must match ``db``); ``None`` → the paper's
            defaults plus the extensions that are on by default.
        tuning: c and ε_δ (:class:`~jstarid.algorithms.sgm.Tuning`) in place of the config's: scalars,
            or (B,) arrays holding one value (a grid of them runs as one batch through
            :func:`~jstarid.algorithms.sgm.tuning.grid_identifications`); ``None``: the config's.
        diagnostics: also return the per-scene :class:`Diagnostics`.
        with_attitude: also solve Wahba from the identified stars (``Identification.attitude``).

    Returns:
        :class:`~jstarid.scene.Identification`: ``ids`` (B, N) int32 catalog rows of the verified
        detections of the neighbor circle (−1 elsewhere; every id −1 where ``ok`` (B,) is False), or
        with ``diagnostics`` a ``(result, Diagnostics)`` tuple (the diagnostics of the first
        pass). With ``config.finishing.fit_focal`` also ``focal_scale`` (B,), the fitted focal
        length / the camera's (NaN where not fitted).

    Raises:
        ValueError: ``config.radius_deg`` differs from the database's, or ``tuning`` holds several
            values per field.
    """
    config = Config() if config is None else config
    check_scenes(scenes)
    if tuning is not None:
        config = with_tuning(config, tuning)
    if abs(config.radius_deg - db.radius_deg) > 1e-12:
        raise ValueError(f"config.radius_deg={config.radius_deg} but the database was built with "
                         f"r={db.radius_deg}")
    # the paper: Algorithm 1 on every scene, its main star the detection nearest the principal point
    result, diag = _algorithm1(db, scenes, config, with_attitude=with_attitude, diagnostics=diagnostics)
    # ours, in order (module .extensions; each off in Config.paper()), some running Algorithm 1 again
    search = functools.partial(_search_again, db, with_attitude=with_attitude)
    result = next_main_stars(scenes, result, config, search)
    result, laddered, claimed = finishing_stage(db, scenes, result, config, search,
                                                with_attitude=with_attitude)
    result = name_at_fitted_focal(db, scenes, result, laddered, config)
    result = whole_circles_only(db, scenes, result, laddered, config)
    result = confirmed_by_the_frame(db, scenes, result, config)
    result = search_lost(db, scenes, result, claimed, config, with_attitude=with_attitude)
    release_staging()
    return (result, diag) if diagnostics else result


def _algorithm1(db, scenes: Scene, config: Config, *, main_rank: int = 0, with_attitude: bool = True,
                diagnostics: bool = False) -> tuple[Identification, Diagnostics | None]:
    """One pass over checked scenes: Algorithm 1 (or the subgraph search, ``Config.subgraph``), the
    names and their verification, with the ``main_rank``-th detection nearest the principal point
    as the main star. Returns ``(result, diagnostics or None)``.

    The batch runs padded with empty scenes (searched by nobody) to
    :func:`~jstarid.runtime.coarse_size` (16, 64, 256, 1,024 scenes, powers of two above): the retries of
    some scenes (other main stars, other focal lengths) then run the programs the batch's own pass
    compiled, where each new retry size compiled the front end (graphs, windows, naming) again.
    Empty scenes cost little (docs/design/sgm.md, "Coarse sizes for what the data sizes")."""
    b = scenes.batch_size
    size = coarse_size(b, MIN_CALL_SIZE, PADDED_PASS_LIMIT)
    if b and size != b:
        result, diag = _algorithm1(db, pad_with_empty(scenes, size), config, main_rank=main_rank,
                                   with_attitude=with_attitude, diagnostics=diagnostics)
        keep = np.arange(b)  # gathered on the host: no program per (size, b)
        return result[keep], (None if diag is None else jax.tree.map(lambda a: a[:b], diag))
    if config.subgraph.on:
        return _subgraph_pass(db, scenes, config, main_rank=main_rank, with_attitude=with_attitude,
                              diagnostics=diagnostics)
    # lines 1–2: main star I, its neighbor graph G_I (the detections within r), A_I and w_I (MST)
    g, usable = searchable_graphs(db, scenes, config, main_rank=main_rank)
    # lines 3–10: for Δw = Δw₀, Δw₀ + h_Δw, … ≤ Δw_max, the rough search S_I (eq. 1, k-vector), each
    # new J ∈ S_I matched spectrally (eqs. 2–5), J* = argmin δ (eq. 6), until δ_{I,J*} ≤ ε_δ
    state = advance_search(db, g, start_search(db, g, usable, config), config)
    outcome = search_outcome(state, config, g.mask.shape[1])

    def resume(outcome, redo):  # the verification rejected J*: strike it out, lines 3–10 go on
        nonlocal state
        retry = np.zeros(outcome.ok.shape, bool)
        retry[redo] = True
        state = advance_search(db, g, reject_best(state, outcome, redo), config, retry)
        return search_outcome(state, config, g.mask.shape[1])

    # lines 11–12: G_I named through P_{I,J*}; then our verification, whose rejections resume the search
    result, outcome, contested_main = names_with_retries(db, scenes, g, outcome, config, resume)
    if with_attitude:
        result = attitude_from_names(db, scenes, result)
    if not diagnostics:
        return result, None
    return result, search_diagnostics(db, scenes, g, usable, outcome, contested_main)


def _search_again(db, scenes: Scene, config: Config, main_rank: int = 0, *,
                  with_attitude: bool) -> Identification:
    """:func:`_algorithm1` for an extension (:data:`.extensions.Search`): other scenes, settings or
    main star."""
    return _algorithm1(db, scenes, config, main_rank=main_rank, with_attitude=with_attitude)[0]


def _subgraph_pass(db, scenes: Scene, config: Config, *, main_rank: int, with_attitude: bool,
                   diagnostics: bool) -> tuple[Identification, Diagnostics | None]:
    """:func:`_algorithm1` with ``Config.subgraph`` (:mod:`.subgraph`): each scene's ranked accepted
    candidates are named and verified in order (up to ``verify.retries`` more after a rejection), with
    the ``main_rank``-th detection nearest the principal point as the main star (the batch padded
    by :func:`_algorithm1`).
    """
    b = scenes.batch_size
    if not b:
        empty = Identification(ids=jnp.asarray(np.asarray(scenes.valid, np.int32) * 0 - 1),
                               ok=jnp.zeros((0,), bool), attitude=None)
        return empty, None
    g, usable = searchable_graphs(db, scenes, config, main_rank=main_rank)
    ranking = subgraph_search(db, g, usable, config)
    result, outcome = names_from_ranking(db, scenes, g, ranking, config)
    result = Identification(ids=result.ids, ok=result.ok, attitude=None)
    if with_attitude:
        result = attitude_from_names(db, scenes, result)
    if not diagnostics:
        return result, None
    return result, subgraph_diagnostics(db, scenes, g, usable, ranking, outcome, b)
