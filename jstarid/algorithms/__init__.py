"""Algorithm registry: ``get(name)`` returns an algorithm module with the SPEC §4 verbs.

Every algorithm is a subpackage (or module) of :mod:`jstarid.algorithms` exposing ``Config`` (a frozen,
hashable dataclass with the paper's defaults), ``build_database(catalog, camera, config)`` and
``identify(database, scenes, config) -> Identification``. Algorithms never import each other; shared
pieces live in :mod:`jstarid.geometry`.
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

__all__ = ["get", "names", "register"]

# name → module path; imported lazily so that `import jstarid` stays light.
_REGISTRY: dict[str, str] = {
    "oracle": "jstarid.algorithms.oracle",
    "sgm": "jstarid.algorithms.sgm",
    "mlv": "jstarid.algorithms.mlv",
    "rpnet": "jstarid.algorithms.rpnet",
}


def register(name: str, module_path: str) -> None:
    """Register an algorithm module (importable path) under ``name``."""
    _REGISTRY[name] = module_path


def _available(name: str) -> bool:
    return importlib.util.find_spec(_REGISTRY[name]) is not None


def names() -> tuple[str, ...]:
    """Names of the registered algorithms whose modules are present."""
    return tuple(n for n in _REGISTRY if _available(n))


def get(name: str) -> ModuleType:
    """The algorithm module registered as ``name`` (raises ``ValueError`` if unknown)."""
    if name not in _REGISTRY or not _available(name):
        raise ValueError(f"unknown algorithm {name!r}; available: {', '.join(names())}")
    return importlib.import_module(_REGISTRY[name])
