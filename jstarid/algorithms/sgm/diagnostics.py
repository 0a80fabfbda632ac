"""Per-scene internals of :func:`~jstarid.algorithms.sgm.identify` (``diagnostics=True``).

One :class:`Diagnostics` per pass, from the search it ran: :func:`search_diagnostics` for
Algorithm 1's Δw search (:mod:`.search`), :func:`subgraph_diagnostics` for the subgraph search
(``Config.subgraph``, :mod:`.subgraph`). Host NumPy throughout; nothing here changes a name.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jstarid.algorithms.sgm.graph import ImageGraph
from jstarid.algorithms.sgm.search import SearchOutcome
from jstarid.algorithms.sgm.subgraph import Ranking
from jstarid.scene import Scene

__all__ = ["Diagnostics", "search_diagnostics", "subgraph_diagnostics"]


class Diagnostics(NamedTuple):
    """Per-scene internals of :func:`~jstarid.algorithms.sgm.identify` (host NumPy arrays, batch
    axis first).

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


def search_diagnostics(db, scenes: Scene, g: ImageGraph, usable: np.ndarray, outcome: SearchOutcome,
                       main_contested: np.ndarray) -> Diagnostics:
    """:class:`Diagnostics` of a pass of Algorithm 1's search.

    Args:
        db: :class:`~.database.Database`. scenes: the (B, N) scenes searched.
        g: their NumPy :class:`~.graph.ImageGraph`. usable: (B,) bool scenes searched.
        outcome: the last :class:`~.search.SearchOutcome` (after the verification's retries).
        main_contested: (B,) bool from :func:`.naming.names_with_retries`.
    """
    matched, pruned = outcome.n_matched, outcome.n_pruned
    return Diagnostics(
        n_candidates=(matched + pruned).astype(np.int32),
        overflow=g.overflow | np.asarray(scenes.overflow), n_matched=matched,
        n_pruned=pruned, n_rejected=outcome.n_rejected, n_i=g.n, w_i=g.w, main=g.main,
        usable=usable, match_ok=outcome.ok, best=outcome.best, best_main=_best_main(db, outcome),
        error=outcome.error, level=outcome.level, main_contested=main_contested)


def subgraph_diagnostics(db, scenes: Scene, g: ImageGraph, usable: np.ndarray, ranking: Ranking,
                         outcome: SearchOutcome, n: int) -> Diagnostics:
    """:class:`Diagnostics` of the first ``n`` rows of a subgraph search (``level`` 0 when accepted).

    Args:
        db: :class:`~.database.Database`. scenes: the (B, N) scenes searched (padded, B ≥ n).
        g: their NumPy :class:`~.graph.ImageGraph`. usable: (B,) bool scenes searched.
        ranking: :func:`.subgraph.subgraph_search`'s :class:`~.subgraph.Ranking`. outcome: the
            accepted candidates' :class:`~.search.SearchOutcome`. n: the scenes of the caller's batch.
    """
    best_err = np.min(ranking.error, axis=1)
    at = np.arange(outcome.ok.size)
    return Diagnostics(
        n_candidates=np.sum(ranking.rows >= 0, axis=1).astype(np.int32)[:n],
        overflow=(g.overflow | np.asarray(scenes.overflow))[:n], n_matched=outcome.n_matched[:n],
        n_pruned=outcome.n_pruned[:n], n_rejected=outcome.n_rejected[:n], n_i=g.n[:n], w_i=g.w[:n],
        main=g.main[:n], usable=usable[:n], match_ok=outcome.ok[:n], best=outcome.best[:n],
        best_main=_best_main(db, outcome)[:n],
        error=np.where(outcome.ok, outcome.error, best_err)[:n], level=outcome.level[:n],
        main_contested=np.zeros(n, bool),
        cut=(outcome.ok & ranking.cut[at, np.maximum(outcome.rank, 0)])[:n])


def _best_main(db, outcome: SearchOutcome) -> np.ndarray:
    """(B,) catalog main star of each accepted database graph (−1 where none was accepted)."""
    return np.where(outcome.ok, db.main[np.clip(outcome.best, 0, None)], -1)
