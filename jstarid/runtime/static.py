"""The static config a kernel compiles with (one rule for every algorithm)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

__all__ = ["static_config"]


def static_config(config, not_compiled: Iterable[str]):
    """``config`` with the fields its kernels do not read as compile-time constants reset to their
    class defaults, so that configs differing only there (traced tolerances, buffer sizes, chunking,
    database or host-loop settings) share one compilation.

    Args:
        config: a frozen dataclass config (the kernels' static argument).
        not_compiled: names of its fields the kernels never read statically.

    Returns:
        The config to pass as the kernels' static argument.

    Raises:
        ValueError: a name that is not a field of the config.
    """
    fields = {f.name: f for f in dataclasses.fields(config)}
    defaults = {}
    for name in not_compiled:
        if name not in fields:
            raise ValueError(f"{type(config).__name__} has no field {name!r}")
        field = fields[name]
        defaults[name] = field.default_factory() if field.default is dataclasses.MISSING else field.default
    return dataclasses.replace(config, **defaults)
