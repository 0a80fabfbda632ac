"""Geometric voting (Kolomenkin, Pollak, Shimshoni & Lindenbaum, "Geometric voting algorithm for
star trackers", IEEE TAES 44(2), 441–456, 2008): a classic baseline.

Every pair of detections asks the catalog's pair table (sorted by angle, searched with a k-vector)
for the star pairs whose angular distance is within ε of its own; each such catalog pair votes for
both of its stars as the identity of both detections. A detection is named after the star with the
most votes; then each pair of named detections whose catalog distance agrees with the measured one
votes for both, and the mutually consistent names are kept (:mod:`.identify`).
"""

from jstarid.algorithms.voting.config import Config, Tuning
from jstarid.algorithms.voting.database import Database, build_database, camera_problem, first_use
from jstarid.algorithms.voting.identify import Diagnostics, identify

__all__ = ["Config", "Database", "Diagnostics", "Tuning", "build_database", "camera_problem", "first_use",
           "identify"]
