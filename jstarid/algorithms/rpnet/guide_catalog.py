"""Guide reference stars (GRSs) of RpNet (§II-A): the classes the network tells apart.

The paper keeps SAO stars with V ≤ 6.0, one star of each close pair at random, and deletes "some
stars in dense areas" (5,045 guides). Here (docs/design/rpnet.md):

* the catalog is :func:`jstarid.load_catalog` with its close-pair removal (``double_sep_deg``; the
  brighter star kept, deterministic): ``load_catalog(6.0, double_sep_deg=0.1)`` has 5,044 stars;
* guides are the catalog rows with V ≤ ``Config.guide_mag_limit``;
* optional thinning: a guide closer than ``Config.guide_min_sep_deg`` to a brighter guide is dropped
  (default 0). The dense-area deletion is not reproduced; every catalog star still appears as a
  *neighbour* in the inputs, only the class list shrinks;
* narrow, deep fields (extension, ``Config.guides_per_cell``): only the brightest few guides of each
  cube-map sky cell are kept, so the classes cover the sky evenly whatever the star density, and a
  frame's brightest detections are mostly guides.

Class k of the network is catalog row ``guide_rows[k]``.
"""

from __future__ import annotations

import numpy as np

from jstarid.algorithms.rpnet.config import Config
from jstarid.catalog import Catalog, load_catalog
from jstarid.sky_index import brightest_per_cell

__all__ = ["guide_rows", "load_guide_catalog"]

PAPER_DOUBLE_SEP_DEG = 0.1  # close-pair threshold used for the RpNet catalog (≈ 7 px at f_px ≈ 4106)


def load_guide_catalog(config: Config | None = None, *,
                       double_sep_deg: float = PAPER_DOUBLE_SEP_DEG, **kwargs) -> Catalog:
    """The Hipparcos catalog RpNet is built on: V ≤ ``guide_mag_limit``, close pairs reduced to one.

    The simulation list goes to V 7.0 (``sim_margin = 1``), the paper's magnitude-noise limit (§II-C.2).
    """
    config = Config() if config is None else config
    return load_catalog(config.guide_mag_limit, double_sep_deg=double_sep_deg, **kwargs)


def guide_rows(catalog: Catalog, config: Config | None = None) -> np.ndarray:
    """Catalog rows of the guide stars, brightest first.

    Args:
        catalog: the identification catalog (rows sorted brightest first).
        config: uses ``guide_mag_limit`` (V), ``guides_per_cell`` and ``guide_cell_grid`` (the
            brightest few per sky cell, applied first) and ``guide_min_sep_deg`` (deg).

    Returns:
        (K,) int32 catalog rows; class k ↔ row ``guide_rows[k]``.

    Raises:
        ValueError: no catalog star passes the selection.
    """
    config = Config() if config is None else config
    rows = np.nonzero(np.asarray(catalog.mag) <= config.guide_mag_limit)[0]
    rows = rows[np.argsort(np.asarray(catalog.mag)[rows], kind="stable")]
    if config.guides_per_cell > 0:
        rows = brightest_per_cell(np.asarray(catalog.unit_vectors)[rows], config.guide_cell_grid,
                                  config.guides_per_cell, rows)
    if config.guide_min_sep_deg > 0 and len(rows) > 1:
        from scipy.spatial import cKDTree

        vec = np.asarray(catalog.unit_vectors)[rows]
        chord = 2.0 * np.sin(np.radians(config.guide_min_sep_deg) / 2.0)
        tree = cKDTree(vec)
        dropped = np.zeros(len(rows), bool)
        for i in range(len(rows)):  # brightest first: a kept guide removes its fainter close neighbours
            if dropped[i]:
                continue
            for j in tree.query_ball_point(vec[i], chord):
                if j > i:
                    dropped[j] = True
        rows = rows[~dropped]
    if rows.size == 0:
        raise ValueError(f"no catalog star with V ≤ {config.guide_mag_limit}")
    return rows.astype(np.int32)
