"""SGM: star identification by spectral graph matching (You et al. 2022, seed 000).

Verbs (SPEC §4): :class:`Config` (Table 1 defaults), :func:`build_database` (neighbor graph + MST
weight per catalog star, sorted by w with a k-vector, cached) and :func:`identify` (Algorithm 1,
batched). Modules: ``config`` (settings), ``graph`` (neighbor graphs, MST), ``database``,
``matching`` (eqs. 2–5), ``search`` (rough search eq. 1 + dynamic Δw search), ``verify`` (post-match
attitude and close-pair check — our addition, on by default), ``identify``.
"""

from jstarid.algorithms.sgm.config import Config
from jstarid.algorithms.sgm.database import Database, build_database
from jstarid.algorithms.sgm.identify import identify

__all__ = ["Config", "Database", "build_database", "identify"]
