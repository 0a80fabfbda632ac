"""SGM: star identification by spectral graph matching (You et al. 2022).

Verbs (:mod:`jstarid.algorithms.base`): :class:`Config` (Table 1 defaults; ``Config.paper()`` the
paper's algorithm alone), :func:`build_database` (neighbor graph + MST weight per catalog star,
sorted by w with a k-vector, cached) and :func:`identify` (Algorithm 1, batched). Modules:
``config`` (settings), ``graph`` (neighbor graphs, MST), ``database``, ``matching`` (eqs. 2–5),
``search`` (rough search eq. 1 + dynamic Δw search), ``verify`` (post-match attitude and close-pair
check — our addition, on by default), ``identify``, ``tuning`` (c × ε_δ grids).
"""

from jstarid.algorithms.sgm.config import Config, Tuning
from jstarid.algorithms.sgm.database import Database, build_database, camera_problem, first_use
from jstarid.algorithms.sgm.identify import Diagnostics, identify
from jstarid.algorithms.sgm.tuning import identify_grid

__all__ = ["Config", "Database", "Diagnostics", "Tuning", "build_database", "camera_problem", "first_use",
           "identify", "identify_grid"]
