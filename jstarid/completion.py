"""Name the rest of the frame from an identification's attitude (after any algorithm).

The algorithms name what their method covers — MLV its ``n_stars`` brightest detections, SGM the
neighbor circle — while a user of a star tracker wants every star of the frame named.
:func:`name_from_attitude` takes any :class:`~jstarid.scene.Identification`, fits the attitude to its
named stars (Wahba, SVD), projects the catalog stars that can be in the frame (a sky-index cell of the
boresight, as the simulator does) and names an unnamed detection after catalog star *s* when

1. *s* projects within ``tol_px`` of the detection (the detection's nearest projected star), and
2. no other catalog star projects within ``isolation · tol_px`` of the detection (no close pair to
   confuse), and
3. the detection is the nearest valid detection to *s*'s projection, and *s* is not already a name
   in the scene (one star, one detection).

Only scenes the algorithm solved (``ok``) with at least ``min_named`` names are extended; names it
gave are kept as they are, so the step never turns a correct detection into a wrong one, and a star
it adds needs its own detection to land within ``tol_px`` of where the verified attitude puts it.
A detection of a star fainter than the catalog stays unnamed unless a catalog star projects within
``tol_px`` of it while no other does — the residual risk, kept small by a tight ``tol_px``.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.attitude import estimate_attitude
from jstarid.geometry import precise
from jstarid.scene import Identification, Scene
from jstarid.sky_index import build_sky_index, cell_of

__all__ = ["name_from_attitude"]


def name_from_attitude(catalog, camera, scenes: Scene, result: Identification, *, tol_px: float = 2.0,
                       isolation: float = 2.0, min_named: int = 3) -> Identification:
    """Extend ``result`` to every detection the attitude of its named stars explains (module doc).

    Args:
        catalog: :class:`~jstarid.catalog.Catalog` whose rows ``result.ids`` refers to.
        camera: :class:`~jstarid.camera.Camera` of the scenes.
        scenes: (B, N) :class:`~jstarid.scene.Scene`.
        result: (B, N) :class:`~jstarid.scene.Identification`.
        tol_px: largest distance (px) between a detection and the projection of the star it is named
            after.
        isolation: no second catalog star may project within ``isolation · tol_px`` (≥ 1).
        min_named: fewest names a scene needs for its attitude to be used.

    Returns:
        An :class:`~jstarid.scene.Identification` with the added names, the same ``ok`` and the
        attitude refitted to all names (NaN where a scene is not extended and had none).

    Raises:
        ValueError: a bad tolerance, isolation factor or ``min_named``.
    """
    if not (math.isfinite(tol_px) and tol_px > 0):
        raise ValueError(f"tol_px must be a positive number of pixels, got {tol_px}")
    if not (math.isfinite(isolation) and isolation >= 1):
        raise ValueError(f"isolation must be ≥ 1, got {isolation}")
    if not isinstance(min_named, int | np.integer) or min_named < 2:
        raise ValueError(f"min_named must be an integer ≥ 2 (a rotation needs two stars), got {min_named}")
    att, _, have = estimate_attitude(catalog, camera, scenes, result, min_stars=int(min_named))
    margin = math.atan(isolation * tol_px / camera.f_px)
    index = build_sky_index(catalog.unit_vectors, camera.half_diagonal_rad, margin_rad=margin,
                            key=f"{catalog.fingerprint}-complete-{margin:.3e}")
    cells, _ = index.device_arrays()
    star_vec = jnp.asarray(np.concatenate([catalog.unit_vectors, [[0.0, 0.0, 1.0]]]), jnp.float32)
    ids = _extend(star_vec, cells, jnp.where(jnp.isfinite(att), att, 0.0), have & result.ok,
                  scenes.xy, scenes.valid, jnp.where(scenes.valid, result.ids, -1),
                  camera=camera, grid=index.grid, tol_px=float(tol_px), isolation=float(isolation))
    extended = Identification(ids=ids, ok=result.ok)
    att2, _, have2 = estimate_attitude(catalog, camera, scenes, extended, min_stars=2)
    return Identification(ids=ids, ok=result.ok,
                          attitude=jnp.where((have2 & result.ok)[:, None, None], att2, jnp.nan))


@functools.partial(jax.jit, static_argnames=("camera", "grid", "tol_px", "isolation"))
def _extend(star_vec, cells, att, use, xy, valid, ids, *, camera, grid, tol_px, isolation):
    """(B, N) ids with the new names; per scene (vmapped) the three conditions of the module doc."""
    pad_row = star_vec.shape[0] - 1  # the sentinel row appended to the catalog

    def one(c, use_i, xy_i, valid_i, ids_i):
        rows = cells[cell_of(c[2], grid)]  # (K,) catalog rows that can be in the frame; c[2] = Cᵀẑ
        v = precise.matmul(star_vec[rows], c.T)  # camera frame
        pred, _ = camera.project(v)
        # every star in front of the camera counts, also one just outside the frame: it may still
        # be the nearer star of a detection at the edge (condition 2)
        in_front = (rows < pad_row) & (v[:, 2] > 0)
        d = jnp.linalg.norm(xy_i[:, None, :] - pred[None, :, :], axis=-1)  # (N, K) px
        d = jnp.where(valid_i[:, None] & in_front[None, :], d, jnp.inf)
        nearest = jnp.argmin(d, axis=1)  # (N,) the nearest projected star of each detection
        d1 = jnp.take_along_axis(d, nearest[:, None], axis=1)[:, 0]
        d2 = jnp.min(jnp.where(jnp.arange(d.shape[1])[None, :] == nearest[:, None], jnp.inf, d), axis=1)
        nearest_det = jnp.argmin(d, axis=0)  # (K,) the nearest detection of each projected star
        mutual = nearest_det[nearest] == jnp.arange(d.shape[0])
        row = rows[nearest]
        taken = jnp.any((ids_i[None, :] == row[:, None]) & (ids_i[None, :] >= 0), axis=1)
        new = (use_i & valid_i & (ids_i < 0) & (d1 <= tol_px) & (d2 > isolation * tol_px) & mutual
               & ~taken)
        return jnp.where(new, row, ids_i).astype(jnp.int32)

    return jax.vmap(one)(att, use, xy, valid, ids)
