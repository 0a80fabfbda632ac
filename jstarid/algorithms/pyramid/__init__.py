"""The pyramid algorithm (Mortari, Samaan, Bruccoleri & Junkins, "The Pyramid Star Identification
Technique", Navigation 51(3), 171–183, 2004): a classic baseline.

Triples of detections, taken in the pyramid's order, are matched to catalog triangles through
k-vector searches of the catalog's pair angles; a triangle is accepted when a fourth detection
confirms it (its three angles to the triangle's stars match a catalog star's) and no other
candidate triangle of the triple is confirmed (:mod:`.identify`).
"""

from jstarid.algorithms.pyramid.config import Config, Tuning
from jstarid.algorithms.pyramid.database import Database, build_database, camera_problem, first_use
from jstarid.algorithms.pyramid.identify import Diagnostics, identify

__all__ = ["Config", "Database", "Diagnostics", "Tuning", "build_database", "camera_problem", "first_use",
           "identify"]
