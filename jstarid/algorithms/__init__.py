"""Algorithm registry: ``get(name)`` returns an algorithm module that keeps the contract of
:mod:`jstarid.algorithms.base` (``Config``, ``Tuning``, ``Database``, ``Diagnostics``,
``build_database``, ``identify``). Algorithms never import each other; shared pieces live in
:mod:`jstarid.geometry` and :mod:`jstarid.algorithms.base`.
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

__all__ = ["BASELINES", "get", "names", "register", "seed_names"]

# name → module path; imported lazily so that `import jstarid` stays light.
_REGISTRY: dict[str, str] = {
    "oracle": "jstarid.algorithms.oracle",
    "sgm": "jstarid.algorithms.sgm",
    "mlv": "jstarid.algorithms.mlv",
    "rpnet": "jstarid.algorithms.rpnet",
    "voting": "jstarid.algorithms.voting",
    "pyramid": "jstarid.algorithms.pyramid",
    "grid": "jstarid.algorithms.grid",
}

#: Classic methods the seed algorithms are measured against (run on request: ``--baselines``).
BASELINES = ("pyramid", "voting", "grid")


def register(name: str, module_path: str) -> None:
    """Register an algorithm module (importable path) under ``name``; :func:`get` checks it."""
    _REGISTRY[name] = module_path


def _available(name: str) -> bool:
    return importlib.util.find_spec(_REGISTRY[name]) is not None


def names() -> tuple[str, ...]:
    """Names of the registered algorithms whose modules are present."""
    return tuple(n for n in _REGISTRY if _available(n))


def seed_names() -> tuple[str, ...]:
    """The algorithms ``jstarid demo`` runs by default: every registered one but the oracle (a test
    reference) and the :data:`BASELINES`."""
    return tuple(n for n in names() if n != "oracle" and n not in BASELINES)


def get(name: str) -> ModuleType:
    """The algorithm module registered as ``name``.

    Raises:
        ValueError: ``name`` is not registered.
        TypeError: the module does not keep the contract (:func:`.base.check_algorithm`).
    """
    if name not in _REGISTRY or not _available(name):
        raise ValueError(f"unknown algorithm {name!r}; available: {', '.join(names())}")
    from jstarid.algorithms.base import check_algorithm

    return check_algorithm(importlib.import_module(_REGISTRY[name]), name)
