"""Noise axes and their levels: what a sweep varies, as one :class:`~jstarid.NoiseConfig` batch.

A sweep varies one or two :class:`~jstarid.NoiseConfig` fields (its *axes*; a sweep from pixels
may also vary :class:`~jstarid.SensorConfig` fields, :data:`~jstarid.engine.pixels.SENSOR_AXES`);
every combination of their values is a *level*, and each level gets the same number of scenes. The
whole sweep is one (L · n,) noise batch, level-major (the scenes of level 0 first), so one
``simulate`` call draws every level.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence

import numpy as np

from jstarid.engine.pixels import SENSOR_AXES
from jstarid.simulator import NoiseConfig

__all__ = ["AXES", "NOISE_AXES", "axis_field", "level_grid", "level_noise", "level_label"]

# NoiseConfig field → how a figure labels it
NOISE_AXES = {
    "position_sigma_px": "position noise σ (px)",
    "magnitude_sigma": "magnitude noise σ (mag)",
    "n_missing": "missing stars per scene",
    "n_false": "false stars per scene",
    "false_ratio": "false-star ratio",
    "false_per_true": "false stars per true star",
    "false_mean": "mean false stars per scene (Poisson)",
}
AXES = {**NOISE_AXES, **SENSOR_AXES}  # every axis a sweep may vary (sensor axes: from pixels only)
# the short names the command line accepts
_SHORT = {"position": "position_sigma_px", "magnitude": "magnitude_sigma", "missing": "n_missing",
          "false": "n_false", "false-ratio": "false_ratio", "false_ratio": "false_ratio",
          "false-per-true": "false_per_true", "false-mean": "false_mean"}
_SHORT.update({"exposure": "exposure_s", "read-noise": "read_noise_e", "defocus": "defocus_px",
               "smear": "smear_px"})
_INTEGER = ("n_missing", "n_false", "hot_pixels")


def axis_field(name: str) -> str:
    """The field an axis name means (``"position"``, ``"exposure"`` or the field name): a
    :class:`~jstarid.NoiseConfig` field or, for sweeps from pixels, a :class:`~jstarid.SensorConfig` one.

    Raises:
        ValueError: not an axis (the message lists them).
    """
    field = _SHORT.get(name, name)
    if field not in AXES:
        raise ValueError(f"unknown axis {name!r}; choose one of "
                         f"{', '.join(sorted(set(_SHORT) | set(AXES)))}")
    return field


def level_grid(axes: Mapping[str, Sequence[float]]) -> list[dict[str, float]]:
    """Every combination of the axes' values (first axis slowest), as ``{field: value}`` dicts.

    Args:
        axes: one or two ``{axis: values}`` (axis as in :func:`axis_field`); values are checked by
            :meth:`~jstarid.NoiseConfig.validate` when the noise is built.

    Raises:
        ValueError: no axis, more than two, an unknown axis, or an axis without values.
    """
    if not 1 <= len(axes) <= 2:
        raise ValueError(f"a sweep has one or two noise axes, got {len(axes)}")
    fields = [axis_field(a) for a in axes]
    if len(set(fields)) != len(fields):
        raise ValueError(f"noise axes repeat a field: {list(axes)}")
    values = []
    for field, vals in zip(fields, axes.values(), strict=True):
        vals = [int(v) if field in _INTEGER else float(v) for v in np.atleast_1d(vals)]
        if not vals:
            raise ValueError(f"noise axis {field} has no values")
        values.append(vals)
    return [dict(zip(fields, combo, strict=True)) for combo in itertools.product(*values)]


def level_noise(levels: Sequence[Mapping[str, float]], scenes_per_level: int,
                fixed: Mapping[str, float] | None = None) -> NoiseConfig:
    """The (L · n,) noise batch of ``levels``, level-major, with ``fixed`` settings for every scene.

    Raises:
        ValueError: a fixed field that is also an axis, an unknown field, or out-of-range values.
    """
    fixed = dict(fixed or {})
    swept = set(levels[0]) & set(NOISE_AXES)  # sensor fields are the renderer's (engine.pixels)
    clash = swept & set(fixed)
    if clash:
        raise ValueError(f"{', '.join(sorted(clash))} is both a noise axis and a fixed setting")
    columns = {f: np.repeat(np.asarray([lv[f] for lv in levels]), scenes_per_level) for f in swept}
    try:
        noise = NoiseConfig(**fixed, **columns)
    except TypeError as err:  # an unknown field name
        raise ValueError(f"bad noise setting: {err}") from None
    noise.validate()
    return noise


def level_label(level: Mapping[str, float]) -> str:
    """``"position_sigma_px=1, n_false=2"`` (for tables and legends)."""
    return ", ".join(f"{k}={v:g}" for k, v in level.items())
