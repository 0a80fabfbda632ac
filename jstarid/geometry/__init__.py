"""Shared geometric building blocks (k-vector range search, …) reused by every algorithm."""

from jstarid.geometry.kvector import KVector, build_kvector, range_search

__all__ = ["KVector", "build_kvector", "range_search"]
