"""Configs that hold configs: a field set by its dotted path, a nested config built from a mapping.

An algorithm's frozen ``Config`` groups related settings in nested frozen dataclasses (SGM's
``verify``, ``screen``, …; every seed's ``finishing``). A group that an extension switches on and off
has a boolean field ``on``; :func:`replace_at` sets it when given a bool for the group itself, so
``--set screen=false`` switches SGM's screen off and keeps the screen's (camera-scaled) tolerances.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any, TypeVar

__all__ = ["Switched", "differences", "nested", "replace_at", "value_at", "with_fields"]

T = TypeVar("T")


class Switched:
    """Base of a nested config with an ``on`` switch: its truth value is refused, so that
    ``if config.screen:`` (always true for a dataclass) fails loudly instead of ignoring the switch;
    read ``config.screen.on``."""

    def __bool__(self):
        raise TypeError(f"the truth value of a {type(self).__name__} is ambiguous; read its .on")


def nested(cls: type[T], value: Any, name: str) -> T:
    """``value`` itself, or a ``cls`` built from a mapping of its fields (a config read from JSON or
    ``--set``).

    Args:
        cls: the nested config's dataclass.
        value: a ``cls`` or a mapping of some of its fields (the rest default).
        name: the field that holds it, for the messages.

    Raises:
        TypeError: anything else, or a mapping with a field ``cls`` lacks.
    """
    if isinstance(value, cls):
        return value
    if isinstance(value, Mapping):
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(value) - known
        if unknown:
            raise TypeError(f"{cls.__name__} has no field(s) {sorted(unknown)}; fields: {sorted(known)}")
        return cls(**value)
    hint = (f" (to switch it on or off: {name}.on, or {cls.__name__}(on=…))"
            if isinstance(value, bool) and "on" in {f.name for f in dataclasses.fields(cls)} else "")
    raise TypeError(f"{name} must be a {cls.__name__} or a mapping of its fields, got {value!r}{hint}")


def replace_at(config, path: str | Sequence[str], value):
    """``config`` with the field at the dotted ``path`` set to ``value`` (:func:`with_fields`)."""
    return with_fields(config, {path if isinstance(path, str) else ".".join(path): value})


def value_at(config, path: str):
    """The value of the field at the dotted ``path`` (``"verify.cap_deg"``)."""
    for name in path.split("."):
        config = getattr(config, name)
    return config


def with_fields(config, fields: Mapping[str, Any]):
    """``config`` with every ``{dotted path: value}`` of ``fields`` set.

    A longer path sets a field of a nested config (``verify.retries``); a bool given for a nested
    config with an ``on`` field sets ``on`` (``screen=False``); a list given for a tuple field becomes a
    tuple. The fields of one config are set together, so that its validation sees them all (a floor
    and a cap scaled at once), and every config on a path is rebuilt through its own validation; a
    later entry for the same field wins.

    Raises:
        ValueError: an unknown field (the message lists the config's fields, and the dotted name
            where a flat name like ``verify_retries`` names a nested one), or a path through a field
            that is not a nested config.
    """
    known = {f.name for f in dataclasses.fields(config)}
    whole: dict[str, Any] = {}  # fields given a value of their own
    inner: dict[str, dict[str, Any]] = {}  # nested fields, by the nested config that holds them
    for path, value in fields.items():
        name, _, rest = path.partition(".")
        if name not in known:
            raise ValueError(f"{type(config).__name__} has no field {name!r}{_dotted_hint(config, name)}; "
                             f"fields: {', '.join(sorted(known))}")
        current = whole.get(name, getattr(config, name))
        if not rest and isinstance(value, bool) and dataclasses.is_dataclass(current) \
                and hasattr(current, "on"):
            rest = "on"
        if rest:
            if not dataclasses.is_dataclass(current):
                raise ValueError(f"{type(config).__name__}.{name} is not a nested config; cannot set "
                                 f"{path}")
            inner.setdefault(name, {})[rest] = value
        else:
            inner.pop(name, None)
            whole[name] = (tuple(value) if isinstance(getattr(config, name), tuple)
                           and isinstance(value, list) else value)
    for name, nested_fields in inner.items():
        whole[name] = with_fields(whole.get(name, getattr(config, name)), nested_fields)
    return dataclasses.replace(config, **whole)


def differences(config, other) -> dict[str, Any]:
    """``{dotted path: value in other}`` for every leaf field where two configs of one class differ
    (nested configs compared field by field)."""
    out = {}
    for f in dataclasses.fields(config):
        mine, theirs = getattr(config, f.name), getattr(other, f.name)
        if dataclasses.is_dataclass(mine) and type(mine) is type(theirs):
            out.update({f"{f.name}.{k}": v for k, v in differences(mine, theirs).items()})
        elif mine != theirs:
            out[f.name] = theirs
    return out


def _dotted_hint(config, name: str) -> str:
    """`` (did you mean 'verify.retries'?)`` where ``name`` is a nested field's flat spelling: the
    group's name and the field's (``verify_retries``), the field's alone (``prune``), or another
    prefix and the field's (``focal_search_dw_max_deg`` for ``ladder.dw_max_deg``), in that order."""
    groups = [(f.name, sorted((g.name for g in dataclasses.fields(getattr(config, f.name))), key=len,
                              reverse=True))
              for f in dataclasses.fields(config) if dataclasses.is_dataclass(getattr(config, f.name))]
    rules = (lambda group, field: name == f"{group}_{field}", lambda group, field: name == field,
             lambda group, field: name.endswith(f"_{field}"))
    for rule in rules:
        for group, fields in groups:
            for field in fields:
                if rule(group, field):
                    return f" (did you mean '{group}.{field}'?)"
    return ""
