"""The papers' experiment definitions: which scenes, which levels, the papers' own figures.

One module per paper (:mod:`~jstarid.papers.mlv`, :mod:`~jstarid.papers.rpnet`,
:mod:`~jstarid.papers.sgm`), shared by the scripts in ``experiments/`` that reproduce, tune or
diagnose it, so that a sweep's levels or a figure quoted from a paper are written down once. They
hold data and scene drawing only, never the algorithm they describe.
"""

from typing import NamedTuple

__all__ = ["Sweep"]


class Sweep(NamedTuple):
    """One noise sweep: the :class:`~jstarid.NoiseConfig` field varied, its levels, the fields held
    fixed, and the x-axis label."""

    field: str
    levels: list
    fixed: dict
    label: str
