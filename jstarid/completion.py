"""Naming detections from an attitude, and naming the rest of the frame after any algorithm.

:func:`name_stars` is the shared rule (RpNet's naming passes use it too): a detection, rotated into
ICRS, is named after its nearest catalog star when that star is within the tolerance, the
second-nearest beyond ``isolation`` × the tolerance, and no other detection named by the rule
wants the same star.

The algorithms name what their method covers (MLV its ``n_stars`` brightest detections, SGM the
neighbor circle). :func:`name_from_attitude` takes any :class:`~jstarid.scene.Identification` and
fits the camera to its names: attitude and focal length together (:mod:`jstarid.camera_fit`), so a
lens whose focal length is off by a few % does not put the frame's edge stars where other catalog
stars lie. Names the fit cannot explain are taken back, and a scene whose fit fails is no longer
claimed. It then names the unnamed detections in rounds (the first choosing the focal scale that
explains the most detections, each later one refitting the camera to every name) by
:func:`name_stars` against the catalog stars that can be in the frame
(:func:`~jstarid.sky_index.local_stars`), with a radius that follows the fit's centroid noise and a
brightness check (:func:`magnitude_agrees`), unless the star is already a name in the scene.

Only solved scenes (``ok``) with at least ``min_named`` names are checked and extended (others are
returned as given). A detection of a star fainter than the catalog stays unnamed unless a catalog
star lies within the radius with no other within ``isolation`` × it and a brightness that agrees:
the residual risk, kept small by a tight radius.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.attitude import solve_wahba
from jstarid.camera import Camera
from jstarid.camera_fit import check_claims, unproject_scaled, verify_names
from jstarid.geometry import precise
from jstarid.geometry.angles import angle_between
from jstarid.robust import magnitude_offsets, masked_median
from jstarid.runtime.batching import chunk_calls, run_calls, take_rows
from jstarid.runtime.devices import batch_mesh
from jstarid.runtime.padding import call_width, columns_in_use, next_power_of_two
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Identification, Scene
from jstarid.sky_index import build_sky_index, local_stars

__all__ = ["first_argmax", "magnitude_agrees", "name_from_attitude", "name_stars"]

EXTEND_ROUNDS = 2  # naming rounds of name_from_attitude, each with the camera refitted to all names
SCALE_SCAN = 81  # focal scales tried by the first round (0.25 % apart at max_scale_error = 0.1)
EXTEND_CHUNK = 256  # scenes per call of the naming rounds (padded to a power of two)
# … each cut to the columns its scenes fill, a power of two at least this wide: the scale scan's work
# grows with the columns, and frames hold far fewer detections than the naming capacity (512)
EXTEND_MIN_WIDTH = 64
SCAN_BATCH = 9  # of them evaluated together (memory: SCAN_BATCH × detections × local stars per scene)


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
                       isolation: float = 2.0, min_named: int = 3, k_sigma: float = 5.0,
                       mag_tol: float = 1.0, max_scale_error: float = 0.1,
                       fit_scale: bool = True) -> Identification:
    """Extend ``result`` to every detection the attitude of its named stars explains (module doc).

    The attitude and the focal length are first fitted together to the given names
    (:func:`jstarid.camera_fit.verify_names`): names far from their star (6 σ̂, at least 2.5 px) are
    taken back, and a
    scene whose fit needs the focal length moved by more than ``max_scale_error`` is not solved.
    New names then use the fitted camera, a radius that follows the fit's centroid noise
    (``k_sigma`` σ̂, at most ``tol_px``), and must agree in brightness: a detection's magnitude
    minus its star's may differ from the median of the named stars' by at most ``mag_tol`` (or 3
    robust σ of that difference where the magnitudes scatter more; on the faint side also by as
    much as the star is brighter than the names' median V: saturation), checked from 4 names on
    (:func:`magnitude_agrees`).

    Args:
        catalog: :class:`~jstarid.catalog.Catalog` whose rows ``result.ids`` refers to.
        camera: :class:`~jstarid.camera.Camera` of the scenes (the nominal one).
        scenes: (B, N) :class:`~jstarid.scene.Scene`.
        result: (B, N) :class:`~jstarid.scene.Identification`.
        tol_px: largest distance (px) between a detection and the star it is named after.
        isolation: no second catalog star may lie within ``isolation`` × the naming radius (≥ 1).
        min_named: fewest names a scene needs for its attitude to be used.
        k_sigma: the naming radius in units of the fit's centroid noise σ̂.
        mag_tol: brightness tolerance (mag) of a new name (module doc); ``inf`` turns it off.
        max_scale_error: largest relative focal-length correction of a solved scene.
        fit_scale: fit the focal length (False: attitude only, the nominal camera).

    Returns:
        An :class:`~jstarid.scene.Identification` with the checked and added names, ``ok`` (a scene
        may lose its claim, never gain one), the attitude refitted to all names (NaN where not
        solved) and ``focal_scale`` (NaN where not fitted). A failed scene, or one with fewer than
        ``min_named`` names, is returned as given.

    Raises:
        ValueError: a bad tolerance, isolation factor, ``min_named`` or scale error.
    """
    if not (math.isfinite(tol_px) and tol_px > 0):
        raise ValueError(f"tol_px must be a positive number of pixels, got {tol_px}")
    if not (math.isfinite(isolation) and isolation >= 1):
        raise ValueError(f"isolation must be ≥ 1, got {isolation}")
    if not isinstance(min_named, int | np.integer) or min_named < 2:
        raise ValueError(f"min_named must be an integer ≥ 2 (a rotation needs two stars), got {min_named}")
    if not (math.isfinite(max_scale_error) and 0 <= max_scale_error < 0.5):
        raise ValueError(f"max_scale_error must be in [0, 0.5), got {max_scale_error}")
    if not (k_sigma > 0 and mag_tol > 0):
        raise ValueError(f"k_sigma and mag_tol must be positive, got {k_sigma}, {mag_tol}")
    vectors = jnp.asarray(catalog.unit_vectors, jnp.float32)
    scenes = jax.tree.map(np.asarray, scenes)  # host copies (see camera_fit.verify_names)
    result = jax.tree.map(np.asarray, result)
    # a scene with fewer names than min_named can be neither checked nor extended: left alone
    ids, ok, fit, enough = check_claims(vectors, camera, scenes, result, max_scale_error=max_scale_error,
                                        min_named=int(min_named), fit_scale=fit_scale, star_mags=catalog.mag)
    # a fitted focal length can put stars slightly beyond the nominal field into the frame
    margin = math.atan(isolation * tol_px / camera.f_px) + max_scale_error * camera.half_diagonal_rad
    index = build_sky_index(catalog.unit_vectors, camera.half_diagonal_rad, margin_rad=margin,
                            key=f"{catalog.fingerprint}-complete-{margin:.3e}")
    cells, _ = index.device_arrays()
    use = ok & enough
    star_mag = jnp.asarray(catalog.mag, jnp.float32)
    det_mag = np.asarray(scenes.mag, np.float32)
    fitted = dict(max_scale_error=max_scale_error, min_named=2, fit_scale=fit_scale)
    # rounds of naming and refitting: the first names come from the algorithm's stars (often
    # central ones, a weak lever on the focal length); every round's names reach further out
    shared = (vectors, star_mag, cells, jnp.float32(isolation), jnp.float32(mag_tol),
              jnp.float32(max_scale_error), camera.pinhole_numbers())
    one = batch_mesh(jax.devices()[:1])
    filled = columns_in_use(scenes.valid)
    for k in range(EXTEND_ROUNDS):
        # only the scenes in use, in calls of power-of-two sizes: a batch of any size, most of it
        # unsolved or not, meets a few programs, and the first round's scale scan runs where it counts.
        # No floor of 16 (runtime.call_size): each padding row would repeat the 81-scale scan
        per_scene = tuple(np.asarray(a) for a in (
            fit.attitude, fit.scale, fit.k1, scenes.xy, scenes.valid, det_mag, ids,
            np.clip(k_sigma * np.asarray(fit.sigma_px), min(1.0, tol_px), tol_px)))
        scan = SCALE_SCAN if (k == 0 and fit_scale and max_scale_error > 0) else 0
        rows = np.flatnonzero(np.asarray(use))
        ids, = run_calls(_extend, chunk_calls(rows, EXTEND_CHUNK, size=next_power_of_two),
                         functools.partial(_cut_to_filled, per_scene, filled), shared,
                         n_rows=scenes.batch_size, tails=[(scenes.capacity,)], fills=[-1],
                         out=[np.array(ids, np.int32)], static=dict(grid=index.grid, scan=scan), mesh=one)
        kept, solved, fit = verify_names(vectors, camera, scenes.xy, scenes.valid, ids, use, **fitted)
        ids = jnp.where(use[:, None], kept, ids)  # a name the refitted camera cannot explain goes
        ok = jnp.where(use, solved, ok)
        use = use & solved
    final = fit
    # a failed scene, or one with too few names, is returned as given
    ids = jnp.where(enough[:, None], ids, result.ids)
    attitude = jnp.where(ok[:, None, None], final.attitude, jnp.nan)
    if result.attitude is not None:
        attitude = jnp.where(enough[:, None, None], attitude, result.attitude)
    return Identification(ids=ids, ok=ok, attitude=attitude,
                          focal_scale=jnp.where(enough & ok, final.scale, jnp.nan),
                          distortion_k1=jnp.where(enough & ok, final.k1, jnp.nan))


def magnitude_agrees(det_mag, star_mag, named, candidate, mag_tol):
    """(N,) bool: ``candidate`` names whose magnitude difference (detection − catalog) lies within
    ``max(mag_tol, 3 σ̂)`` of the median difference of the ``named`` detections
    (:func:`jstarid.robust.magnitude_offsets`) — and, on the faint side, also within the amount by
    which the star is brighter than the named stars' median V.

    Why the faint side widens: a saturated star reads fainter than its V, by more the brighter it
    is (Spica on an 8-bit OreSat frame: docs/design/own_sky.md). A detection far *brighter* than its
    star is another object and keeps the plain tolerance, as in the camera check
    (:func:`jstarid.robust.brighter_than_named`).

    Instrumental magnitudes (any zero point) are fine: only differences from the median count.
    Fewer than 4 names: every candidate agrees (no zero point to trust).
    """
    offset, spread, count = magnitude_offsets(det_mag, star_mag, named)
    tol = jnp.maximum(mag_tol, 3.0 * spread)
    saturation = jnp.maximum(masked_median(star_mag, named) - star_mag, 0.0)  # mag, ≥ 0
    return candidate & ((count < 4) | ((offset >= -tol) & (offset <= tol + saturation)))


def _cut_to_filled(per_scene: tuple, filled: np.ndarray, call) -> tuple:
    """A call's rows of ``per_scene`` (attitude, scale, k1, then the (B, N) detection arrays xy,
    valid, mag, ids, then the tolerance), the detection arrays cut to the columns its scenes fill
    (:data:`EXTEND_MIN_WIDTH`); the columns cut hold no detection, so they could take no name."""
    taken = take_rows(per_scene, call, mode="edge")
    cut = call_width(filled, call.rows, taken[3].shape[1], EXTEND_MIN_WIDTH)
    return (*taken[:3], *(a[:, :cut] for a in taken[3:7]), *taken[7:])


@functools.partial(stored_jit, static_argnames=("grid", "scan"))
def _extend(att, scale, k1, xy, valid, mag, ids, tol_px, star_vec, star_mag, cells, isolation, mag_tol, span,
            optics, *, grid, scan):
    """(B, N) ids with the new names of B scenes in use (vmapped over scenes); the tolerances and the
    camera (``optics``: :meth:`~jstarid.camera.Camera.pinhole_numbers`) are traced (no recompile).

    ``scan`` > 0 (static): the focal scale is first chosen among ``scan`` values evenly over
    ``1 ± span`` as the one under which the given names' attitude names the most detections (ties:
    the one nearest 1). Three names cannot fit a scale, and a wrong one puts the frame's edge
    pixels off; the right one names the frame.
    """
    camera = Camera.traced(optics)

    def one(c, s, k1_i, xy_i, valid_i, mag_i, ids_i, tol_i):
        rows, vectors, _ = local_stars(cells, star_vec, c[2], grid)  # c[2] = Cᵀ ẑ, the boresight
        have = ids_i >= 0

        def names(c_s, s_s):
            body = unproject_scaled(camera, xy_i, s_s, k1_i)
            local, named = name_stars(c_s, body, valid_i, vectors, tol_i / (camera.f_px * s_s), isolation)
            row = rows[local]
            taken = jnp.any((ids_i[None, :] == row[:, None]) & have[None, :], axis=1)
            new = ~have & named & ~taken
            star_mag_i = star_mag[jnp.where(have, ids_i, row).clip(0, star_mag.shape[0] - 1)]
            return row, magnitude_agrees(mag_i, star_mag_i, have, new, mag_tol)

        if scan:
            grid_s = 1.0 + span * jnp.linspace(-1.0, 1.0, scan, dtype=jnp.float32)
            ref = star_vec[jnp.clip(ids_i, 0, star_vec.shape[0] - 1)]

            def count(s_s):
                c_s = solve_wahba(unproject_scaled(camera, xy_i, s_s), ref, have.astype(jnp.float32))
                return jnp.sum(names(c_s, s_s)[1]), c_s

            # a few scales at a time: all of them at once hold (scan, N, M) cosines per scene, GBs for
            # a frame of 512 detections against a deep catalog
            counts, cs = jax.lax.map(count, grid_s, batch_size=SCAN_BATCH)
            near_one = jnp.abs(jnp.arange(scan) - (scan - 1) / 2.0)
            best = first_argmax(counts.astype(jnp.float32) * scan - near_one)
            c, s = cs[best], grid_s[best]
        row, new = names(c, s)
        return jnp.where(new, row, ids_i).astype(jnp.int32)

    return jax.vmap(one)(att, scale, k1, xy, valid, mag, ids, tol_px)
