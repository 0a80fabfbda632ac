"""Names that a neighbouring catalog star explains as well: taken back.

An algorithm names a detection after the star its pattern or its verification put there; the camera
check (:func:`jstarid.camera_fit.check_identification`) then asks only whether that star lies within
the fit's radius. Where two catalog stars lie a few σ apart, the detection of one can land within
the radius of the other, and be named after it: a close pair at σ = 3 px (the brighter star's
detection a fraction of a pixel from its fainter neighbour, several σ from its own star, and far
brighter than the neighbour: docs/design/rival_stars.md), or a blend of a pair on a real frame. The
radius cannot tell the two apart; the position and the brightness together can.

**The test.** For a named detection ``i`` (star ``s``) and every other catalog star ``t`` within the
check's largest radius of it, the log-odds that ``s`` rather than ``t`` is the source are

    Δ(s, t) = (d_t² − d_s²) / (2 σ̂²) + (b(o_t) − b(o_s)),

the first term the log-ratio of two 2-D Gaussian densities of the centroid error (σ̂ px per axis,
from the scene's named residuals: median / √(2 ln 2), never below :data:`SIGMA_FLOOR_PX`), the second
the same for the brightness: ``o`` is the detection's magnitude minus the star's, about the named
stars' zero point, and ``b(o) = min(o² / (2 σ̂_m²), MAG_OUTLIER_NATS)`` with ``σ̂_m`` the robust
scatter of the named offsets (never below :data:`MAG_FLOOR`) — a Gaussian with an outlier floor, so
that a star whose colour puts it a magnitude off (real sensors) is not ruled out by its brightness
alone. With fewer than :data:`MIN_MAG_NAMES` names the brightness does not count (no zero point). A
name stands only where ``Δ ≥ ln(odds)`` against every such ``t`` (``Finishing.rival_odds``, 20 by
default): a detection that could as well be another star's light is left unnamed, never named as
the wrong one — a lost name costs recall, a wrong one the frame.

**No star at all.** The other rival is a false detection (a hot pixel, a cosmic ray, a satellite)
landing near a catalog star that was not detected — too faint for this frame, or crowded out of a
list kept to its brightest detections — which no neighbouring star can expose. A name stands only
where its star explains the detection ``odds`` times better than a false detection does:

    ln t₂(d_s; σ̂, ν) + [ln(FALSE_MAG_SPAN / (√(2π) σ̂_m)) − b(o_s)] − ln(λ / A) ≥ ln(odds),

the density of the centroid error — a bivariate t, σ̂ having ν = 2n − 4 degrees of freedom over n
names (a Gaussian as n grows) — against a false detection's uniform density over the
frame (λ expected per frame, ``Finishing.false_per_frame``, over its area A in px²), and the
brightness term as a Gaussian density about the zero point against a false detection's uniform over
:data:`FALSE_MAG_SPAN` (only with a zero point). On a coarse camera (290″/px, σ = 2 px) a false
detection one magnitude brighter than an undetected star 4 px away is taken back; a right name
within 2 σ̂ and 2 σ̂_m keeps a margin of several nats (docs/design/rival_stars.md).

Only the identification catalog's stars count as rivals (a detection of a star fainter than the
catalog is not this test's to see), and every candidate is a rival whether or not another
detection is named after it: a pair both detected and both named a few σ apart and of equal
brightness loses both names (the price, measured in RESULTS.md).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.camera import Camera
from jstarid.camera_fit import (
    CHECK_CHUNK,
    RAYLEIGH_MEDIAN,
    check_call_size,
    check_width,
    unproject_scaled,
)
from jstarid.geometry import precise
from jstarid.geometry.angles import angle_between
from jstarid.robust import magnitude_offsets, masked_median
from jstarid.runtime.batching import chunk_calls, run_calls, take_rows
from jstarid.runtime.devices import batch_mesh
from jstarid.runtime.padding import columns_in_use
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Identification, Scene
from jstarid.sky_index import build_sky_index, cell_of

__all__ = ["rivalled_names", "without_rivalled_names"]

SIGMA_FLOOR_PX = 0.1  # σ̂ of the position term never below this (px): a noiseless frame's residuals
MAG_FLOOR = 0.25  # σ̂_m never below this (mag): simulated magnitudes without noise scatter by 0
MAG_OUTLIER_NATS = 8.0  # the brightness term's ceiling (nats): a colour term's 1 mag outlier
MIN_MAG_NAMES = 4  # fewest names whose offsets set a zero point (as robust.brighter_than_named)
MIN_NAMES = 3  # a scene left with fewer names is no longer claimed (the camera check's minimum)
FALSE_MAG_SPAN = 4.0  # mag: a false detection's brightness, taken as uniform over this span
SQRT_2PI = math.sqrt(2.0 * math.pi)


def rivalled_names(xy, valid, mag, ids, attitude, scale, k1, star_vectors, star_mags, cells, optics, *,
                   grid: int, log_odds, max_tol_px, false_density=0.0):
    """(N,) bool: the names of one scene that a neighbouring catalog star explains as well (module doc).

    Args:
        xy: (N, 2) detections (px). valid: (N,) bool. mag: (N,) their magnitudes (mag; any zero point).
        ids: (N,) int32 catalog rows named, −1 unnamed.
        attitude: (3, 3) ``C`` (ICRS → camera) fitted to the names. scale: () fitted focal length /
            nominal. k1: () fitted radial distortion.
        star_vectors: (M, 3) ICRS unit vectors. star_mags: (M,) V (mag).
        cells: the rival index's cell lists (:func:`jstarid.sky_index.SkyIndex.device_arrays`, built
            with the check's largest radius as its field radius). optics: the camera's
            :meth:`~jstarid.camera.Camera.pinhole_numbers`.
        grid: the index's G (static). log_odds: ``ln(odds)``, the margin a name must keep.
        max_tol_px: the farthest a rival may lie from the detection (px; the index must reach it).
        false_density: () false detections expected per px² (the frame's expected count over its
            area); above 0 the detection's other rival is no star at all (module doc); 0: not asked.

    Returns:
        (N,) bool, True for a name some other star within ``max_tol_px`` explains with log-odds
        below ``log_odds``, or that a false detection explains as well.
    """
    camera = Camera.traced(optics)
    m = star_vectors.shape[0]
    named = valid & (ids >= 0)
    own = jnp.clip(ids, 0, m - 1)
    px = camera.f_px * scale
    sky = precise.small_matmul(unproject_scaled(camera, xy, scale, k1), attitude)  # ICRS: r = Cᵀ v
    d_own = angle_between(sky, star_vectors[own]) * px  # (N,) px
    sigma = jnp.maximum(masked_median(d_own, named) / RAYLEIGH_MEDIAN, SIGMA_FLOOR_PX)
    rows = cells[cell_of(sky, grid)]  # (N, K) the stars the index holds near each detection
    rows_c = jnp.minimum(rows, m - 1)
    d = angle_between(sky[:, None, :], star_vectors[rows_c]) * px  # (N, K) px
    rival = (rows < m) & (rows != ids[:, None]) & (d <= max_tol_px)

    offset, spread, count = magnitude_offsets(mag, star_mags[own], named)
    zero = mag - star_mags[own] - offset  # the named stars' zero point (the same on every row)
    sigma_m = jnp.maximum(spread, MAG_FLOOR)

    def brightness(o):  # nats, a Gaussian with an outlier floor; nothing without a zero point
        cost = jnp.minimum(0.5 * (o / sigma_m) ** 2, MAG_OUTLIER_NATS)
        return jnp.where((count >= MIN_MAG_NAMES) & jnp.isfinite(cost), cost, 0.0)

    o_rival = mag[:, None] - star_mags[rows_c] - zero[:, None]
    evidence = ((d**2 - d_own[:, None] ** 2) / (2.0 * sigma**2)
                + brightness(o_rival) - brightness(offset)[:, None])
    # no star at all: the named star's densities (position below, Gaussian brightness about the
    # zero point) against a false detection's (uniform over the frame and FALSE_MAG_SPAN)
    with_mag = (count >= MIN_MAG_NAMES) & jnp.isfinite(offset)
    mag_nats = jnp.where(with_mag, jnp.log(FALSE_MAG_SPAN / (SQRT_2PI * sigma_m)) - brightness(offset), 0.0)
    # σ̂ comes from the names themselves: the position density is the bivariate t of its dof (2 per
    # name less the fit's 4; camera_fit.studentized_k), not a Gaussian that takes a right name 5 σ̂
    # out of 9 for a false detection
    dof = jnp.maximum(2.0 * jnp.sum(named) - 4.0, 1.0)
    own_nats = (-0.5 * (dof + 2.0) * jnp.log1p(d_own**2 / (dof * sigma**2))
                - jnp.log(2.0 * jnp.pi * sigma**2) + mag_nats)
    false_star = (false_density > 0) & (own_nats - jnp.log(jnp.maximum(false_density, 1e-30)) < log_odds)
    return named & (jnp.any(rival & (evidence < log_odds), axis=1) | false_star)


@stored_jit(static_argnames=("grid",))
def _rival_kernel(xy, valid, mag, ids, attitude, scale, k1, star_vectors, star_mags, cells, optics, log_odds,
                  max_tol_px, false_density, *, grid):
    """(B, N) bool: :func:`rivalled_names` of each scene."""
    def one(xy_i, valid_i, mag_i, ids_i, att_i, scale_i, k1_i):
        return rivalled_names(xy_i, valid_i, mag_i, ids_i, att_i, scale_i, k1_i, star_vectors, star_mags,
                              cells, optics, grid=grid, log_odds=log_odds,
                              max_tol_px=max_tol_px, false_density=false_density)

    return jax.vmap(one)(xy, valid, mag, ids, attitude, scale, k1)


def without_rivalled_names(result: Identification, scenes: Scene, *, stars, camera, odds: float,
                           max_tol_px: float, max_scale_error: float,
                           false_per_frame: float = 0.0) -> Identification:
    """``result`` with the names a neighbouring catalog star explains as well taken back (module doc).

    Checks the solved scenes with an attitude; a scene left with fewer than :data:`MIN_NAMES` names
    is no longer claimed (ids −1, ``ok`` False, NaN attitude and fits). The attitude stays the one
    given (fitted with the names taken back: they lie within the check's radius).

    Args:
        result: (B, N) :class:`~jstarid.scene.Identification` with ``attitude`` (NaN where not
            solved); ``focal_scale`` and ``distortion_k1`` used where given and finite (else 1, 0).
        scenes: (B, N) :class:`~jstarid.scene.Scene` from ``camera``.
        stars: the catalog rows ``result.ids`` names: a :class:`~jstarid.finishing.StarTable` or a
            :class:`~jstarid.catalog.Catalog` (``unit_vectors``, ``mag``, ``fingerprint``).
        camera: the nominal :class:`~jstarid.camera.Camera`.
        odds: the factor by which a name's star must explain its detection better than any other.
        max_tol_px: the largest distance (px) at which another star counts (the check's radius).
        max_scale_error: the largest focal-length correction the fit may have made.
        false_per_frame: false detections a frame is expected to hold (``Finishing.false_per_frame``):
            the prior of the rival that is no star; 0: that rival is not asked.

    Returns:
        An :class:`~jstarid.scene.Identification`.

    Raises:
        ValueError: ``odds`` below 1, a non-positive ``max_tol_px`` or a negative ``false_per_frame``.
    """
    if not (math.isfinite(odds) and odds >= 1.0):
        raise ValueError(f"odds must be a finite number ≥ 1, got {odds}")
    if not (math.isfinite(max_tol_px) and max_tol_px > 0):
        raise ValueError(f"max_tol_px must be a positive number of pixels, got {max_tol_px}")
    if not (math.isfinite(false_per_frame) and false_per_frame >= 0):
        raise ValueError(f"false_per_frame must be a number ≥ 0, got {false_per_frame}")
    b, n = scenes.batch_size, scenes.capacity
    if result.attitude is None or not b:
        return result
    attitude = np.asarray(result.attitude, np.float32)
    ids = np.where(np.asarray(scenes.valid), np.asarray(result.ids), -1).astype(np.int32)
    solved = np.asarray(result.ok) & np.isfinite(attitude).all(axis=(1, 2))
    rows = np.flatnonzero(solved & (ids >= 0).any(axis=1))
    if not rows.size:
        return result

    def fitted(x, default):
        x = np.full(b, default, np.float32) if x is None else np.asarray(x, np.float32)
        return np.where(np.isfinite(x), x, default).astype(np.float32)

    radius = math.atan(max_tol_px * (1.0 + max_scale_error) / camera.f_px)
    index = build_sky_index(np.asarray(stars.unit_vectors), radius,
                            key=f"{stars.fingerprint}-rivals-{radius:.3e}")
    cells, _ = index.device_arrays()
    valid = np.asarray(scenes.valid)
    filled = columns_in_use(valid)
    per_scene = (np.asarray(scenes.xy, np.float32), valid, np.asarray(scenes.mag, np.float32), ids, attitude,
                 fitted(result.focal_scale, 1.0), fitted(result.distortion_k1, 0.0))

    def args(call):  # each call cut to the columns its detections fill (as the camera check's)
        cut = check_width(call, filled, n)
        xy, valid_c, mag, ids_c, *rest = take_rows(per_scene, call)
        return (xy[:, :cut], valid_c[:, :cut], mag[:, :cut], ids_c[:, :cut], *rest)

    shared = (jnp.asarray(stars.unit_vectors, jnp.float32), jnp.asarray(stars.mag, jnp.float32), cells,
              camera.pinhole_numbers(), jnp.float32(math.log(odds)), jnp.float32(max_tol_px),
              jnp.float32(false_per_frame / (camera.width * camera.height)))
    plan = chunk_calls(rows, CHECK_CHUNK, size=check_call_size)  # the camera check's call plan
    rivalled, = run_calls(_rival_kernel, plan, args, shared, n_rows=b, tails=[(n,)], fills=[False],
                          static=dict(grid=index.grid), mesh=batch_mesh(jax.devices()[:1]))
    if not rivalled.any():
        return result
    kept = np.where(rivalled, -1, np.asarray(result.ids))
    lost = np.flatnonzero(np.asarray(result.ok) & ((kept >= 0).sum(axis=1) < MIN_NAMES))
    out = dataclasses.replace(result, ids=jnp.asarray(kept, jnp.int32))
    return out.failed(lost) if lost.size else out
