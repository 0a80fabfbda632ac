"""What a sweep runs: algorithms, each with a config and a label, and parameter grids of them.

An :class:`Entry` is one row group of the table: a registered algorithm, its config and a label.
:func:`entries` turns names (``"mlv"``) into entries with each algorithm's default config;
:func:`grid` expands one algorithm over a product of config values. Entries of one grid share a
``group``; the engine runs a group through the algorithm's ``identify_grid`` when it has one (one
batch for every grid point: MLV's traced tolerances are per-scene arrays) and otherwise as
successive ``identify`` calls, which share one compilation where the varied fields are the
algorithm's traced ``Tuning``. Every optional hook is read through :mod:`jstarid.algorithms.base`:
nothing here knows an algorithm by name.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

from jstarid import algorithms
from jstarid.algorithms import base
from jstarid.config_tree import with_fields

__all__ = ["Entry", "default_config", "entries", "grid"]


class Entry(NamedTuple):
    """One algorithm setting of a sweep.

    Attributes:
        label: its name in tables and figures (unique within a sweep).
        algorithm: registry name (:func:`jstarid.algorithms.names`).
        config: the algorithm's ``Config``.
        group: entries with the same group come from one :func:`grid` (``""``: none).
        setting: the grid's ``(field, value)`` pairs of this entry (columns of the table).
    """

    label: str
    algorithm: str
    config: Any
    group: str = ""
    setting: tuple = ()


def default_config(name: str, *, rpnet_network: str | None = None, camera=None, frames: bool = False):
    """The config a sweep uses when none is given (:func:`jstarid.algorithms.base.default_config`):
    ``Config()``, for ``camera`` where the algorithm has ``Config.for_camera`` and a camera is given
    (tolerances that follow the camera, the published values on the papers' cameras), with the
    settings of a named preset where the algorithm has ``PRESETS``.

    RpNet's presets are its networks: it trains one per camera on first use; ``Config()`` is the
    paper's Table 3 training (about 2 hours on 2 CPU cores), so sweeps default to the ``quick``
    preset (about 5 minutes).

    Args:
        name: registry name.
        rpnet_network: the preset of an algorithm that has presets (RpNet's network: ``"quick"``
            or ``"table3"``); one without presets ignores it (``None``: each algorithm's first
            preset, RpNet's ``"quick"``).
        camera: the :class:`~jstarid.Camera` the config is for (``None``: the published defaults).
        frames: the config for detections extracted from real frames, which do not stop at the
            catalog's magnitude limit: the algorithm's ``Config.FRAME_SETTINGS`` applied (SGM: its
            magnitude-robust ``subgraph`` search; MLV and RpNet have none: they vote on triangles
            and patterns that tolerate missing and extra stars).

    Raises:
        ValueError: an unknown algorithm, or a preset the algorithm does not have.
    """
    return base.default_config(algorithms.get(name), camera, preset=rpnet_network, frames=frames)


def entries(items: Sequence[str | Entry] | str, *, rpnet_network: str | None = None,
            camera=None) -> list[Entry]:
    """Entries from registry names (``"sgm,mlv"`` or a list, each with :func:`default_config` for
    ``camera``), entries or grids.

    Raises:
        ValueError: an unknown algorithm, no algorithm, or a label used twice.
    """
    if isinstance(items, str):
        items = [s.strip() for s in items.split(",") if s.strip()]
    out = []
    for item in items:
        if isinstance(item, Entry):
            algorithms.get(item.algorithm)  # a clear error for an unknown name
            out.append(item)
        elif isinstance(item, list | tuple) and item and all(isinstance(e, Entry) for e in item):
            out.extend(item)
        else:
            out.append(Entry(str(item), str(item), default_config(
                str(item), rpnet_network=rpnet_network, camera=camera)))
    if not out:
        raise ValueError("no algorithm to run")
    labels = [e.label for e in out]
    if len(set(labels)) != len(labels):
        raise ValueError(f"entry labels must be unique, got {labels}")
    return out


def check_camera(items: Sequence[Entry], camera, catalog=None) -> None:
    """Stop before anything is built when an entry's algorithm cannot work on ``camera`` and
    ``catalog`` (default: the camera's detection limit) — its optional
    ``camera_problem(camera, config, catalog)``, e.g. SGM's neighbor circle wider than the frame.

    Raises:
        ValueError: one line naming every entry that cannot work and why.
    """
    problems = []
    for entry in items:
        text = base.camera_problem(algorithms.get(entry.algorithm), camera, entry.config, catalog)
        if text:
            problems.append(f"{entry.label}: {text}")
    if problems:
        raise ValueError("; ".join(dict.fromkeys(problems)))


def grid(algorithm: str, config=None, *, label: str | None = None, camera=None,
         **values: Sequence) -> list[Entry]:
    """One entry per combination of config values (first field slowest).

    ``js.grid("mlv", th1=[0, 1, 2], eps_deg=[0.1, 0.2])`` gives six MLV entries labelled
    ``"mlv th1=0 eps_deg=0.1"`` …, run as one batch (the grid is a batch axis).

    Args:
        algorithm: registry name.
        config: the base config (default: :func:`default_config` for ``camera``).
        label: the label's prefix (default: the algorithm's name).
        **values: ``field=[values]`` of the algorithm's ``Config`` (a nested field by its dotted
            name, through a mapping: ``**{"screen.fraction": [0.5, 0.6]}``).

    Raises:
        ValueError: an unknown field or a field without values.
    """
    start = default_config(algorithm, camera=camera) if config is None else config
    for name, vals in values.items():
        if len(vals) == 0:
            raise ValueError(f"grid field {name} has no values")
        with_fields(start, {name: vals[0]})  # an unknown field: a clear error before anything runs
    prefix = label or algorithm
    group = f"{prefix}[{','.join(values)}]"
    out = []
    for combo in itertools.product(*values.values()):
        setting = dict(zip(values, combo, strict=True))
        text = " ".join(f"{k}={_short(v)}" for k, v in setting.items())
        out.append(Entry(f"{prefix} {text}".strip(), algorithm,
                         with_fields(start, setting), group, tuple(setting.items())))
    return out


def _short(value) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def describe(entry: Entry) -> Mapping[str, Any]:
    """An entry as JSON-ready settings (label, algorithm, group, every config field)."""
    from jstarid.serialization import to_json

    return {"label": entry.label, "algorithm": entry.algorithm, "group": entry.group,
            "setting": to_json(dict(entry.setting)), "config_type": type(entry.config).__qualname__,
            "config": to_json(entry.config)}
