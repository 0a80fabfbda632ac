"""The grid algorithm (Padgett & Kreutz-Delgado, "A grid algorithm for autonomous star
identification", IEEE TAES 33(1), 202–213, 1997): a classic baseline.

Each reference star's neighbours, turned so that its nearest neighbour lies along +x, are dropped
onto a g × g grid; the occupied cells are a bit pattern, matched to every catalog star's pattern by
bit overlap (:mod:`.pattern`, :mod:`.identify`).
"""

from jstarid.algorithms.grid.config import Config, Tuning
from jstarid.algorithms.grid.database import Database, build_database
from jstarid.algorithms.grid.identify import Diagnostics, identify

__all__ = ["Config", "Database", "Diagnostics", "Tuning", "build_database", "identify"]
