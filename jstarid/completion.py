"""Naming detections from an attitude, and naming the rest of the frame after any algorithm.

:func:`name_stars` is the shared rule (RpNet's naming passes use it too): a detection, rotated into
ICRS, is named after its nearest catalog star when that star is within the tolerance, the
second-nearest beyond ``isolation`` × the tolerance, and no other detection named by the rule
wants the same star.

The algorithms name what their method covers (MLV its ``n_stars`` brightest detections, SGM the
neighbor circle). :func:`name_from_attitude` takes any :class:`~jstarid.scene.Identification`, fits
the attitude to its named stars (Wahba), and names each unnamed detection by :func:`name_stars`
against the catalog stars that can be in the frame (:func:`~jstarid.sky_index.local_stars`), unless
its star is already a name in the scene.

Only solved scenes (``ok``) with at least ``min_named`` names are extended, and existing names are
kept, so the step never turns a correct detection into a wrong one. A detection of a star fainter
than the catalog stays unnamed unless a catalog star lies within the tolerance with no other within
``isolation`` × it: the residual risk, kept small by a tight tolerance.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.attitude import estimate_attitude
from jstarid.geometry import precise
from jstarid.geometry.angles import angle_between
from jstarid.scene import Identification, Scene
from jstarid.sky_index import build_sky_index, local_stars

__all__ = ["first_argmax", "name_from_attitude", "name_stars"]


def first_argmax(x):
    """``jnp.argmax(x, axis=-1)`` for NaN-free x as a max, then the first index reaching it: two plain
    reductions vectorize on CPU where argmax's (value, index) reduction does not; same ties.
    """
    top = jnp.max(x, axis=-1, keepdims=True)
    idx = jnp.min(jnp.where(x == top, jnp.arange(x.shape[-1], dtype=jnp.int32), x.shape[-1]), axis=-1)
    return jnp.minimum(idx, x.shape[-1] - 1)


def name_stars(c, body, valid, star_vectors, tol_rad, isolation=1.0):
    """Name detections from an attitude: nearest catalog star within ``tol_rad``, unambiguous.

    Args:
        c: (3, 3) attitude, ``v_cam = C r``.
        body: (N, 3) camera-frame unit vectors of the detections. valid: (N,) bool.
        star_vectors: (M, 3) ICRS catalog unit vectors.
        tol_rad: match radius (rad), a float or a traced scalar.
        isolation: the second-nearest catalog star must lie beyond ``isolation · tol_rad`` (≥ 1; a float
            or a traced scalar).

    Returns:
        ``(rows, named)``: (N,) int32 nearest catalog row and (N,) bool, True when that star is within
        ``tol_rad``, the second-nearest is not within ``isolation · tol_rad``, and no other named
        detection has the same row.
    """
    ref = precise.small_matmul(body, c)  # (N, 3) ICRS directions: r = Cᵀ v
    cos = precise.small_matmul(ref, star_vectors.T)  # (N, M), fused into the two argmaxes
    best = first_argmax(cos)  # two reductions instead of a top-2 (a sort on CPU)
    second = first_argmax(jnp.where(jnp.arange(cos.shape[1])[None, :] == best[:, None], -2.0, cos))
    # float32 cosines near 1 resolve only ≈ 3.5e-4 rad (1.4 px here): the cosines pick the two nearest
    # stars, the distances are measured with atan2 (accurate at small angles)
    d1 = angle_between(ref, star_vectors[best])
    d2 = angle_between(ref, star_vectors[second])
    named = valid & (d1 <= tol_rad) & (d2 > isolation * tol_rad)
    same = (best[:, None] == best[None, :]) & named[:, None] & named[None, :]
    clash = jnp.sum(same, axis=1) > 1
    return best.astype(jnp.int32), named & ~clash


def name_from_attitude(catalog, camera, scenes: Scene, result: Identification, *, tol_px: float = 2.0,
                       isolation: float = 2.0, min_named: int = 3) -> Identification:
    """Extend ``result`` to every detection the attitude of its named stars explains (module doc).

    Args:
        catalog: :class:`~jstarid.catalog.Catalog` whose rows ``result.ids`` refers to.
        camera: :class:`~jstarid.camera.Camera` of the scenes.
        scenes: (B, N) :class:`~jstarid.scene.Scene`.
        result: (B, N) :class:`~jstarid.scene.Identification`.
        tol_px: largest angle between a detection and the star it is named after, in pixels at the
            principal point (``tol_px / f_px`` rad).
        isolation: no second catalog star may lie within ``isolation · tol_px`` (≥ 1).
        min_named: fewest names a scene needs for its attitude to be used.

    Returns:
        An :class:`~jstarid.scene.Identification` with the added names, the same ``ok`` and the
        attitude refitted to all names (NaN where a scene is not solved or has fewer than 2 names).

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
    margin = math.atan(isolation * tol_px / camera.f_px)  # a star just outside can still compete
    index = build_sky_index(catalog.unit_vectors, camera.half_diagonal_rad, margin_rad=margin,
                            key=f"{catalog.fingerprint}-complete-{margin:.3e}")
    cells, _ = index.device_arrays()
    ids = _extend(jnp.asarray(catalog.unit_vectors, jnp.float32), cells,
                  jnp.where(jnp.isfinite(att), att, 0.0), have & result.ok, scenes.xy, scenes.valid,
                  jnp.where(scenes.valid, result.ids, -1), jnp.float32(tol_px / camera.f_px),
                  jnp.float32(isolation), camera=camera, grid=index.grid)
    extended = Identification(ids=ids, ok=result.ok)
    att2, _, have2 = estimate_attitude(catalog, camera, scenes, extended, min_stars=2)
    return Identification(ids=ids, ok=result.ok,
                          attitude=jnp.where((have2 & result.ok)[:, None, None], att2, jnp.nan))


@functools.partial(jax.jit, static_argnames=("camera", "grid"))
def _extend(star_vec, cells, att, use, xy, valid, ids, tol_rad, isolation, *, camera, grid):
    """(B, N) ids with the new names (vmapped over scenes); the tolerances are traced (no recompile)."""
    def one(c, use_i, xy_i, valid_i, ids_i):
        rows, vectors, _ = local_stars(cells, star_vec, c[2], grid)  # c[2] = Cᵀ ẑ, the boresight
        local, named = name_stars(c, camera.unproject(xy_i), valid_i, vectors, tol_rad, isolation)
        row = rows[local]
        taken = jnp.any((ids_i[None, :] == row[:, None]) & (ids_i[None, :] >= 0), axis=1)
        new = use_i & (ids_i < 0) & named & ~taken
        return jnp.where(new, row, ids_i).astype(jnp.int32)

    return jax.vmap(one)(att, use, xy, valid, ids)
