"""SGM: star identification by spectral graph matching (You et al. 2022).

Verbs (:mod:`jstarid.algorithms.base`): :class:`Config` (Table 1 defaults; each extension a group of
its own: :class:`Screen`, :class:`Subgraph`, :class:`Verify`, :class:`Ladder`, with the search's
work in :class:`Matching`; ``Config.paper()`` the paper's algorithm alone), :func:`build_database`
(neighbor graph + MST weight per catalog star, sorted by w with a k-vector, cached) and
:func:`identify` (Algorithm 1, batched, then our extensions). Modules, in the order a scene meets them:

- ``identify``: the entry, Algorithm 1's pass followed by the extension steps;
- ``graph``: neighbor graphs and their MST weight (image graphs of a batch: ``searchable_graphs``);
- ``search``: rough search (eq. 1, k-vector) and the dynamic Δw search, with ``bound`` (lower bounds
  on δ that prune candidates) and ``screen`` (the triangle screen; ours), ``matching`` (eqs. 2–5);
- ``naming``: names from the match, the leftover naming and the verification (``verify``: our
  post-match attitude and close-pair check, on by default);
- ``extensions``: next main stars, the finishing stage, naming under the fitted focal length,
  whole circles only;
- ``subgraph``: the magnitude-robust search (``Config.subgraph.on``) in place of the rough search;
- ``diagnostics``: the per-scene internals; ``config``, ``database``, ``tuning`` (c × ε_δ grids);
- ``reference``: the plain NumPy Algorithm 1, an independent reference for tests and benchmarks
  (``identify`` never calls it).
"""

from jstarid.algorithms.sgm.config import Config, Ladder, Matching, Screen, Subgraph, Tuning, Verify
from jstarid.algorithms.sgm.database import Database, build_database, camera_problem, first_use
from jstarid.algorithms.sgm.identify import Diagnostics, identify
from jstarid.algorithms.sgm.tuning import identify_grid

__all__ = ["Config", "Database", "Diagnostics", "Ladder", "Matching", "Screen", "Subgraph", "Tuning",
           "Verify", "build_database", "camera_problem", "first_use", "identify", "identify_grid"]
