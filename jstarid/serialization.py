"""JSON-ready copies of jstarid values, one rule for every writer.

The results files of :mod:`jstarid.experiment` and the databases' cache keys
(:func:`jstarid.algorithms.base.cache_key`) both go through :func:`to_json`; it lives here, below
both, so that the algorithm contract does not import the experiment harness. A change to it changes
every cache key (databases cached on disk are found by key), so it is kept as it is.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path

import jax
import numpy as np

__all__ = ["to_json"]


def to_json(value):
    """A JSON-ready copy of ``value``: dataclasses (configs, cameras) as dicts, NumPy/JAX arrays
    and scalars as lists and numbers, non-finite floats as ``None``, paths as strings."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_json(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [to_json(v) for v in value]
    if isinstance(value, np.ndarray | jax.Array):
        return to_json(np.asarray(value).tolist())
    if isinstance(value, np.generic):
        return to_json(value.item())
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value
