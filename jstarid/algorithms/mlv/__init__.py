"""Multilayer voting star identification with SVD triangle features (MLV; Sensors 2021, 21, 3084).

Modules (one concept each): :mod:`.config` (parameters, :class:`Tuning`), :mod:`.features`
(singular values, eqs. 1–4), :mod:`.database` (onboard database, §2.2), :mod:`.voting` (initial
match, eq. 7 and Fig. 3), :mod:`.verify` (pair-angle verification, eq. 8) and :mod:`.identify`
(Algorithm 1, batched).

Usage::

    mlv = js.algorithms.get("mlv")
    cfg = mlv.Config()                      # mlv.Config.paper(): without our extensions
    db = mlv.build_database(catalog, camera, cfg)
    result = mlv.identify(db, scenes, cfg)
    result, diag = mlv.identify(db, scenes, cfg, diagnostics=True)
"""

from jstarid.algorithms.mlv.config import Config, Tuning
from jstarid.algorithms.mlv.database import Database, build_database, first_use, window_counts
from jstarid.algorithms.mlv.identify import (
    Buffers,
    Diagnostics,
    candidate_buffers,
    default_pool,
    identify,
    identify_grid,
)

__all__ = ["Buffers", "Config", "Database", "Diagnostics", "Tuning", "build_database",
           "candidate_buffers", "default_pool", "first_use", "identify", "identify_grid", "window_counts"]
