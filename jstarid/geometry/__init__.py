"""Shared geometric building blocks (angles, k-vector range search, full-precision products)."""

from jstarid.geometry import precise
from jstarid.geometry.angles import angle_between, pairwise_angles
from jstarid.geometry.kvector import KVector, build_kvector, range_search

__all__ = ["KVector", "angle_between", "build_kvector", "pairwise_angles", "precise", "range_search"]
