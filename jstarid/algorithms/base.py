"""The algorithm contract: what every registered star identifier provides.

An algorithm is a module (usually a subpackage of :mod:`jstarid.algorithms`) exposing:

``Config``
    A frozen, hashable, validated dataclass. ``Config()`` is the algorithm as jstarid runs it by
    default (the paper's parameters plus any documented extensions); ``Config.paper()`` is *the
    paper's algorithm with the paper's parameters and none of our extensions*.
    ``Config.database_fields()`` returns the settings that shape the database (its cache key), and
    ``Config.tuning()`` the traced tolerances (see ``Tuning``).

``Tuning``
    A NamedTuple of the tolerances a parameter grid may sweep without recompiling. Its leaves are
    traced arrays, so a grid of values is a batch axis served by one compilation.

``Database``
    What ``identify`` needs, registered as a JAX pytree (arrays are leaves, settings are static
    metadata), with ``cache_key()`` (:func:`cache_key`: one rule for every algorithm).

``Diagnostics``
    A NamedTuple of per-scene internals (batch axis first) that starts with the fields of
    :class:`DiagnosticsFields`: ``n_candidates`` (B,) int32 and ``overflow`` (B,) bool.

``build_database(catalog, camera, config=None, *, progress=True) -> Database``
    Built once per (catalog, camera, database fields) and cached on disk under
    :func:`jstarid.catalog.cache_dir`.

``identify(database, scenes, config=None, *, diagnostics=False)``
    Returns an :class:`~jstarid.scene.Identification` for the (B, N) scene batch, or
    ``(Identification, Diagnostics)`` with ``diagnostics=True``. ``config=None`` means ``Config()``
    (or, where the database fixes settings, the database's config). A failure is reported as
    ``ok = False`` with every id −1; it is always preferred over a wrong name.

Optional: ``first_use(catalog, camera, config) -> str | None`` says what ``build_database`` will
    build and about how long it takes (``None`` when it is cached), so a command can say so up
    front; ``camera_problem(camera, config, catalog=None) -> str | None`` says in one line why the
    algorithm cannot work on a camera and catalog (the engine and the CLI stop before building
    anything);
    ``identify_grid(database, scenes, configs) -> list[Identification]`` runs a parameter
    grid in one batch (:func:`jstarid.engine.grid` uses it; without it, one call per config).

:func:`check_algorithm` verifies that a module offers these names; the registry runs it on
:func:`jstarid.algorithms.get`, and ``tests/algorithms/test_contract.py`` runs the behavioural
checks over every registered name. ``docs/adding_an_algorithm.md`` walks through adding one.
"""

from __future__ import annotations

import hashlib
import inspect
import json
from collections.abc import Mapping
from types import ModuleType
from typing import Any, NamedTuple, Protocol, runtime_checkable

import jax
import numpy as np

from jstarid.experiment import to_json
from jstarid.scene import Identification, Scene

__all__ = ["Algorithm", "DiagnosticsFields", "REQUIRED", "cache_key", "check_algorithm",
           "check_scenes", "tolerance_rad"]

REQUIRED = ("Config", "Tuning", "Database", "Diagnostics", "build_database", "identify")


class DiagnosticsFields(NamedTuple):
    """The fields every algorithm's ``Diagnostics`` starts with (batch axis first).

    Attributes:
        n_candidates: (B,) int32 candidates the algorithm examined for each scene (database
            triangles, graphs or pairs; what counts is stated in each algorithm's docstring).
        overflow: (B,) bool, some fixed-capacity buffer was exceeded for the scene (the scene's
            own, ``Scene.overflow``, or one of the algorithm's), so its result may be incomplete.
    """

    n_candidates: jax.Array
    overflow: jax.Array


@runtime_checkable
class Algorithm(Protocol):
    """The module-level interface of a registered algorithm (checked by :func:`check_algorithm`)."""

    Config: type
    Tuning: type
    Database: type
    Diagnostics: type

    def build_database(self, catalog, camera, config=None, *, progress: bool = True) -> Any: ...

    def identify(self, database, scenes: Scene, config=None, *,
                 diagnostics: bool = False) -> Identification | tuple[Identification, Any]: ...


def check_algorithm(module: ModuleType, name: str | None = None) -> ModuleType:
    """Check that ``module`` offers the contract's names and signatures.

    Args:
        module: the algorithm module.
        name: its registry name (for the error message).

    Returns:
        ``module`` unchanged.

    Raises:
        TypeError: a required name is missing, ``Config`` lacks ``paper``/``tuning``/
            ``database_fields``, ``Diagnostics`` does not start with ``n_candidates, overflow``,
            or ``identify``/``build_database`` lack the contract's parameters.
    """
    label = name or module.__name__
    missing = [n for n in REQUIRED if not hasattr(module, n)]
    if missing:
        raise TypeError(f"algorithm {label!r} lacks {', '.join(missing)} (see jstarid.algorithms.base)")
    for method in ("paper", "tuning", "database_fields"):
        if not callable(getattr(module.Config, method, None)):
            raise TypeError(f"algorithm {label!r}: Config has no {method}()")
    fields = getattr(module.Diagnostics, "_fields", ())
    if tuple(fields[:2]) != DiagnosticsFields._fields:
        raise TypeError(f"algorithm {label!r}: Diagnostics must be a NamedTuple starting with "
                        f"{DiagnosticsFields._fields}, got {tuple(fields[:2])}")
    if not callable(getattr(module.Database, "cache_key", None)):
        raise TypeError(f"algorithm {label!r}: Database has no cache_key()")
    for fn, params in (("identify", ("config", "diagnostics")), ("build_database", ("config", "progress"))):
        have = inspect.signature(getattr(module, fn)).parameters
        lacking = [p for p in params if p not in have]
        if lacking:
            raise TypeError(f"algorithm {label!r}: {fn} lacks parameter(s) {', '.join(lacking)}")
    return module


def cache_key(algorithm: str, version: int, catalog, camera, fields: Mapping) -> str:
    """The one cache-key rule of every algorithm's database.

    Args:
        algorithm: the registry name (``"sgm"``, ``"mlv"``, …).
        version: the algorithm's database format; bump it when stored arrays change meaning.
        catalog: the :class:`~jstarid.catalog.Catalog` (its ``fingerprint``), or ``None``.
        camera: the :class:`~jstarid.camera.Camera` (every field but its lens distortion, which is
            undone before any algorithm sees a centroid), or ``None`` when the database does not
            depend on it.
        fields: the settings that shape the database (``Config.database_fields()``).

    Returns:
        20 hex digits of the SHA-256 of the canonical JSON of all of the above.
    """
    camera_fields = None if camera is None else to_json(camera.database_fields())
    payload = {"algorithm": algorithm, "version": int(version),
               "catalog": None if catalog is None else catalog.fingerprint,
               "camera": camera_fields, "fields": to_json(dict(fields))}
    text = json.dumps(payload, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def check_scenes(scenes: Scene) -> None:
    """Reject scene batches no algorithm can read, with a clear message (host-side, before jit).

    Raises:
        TypeError: ``scenes`` is not a :class:`~jstarid.scene.Scene`.
        ValueError: inconsistent shapes, an empty capacity, or NaN/inf centroids of valid detections.
    """
    if not isinstance(scenes, Scene):
        raise TypeError(f"identify expects a jstarid Scene batch, got {type(scenes).__name__}; "
                        "pack centroids with js.scenes_from_centroids")
    b, n = np.shape(scenes.valid) if np.ndim(scenes.valid) == 2 else (None, None)
    if b is None or np.shape(scenes.xy) != (b, n, 2) or np.shape(scenes.mag) != (b, n):
        raise ValueError(f"inconsistent Scene shapes: xy {np.shape(scenes.xy)}, mag "
                         f"{np.shape(scenes.mag)}, valid {np.shape(scenes.valid)}; expected (B, N, 2), "
                         "(B, N), (B, N)")
    if n < 1:
        raise ValueError("scenes have capacity 0")
    xy, valid = np.asarray(scenes.xy), np.asarray(scenes.valid)
    if not np.all(np.isfinite(xy[valid])):
        raise ValueError("scenes hold NaN or inf centroids among valid detections")



def tolerance_rad(eps_px, batch_size: int, camera) -> np.ndarray:
    """A tolerance given in pixels at the focal length (a scalar or one per scene) as (B,) float32
    radians, for algorithms whose ``Tuning`` holds ``eps_px``.

    Raises:
        ValueError: a tolerance that is not positive and finite.
    """
    eps_px = np.broadcast_to(np.asarray(eps_px, np.float32), (batch_size,))
    if not np.all(np.isfinite(eps_px) & (eps_px > 0)):
        raise ValueError("eps_px must be positive and finite")
    return eps_px / np.float32(camera.f_px)
