"""The algorithm contract: what every registered star identifier provides, and its optional hooks.

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

``build_database(catalog, camera, config=None, *, use_cache=True, progress=True) -> Database``
    Built once per (catalog, camera, database fields) and cached on disk under
    :func:`jstarid.catalog.cache_dir` (:func:`jstarid.catalog.load_or_build`); ``use_cache=False``
    neither reads nor writes the cache (an algorithm that caches nothing accepts and ignores it).

``identify(database, scenes, config=None, *, tuning=None, diagnostics=False)``
    Returns an :class:`~jstarid.scene.Identification` for the (B, N) scene batch, or
    ``(Identification, Diagnostics)`` with ``diagnostics=True``. ``config=None`` means ``Config()``
    (or, where the database fixes settings, the database's config); ``tuning=None`` means
    ``config.tuning()``, and a ``Tuning`` given replaces the config's tolerances. A failure is reported as
    ``ok = False`` with every id −1; it is always preferred over a wrong name.

**The finishing stage.** An algorithm whose features are angles ends ``identify`` with
:func:`jstarid.finishing.finish` (the focal-length ladder and the camera check, written once),
configured by ``Config.finishing`` (a :class:`jstarid.finishing.Finishing`; ``Finishing.off()`` in
``Config.paper()``). MLV, RpNet and SGM do; ``docs/adding_an_algorithm.md`` §4 shows how.

**Optional hooks.** Each is declared here with a default (:data:`HOOKS`); the engine and the CLI
read every one through the function of this module named with it below (never from the algorithm
module itself), so an algorithm that declares none of them still runs everywhere. Module-level:

``first_use(catalog, camera, config) -> tuple[str, float] | None``
    What ``build_database`` will build first for these settings and about how long it takes on a
    2-core CPU (text, seconds), or ``None`` when it is cached, so a command can say so up front.
    Default: ``None`` (nothing to build ahead). Read with :func:`first_use`.
``camera_problem(camera, config, catalog=None) -> str | None``
    One line saying why the algorithm cannot work on this camera and catalog (the engine and the
    CLI stop before building anything), or ``None``. Default: ``None``. Read with
    :func:`camera_problem`.
``identify_grid(database, scenes, configs) -> list[Identification]``
    ``identify`` with each config of a parameter grid, in one batch (MLV: each config's traced
    ``Tuning`` on its own copy of the scenes); ``ValueError`` for a grid it cannot batch. Default:
    one ``identify`` call per config. Read with :func:`identify_grid`.
``PRESETS: Mapping[str, Mapping[str, Any]]``
    Named settings of the default config, ``{name: {field: value}}``; the first is what a sweep
    uses when none is named (RpNet: its ``"quick"`` and ``"table3"`` networks). Default: ``{}``.
    Read with :func:`presets`, applied by :func:`default_config`.
``REPORTED: Mapping[str, Sequence]``
    ``{field: values}``: the settings a row of the algorithm is reported at (cedar: its default
    ``match_max_error`` and a tuned one). Default: ``{}``. Read with :func:`reported`.

On ``Config``:

``Config.for_camera(camera, **overrides) -> Config`` (classmethod)
    The defaults for ``camera`` (tolerances that follow its pixel scale; the published values on the
    papers' cameras). Default: ``Config(**overrides)``. Read with :func:`config_for_camera`.
``Config.FRAME_SETTINGS: dict``
    ``{field: value}`` for detections extracted from real frames, which do not stop at the catalog's
    magnitude limit (SGM: ``{"subgraph.on": True}``, its subgraph search; a nested config's field by
    its dotted name, :func:`jstarid.config_tree.with_fields`). Default: ``{}``. Read with
    :func:`frame_settings`.
``Config.radius_deg: float``
    The neighbor circle (deg) the ``"sgm"`` criterion scores this config's results on (SGM: its r).
    Default: 6.0, the criterion's own. Read with :func:`scoring_radius_deg`.

On ``Database``:

``Database.info_dict() -> dict``
    How the database was built: ``"cache_path"`` (str, its cache file; ``""`` when not cached) and
    any other entries. Default: ``{}``. Read with :func:`database_info`.
``Database.FIRST_COMPILE_SECONDS: float`` (class attribute)
    About how long the first ``identify`` of a process compiles its kernels on 2 CPU cores (s) when
    no program is kept on disk yet (SGM: one kernel per graph-size bucket, ≈ 100 s). Default: 20.0.
    Read with :func:`first_compile_seconds`.

:func:`default_config` puts ``Config``, ``for_camera``, ``PRESETS`` and ``FRAME_SETTINGS`` together:
the config a sweep or a command uses when none is given. :func:`declares` says whether an algorithm
gives a hook itself (a command that says "already built" needs to know that ``first_use`` answered).

:func:`check_algorithm` verifies that a module offers the required names and that the hooks it
declares have the declared kind; the registry runs it on :func:`jstarid.algorithms.get`, and
``tests/algorithms/test_contract.py`` runs the behavioural checks over every registered name.
``docs/adding_an_algorithm.md`` walks through adding one.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import numbers
from collections.abc import Mapping, Sequence
from types import ModuleType
from typing import Any, NamedTuple, Protocol, runtime_checkable

import jax
import numpy as np

from jstarid.config_tree import differences, with_fields
from jstarid.scene import Identification, Scene
from jstarid.serialization import to_json

__all__ = ["Algorithm", "DiagnosticsFields", "HOOKS", "Hook", "REQUIRED", "cache_key", "camera_problem",
           "check_algorithm", "check_scenes", "config_for_camera", "database_info", "declares",
           "default_config", "first_compile_seconds", "first_use", "frame_settings", "identify_grid",
           "paper_algorithm", "presets", "reported", "scoring_radius_deg", "tolerance_rad"]

REQUIRED = ("Config", "Tuning", "Database", "Diagnostics", "build_database", "identify")


class Hook(NamedTuple):
    """Where an algorithm declares an optional hook and what kind of thing it is.

    Attributes:
        owner: ``"module"``, ``"Config"`` or ``"Database"``: the algorithm module itself or one of
            its classes.
        kind: ``"function"`` (a function, classmethod or method), ``"mapping"`` or ``"number"``.
    """

    owner: str
    kind: str


#: Every optional hook (module docstring: signature, meaning, default, reader).
HOOKS: dict[str, Hook] = {
    "first_use": Hook("module", "function"),
    "camera_problem": Hook("module", "function"),
    "identify_grid": Hook("module", "function"),
    "PRESETS": Hook("module", "mapping"),
    "REPORTED": Hook("module", "mapping"),
    "for_camera": Hook("Config", "function"),
    "FRAME_SETTINGS": Hook("Config", "mapping"),
    "radius_deg": Hook("Config", "number"),
    "info_dict": Hook("Database", "function"),
    "FIRST_COMPILE_SECONDS": Hook("Database", "number"),
}

#: The ``"sgm"`` criterion's neighbor circle (deg) for a config without ``radius_deg``
#: (:func:`jstarid.metrics.scene_outcomes`' own default).
DEFAULT_RADIUS_DEG = 6.0
#: First compilation (s, 2 CPU cores) of an algorithm whose ``Database`` does not say: measured for
#: MLV, RpNet and the baselines, each well under it.
DEFAULT_FIRST_COMPILE_SECONDS = 20.0

_ABSENT = object()  # an optional hook the algorithm does not declare


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

    def build_database(self, catalog, camera, config=None, *, use_cache: bool = True,
                       progress: bool = True) -> Any: ...

    def identify(self, database, scenes: Scene, config=None, *, tuning=None,
                 diagnostics: bool = False) -> Identification | tuple[Identification, Any]: ...


def check_algorithm(module: ModuleType, name: str | None = None) -> ModuleType:
    """Check that ``module`` offers the contract's names and signatures, and hooks of their kind.

    Args:
        module: the algorithm module.
        name: its registry name (for the error message).

    Returns:
        ``module`` unchanged.

    Raises:
        TypeError: a required name is missing, ``Config`` lacks ``paper``/``tuning``/
            ``database_fields``, ``Diagnostics`` does not start with ``n_candidates, overflow``,
            ``identify``/``build_database`` lack the contract's parameters, or a declared hook is
            not of its kind (:data:`HOOKS`).
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
    for fn, params in (("identify", ("config", "tuning", "diagnostics")),
                       ("build_database", ("config", "use_cache", "progress"))):
        have = inspect.signature(getattr(module, fn)).parameters
        lacking = [p for p in params if p not in have]
        if lacking:
            raise TypeError(f"algorithm {label!r}: {fn} lacks parameter(s) {', '.join(lacking)}")
    for hook, (owner, kind) in HOOKS.items():
        value = _own(module if owner == "module" else getattr(module, owner), hook)
        if value is _ABSENT:
            continue
        fits = {"function": callable, "mapping": lambda v: isinstance(v, Mapping),
                "number": lambda v: isinstance(v, numbers.Real)}[kind](value)
        if not fits:
            where = hook if owner == "module" else f"{owner}.{hook}"
            raise TypeError(f"algorithm {label!r}: {where} must be a {kind}, got {type(value).__name__}")
    for preset, settings in _declared_mapping(module, "PRESETS").items():
        if not isinstance(settings, Mapping):
            raise TypeError(f"algorithm {label!r}: PRESETS[{preset!r}] must map Config fields to values")
    return module


def _own(owner, name: str):
    """The hook ``name`` as ``owner`` (a module, class or instance) declares it, else ``_ABSENT``.

    The one place hooks are looked up by name: everything else calls the readers below.
    """
    return getattr(owner, name, _ABSENT)


def declares(module: ModuleType, hook: str) -> bool:
    """Whether ``module`` gives the optional ``hook`` (a name of :data:`HOOKS`) itself rather than
    leaving it to the contract's default; a config field counts for a ``Config`` hook.

    Raises:
        KeyError: ``hook`` is not an optional hook of the contract.
    """
    owner = HOOKS[hook].owner
    if owner == "module":
        return _own(module, hook) is not _ABSENT
    cls = getattr(module, owner)
    fields = {f.name for f in dataclasses.fields(cls)} if dataclasses.is_dataclass(cls) else set()
    return hook in fields or _own(cls, hook) is not _ABSENT


def first_use(module: ModuleType, catalog, camera, config) -> tuple[str, float] | None:
    """``(text, seconds)``: what ``module.build_database`` builds first for these settings and about
    how long it takes on 2 CPU cores (s); ``None`` when it is cached or the algorithm does not say."""
    fn = _own(module, "first_use")
    return None if fn is _ABSENT else fn(catalog, camera, config)


def camera_problem(module: ModuleType, camera, config, catalog=None) -> str | None:
    """One line saying why ``module`` cannot work on ``camera`` and ``catalog`` with ``config``, or
    ``None`` (also when the algorithm does not say)."""
    fn = _own(module, "camera_problem")
    return None if fn is _ABSENT else fn(camera, config, catalog)


def identify_grid(module: ModuleType, database, scenes: Scene, configs: Sequence) -> list[Identification]:
    """``module.identify`` of ``scenes`` with each of ``configs`` on one ``database``: the algorithm's
    ``identify_grid`` (one batch) where it has one, else one ``identify`` call per config.

    Raises:
        ValueError: the algorithm's ``identify_grid`` cannot batch these configs (the caller may
            then call ``identify`` once per config).
    """
    fn = _own(module, "identify_grid")
    if fn is _ABSENT:
        return [module.identify(database, scenes, config) for config in configs]
    return list(fn(database, scenes, configs))


def reported(module: ModuleType) -> dict[str, Sequence]:
    """``{field: values}``: the settings a row of ``module`` is reported at (``{}``: its config alone)."""
    return dict(_declared_mapping(module, "REPORTED"))


def presets(module: ModuleType) -> dict[str, dict]:
    """``{name: {field: value}}``: the named settings of ``module``'s default config, the default first."""
    return {name: dict(settings) for name, settings in _declared_mapping(module, "PRESETS").items()}


def config_for_camera(module: ModuleType, camera, **overrides):
    """``module.Config.for_camera(camera, **overrides)``, or ``Config(**overrides)`` for an algorithm
    whose defaults do not depend on the camera."""
    fn = _own(module.Config, "for_camera")
    return module.Config(**overrides) if fn is _ABSENT else fn(camera, **overrides)


def frame_settings(module: ModuleType) -> dict:
    """``{field: value}`` that ``module``'s config takes for detections extracted from real frames."""
    return dict(_declared_mapping(module.Config, "FRAME_SETTINGS"))


def default_config(module: ModuleType, camera=None, *, preset: str | None = None, frames: bool = False):
    """The config a sweep or a command uses when none is given.

    ``Config()`` with the settings of a named preset (``PRESETS``; default: the first), for
    ``camera`` where one is given (``Config.for_camera``), and with ``Config.FRAME_SETTINGS`` for
    detections from real frames.

    Args:
        module: the algorithm module.
        camera: the :class:`~jstarid.Camera` the config is for (``None``: the published defaults).
        preset: a name of the algorithm's ``PRESETS``; ignored by an algorithm that has none, so
            one name can be given for every algorithm of a sweep (``None``: the first preset).
        frames: the config for detections extracted from real frames.

    Raises:
        ValueError: ``preset`` is not one of the algorithm's presets.
    """
    named = presets(module)
    if preset is not None and named and preset not in named:
        raise ValueError(f"{module.__name__.rpartition('.')[2]} has no preset {preset!r}; presets: "
                         f"{', '.join(named)}")
    overrides = named[preset] if preset in named else next(iter(named.values()), {})
    config = module.Config(**overrides) if camera is None else config_for_camera(module, camera, **overrides)
    settings = frame_settings(module) if frames else {}
    return with_fields(config, settings) if settings else config


def paper_algorithm(config):
    """``config`` with the settings ``Config.paper()`` changes from ``Config()`` — the paper's
    algorithm, our extensions off — and every other field as given (what a camera or a preset
    chose: tolerances, RpNet's network)."""
    cls = type(config)
    return with_fields(config, differences(cls(), cls.paper()))


def scoring_radius_deg(config) -> float:
    """The neighbor circle (deg) the ``"sgm"`` criterion scores ``config``'s results on: its own
    ``radius_deg`` where it has one, else :data:`DEFAULT_RADIUS_DEG`."""
    radius = _own(config, "radius_deg")
    return DEFAULT_RADIUS_DEG if radius is _ABSENT else float(radius)


def database_info(database) -> dict:
    """How ``database`` was built (``"cache_path"``: its cache file, ``""`` when not cached; other
    entries as the algorithm says); ``{}`` when its ``Database`` does not say."""
    fn = _own(database, "info_dict")
    return {} if fn is _ABSENT else dict(fn())


def first_compile_seconds(module: ModuleType) -> float:
    """About how long ``module``'s first ``identify`` compiles on 2 CPU cores (s) with no program on
    disk yet: its ``Database.FIRST_COMPILE_SECONDS``, else :data:`DEFAULT_FIRST_COMPILE_SECONDS`."""
    seconds = _own(module.Database, "FIRST_COMPILE_SECONDS")
    return DEFAULT_FIRST_COMPILE_SECONDS if seconds is _ABSENT else float(seconds)


def _declared_mapping(owner, name: str) -> Mapping:
    value = _own(owner, name)
    return {} if value is _ABSENT or value is None else value


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
