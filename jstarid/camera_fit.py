"""The camera fitted while solving: attitude and focal length from the named stars, and the names
the fit cannot explain taken back.

A focal length off by 1–2 % (an uncalibrated lens, a datasheet value) moves a star at the edge of a
20° frame by 5–15 px, so an attitude fitted with the nominal camera predicts the edge stars in the
wrong place: they go unnamed, or worse, are named after another catalog star that happens to lie
where the wrong model puts them. Fitting the focal length with the attitude removes that error.

**Model.** Pinhole with the nominal principal point and the focal length ``s · f_px``: a detection
at ``xy`` has the camera-frame direction ``(xy − c) / (s f_px)``, ``1`` (normalised). For a fixed
``s`` the attitude is Wahba's problem (:func:`~jstarid.attitude.solve_wahba`); for a fixed attitude
the rotated catalog star projects to ``c + s f_px (v_x, v_y) / v_z``, linear in ``s``, whose least
squares solution is ``s = Σ w (xy − c)·u / (f_px Σ w |u|²)`` with ``u = (v_x, v_y) / v_z``. The two
steps alternate (:data:`ITERATIONS` times; the coupling is weak, so three steps reach float32
precision). The scale is fitted only from :data:`MIN_SCALE_STARS` names on, and only when they
reach away from the principal point (otherwise it is 1). A principal-point offset is not fitted:
to first order it is a rotation, which the attitude absorbs (a 20 px offset leaves sub-pixel
residuals on a 20° frame, checked by the probes in ``tests/algorithms/test_camera_errors.py``).
With :data:`DISTORTION_MIN_STARS` names reaching out into the frame, the verification also fits
one radial distortion term ``k1`` (:func:`fit_distorted`, :func:`project_scaled`; OpenCV's
convention) and keeps it where it is significant: a lens whose edge stars sit pixels off the
pinhole model keeps their names, and ``Identification.distortion_k1`` reports it.

**Robust fit** (:func:`fit_named`). A wrong name among the right ones would pull the fit towards
itself, so a first fit of the attitude alone ranks the names, the attitude and the scale are then
fitted to the better half of them (least trimmed squares, one step),
the centroid noise σ̂ is taken from the median residual (Rayleigh: median = σ √(2 ln 2)), and the
fit is repeated on the names within ``k_sigma`` σ̂ (clipped to ``[min_tol_px, max_tol_px]``), each
name judged by the σ̂ of the others (an externally studentized residual), so that a wrong name
cannot widen its own radius, but never by less than the trimmed σ̂ of every name: the inliers grow
from the better half, and a σ̂ taken from them alone can settle at a fraction of σ. With
``studentized`` (SGM's check) the radius also allows for σ̂'s own scatter over few names
(:func:`studentized_k`: ``k_sigma`` σ̂ becomes the F(2, dof) quantile with the same tail).

**Verification** (:func:`verify_names`). Names outside that radius under the final fit are taken
back; a scene keeps its claim only with ``min_named`` names left, a fitted focal length within
``max_scale_error`` of the nominal one (``--fov-max-error`` in tetra3's terms), and a field that
looks like the fitted sky (:func:`field_seen`, for fits of at most ten names: most of the brightest
stars it puts in the frame were detected). In a fit of at most :data:`FEW_NAMES` names, a name
whose star has a second detection within the radius is taken back too (:func:`_rival_kernel`): a
false detection a few pixels from a star whose own detection the algorithm never saw (it voted
with its brightest detections) bends a few names' fit towards itself, to within the radius,
while the star's own detection stays there. A second detection the fit explains as another
star's light (named, and nearer its own star) is no rival: SGM names every star of its circle,
and a neighbour within the radius took right names back. A failure is always better than a
wrong name.

**Brightness** (:func:`check_claims` with the catalog magnitudes). Before the fit, a name whose
detection is far brighter than its star — beyond the scene's zero point by :data:`BRIGHTER_MAG`,
or :data:`BRIGHTER_SIGMAS` robust σ of the names' offsets where magnitudes scatter more — is taken
back: a bright false star next to the spot of an undetected faint star fits the geometry to a
pixel, never the brightness (found on RpNet at 1 px on ``tetra3_test``). Fainter is allowed:
saturated stars read fainter than their V.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.attitude import solve_wahba
from jstarid.camera import Camera
from jstarid.geometry import precise
from jstarid.geometry.angles import angle_between
from jstarid.geometry.small_linalg import cholesky_solve
from jstarid.robust import brighter_than_named, masked_median
from jstarid.runtime.batching import chunk_calls, run_calls, take_rows
from jstarid.runtime.devices import batch_mesh
from jstarid.runtime.memory_maps import relieve
from jstarid.runtime.padding import (
    MIN_CALL_SIZE,
    call_padded,
    call_width,
    columns_in_use,
    next_power_of_two,
    padded_indices,
)
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import pad_with_empty

__all__ = ["CameraFit", "check_claims", "check_identification", "distort_scenes", "field_seen",
           "fit_distorted", "fit_named", "fit_scaled", "project_scaled", "rescale_scenes", "search_focal",
           "studentized_k", "unproject_scaled", "verify_names"]

ITERATIONS = 4  # Gauss–Newton steps of the joint attitude and scale fit
MIN_SCALE_STARS = 4  # fewest names from which the focal length is fitted (3 rotation + 1 scale)
MIN_LEVER = 0.05  # the names' RMS distance from the principal point must exceed this × f_px
SCALE_RANGE = (0.5, 2.0)  # the fitted scale is clipped to this range (a verification rejects far less)
K_SIGMA = 6.0  # a name is taken back beyond this many σ̂ from its star (a right one: 1 in 6.6e7)
MIN_TOL_PX = 2.5  # … and never within this radius (px): σ̂ of ten names can come out at half σ
MAX_TOL_PX = 10.0  # largest verification radius (px): 5 σ at 2 px per axis, beyond any real tracker
LADDER_MIN_NAMES = 6  # fewest names of a solution found under a rescaled focal length
FEW_RETRIES = 64  # search_focal: up to this many retries (scenes × factors) always run in one call
BATCH_RETRIES = 1  # … and up to this many times the batch size
RETRY_FLOOR = MIN_CALL_SIZE  # … and a retried batch is padded to a coarse size at least this large:
# the smallest call of the algorithms' kernels, so a few retries compile nothing a small batch has not
FEW_NAMES = 10  # up to this many names the robust fit tests each name by leaving it out
DROP_STEPS = 2  # … and drops at most this many
DELETION_RATIO = 3.0  # … each time the others' RMS residual shrinks at least this many times
TRIM_SHARE = 0.8  # the trimmed σ̂ of the refits uses the smallest 80 % of the residuals
REFITS = 4  # fits on the inliers of the previous fit (the inlier set grows from the better half)
FIELD_STARS = 10  # the brightest catalog stars in the fitted frame that the field check looks for
FIELD_FRACTION = 0.5  # … of which at least this share must have a detection
FIELD_SCALES = 81  # focal scales the field check also tries (0.25 % apart at a span of 0.1)
FIELD_MIN = 3  # fewer unnamed stars than this in the window: nothing to judge, the check passes
FIELD_MAX_NAMES = 10  # … and is made only for fits of at most this many names (field_seen)
FIELD_GROUP = 32  # scenes per lax.map group of the check (the catalog is projected per scene)
CHECK_CHUNK = 1024  # scenes per call of the check's kernels (on one device, see verify_names)
CHECK_MIN_CALL = 64  # … padded to a power of two at least this large (fewer programs to compile)
CHECK_MIN_WIDTH = 32  # … and cut to a power of two of columns at least this wide
DISTORTION_MIN_STARS = 12  # fewest inliers from which the radial distortion k1 is fitted
DISTORTION_MIN_REACH = 0.5  # … the farthest of them at least this share of the half diagonal out
K1_SIGNIFICANCE = 4.0  # … and kept only this many standard errors away from 0
K1_RANGE = (-1.0, 1.0)  # the fitted k1 is clipped to this range (normalised coordinates)
DISTORTION_ITERATIONS = 2  # Gauss–Newton steps of each fit with k1 (from a 4-parameter fit: the
# residuals are nearly linear in k1 and the scale)
UNDISTORT_ITERATIONS = 4  # fixed-point steps inverting the radial term (|k1 r²| ≪ 1 on a tracker)
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))  # median / σ of a 2-D Gaussian error's length
BRIGHTER_MAG = 2.0  # a name observed this much brighter than its star (beyond the zero point) is
# taken back (robust.brighter_than_named): above blends (0.75 mag for an equal pair) and the colour
# term of an unfiltered sensor on a red star (≈ 1 mag)
BRIGHTER_SIGMAS = 5.0  # … and beyond this many σ̂ of the scene's named offsets (noisy magnitudes)


class CameraFit(NamedTuple):
    """A fit of attitude and focal length to one scene's names (batched: leading axis B).

    Attributes:
        attitude: (3, 3) ``C`` (ICRS → camera).
        scale: () fitted focal length / nominal focal length (1 where not fitted).
        residual_px: (N,) distance of each detection from where the fit puts its name's star (px);
            meaningful only where the detection is named.
        inlier: (N,) bool, named and within the fit's tolerance.
        sigma_px: () robust centroid noise σ̂ (px per axis) of the names.
        tol_px: () the inlier radius used (px).
        k1: () fitted radial distortion (:func:`project_scaled`; 0 where not fitted).
    """

    attitude: jax.Array
    scale: jax.Array
    residual_px: jax.Array
    inlier: jax.Array
    sigma_px: jax.Array
    tol_px: jax.Array
    k1: jax.Array | float = 0.0


def unproject_scaled(camera, xy, scale, k1=0.0):
    """Pixels (..., 2) → camera-frame unit vectors (..., 3) with the focal length ``scale · f_px``
    and the radial distortion ``k1`` (the inverse of :func:`project_scaled`).

    ``scale`` and ``k1`` broadcast against ``xy[..., 0]`` (a scalar, or one per scene with a
    trailing axis). The distortion is undone by :data:`UNDISTORT_ITERATIONS` fixed-point steps
    ``u ← u_d / (1 + k1 |u|²)`` (each shrinks the error by ``|k1| r²``-fold: 1e-6 after four at
    ``k1 r² = 0.03``).
    """
    f = camera.f_px * scale
    u = (xy[..., 0] - camera.cx) / f
    v = (xy[..., 1] - camera.cy) / f
    if not (isinstance(k1, float) and k1 == 0.0):  # static: no distortion, no steps
        u_d, v_d = u, v
        for _ in range(UNDISTORT_ITERATIONS):
            d = 1.0 + k1 * (u**2 + v**2)
            u, v = u_d / d, v_d / d
    ray = jnp.stack([u, v, jnp.ones_like(u)], axis=-1)
    return ray / jnp.linalg.norm(ray, axis=-1, keepdims=True)


def _rotation_from_vector(theta):
    """(3,) rotation vector → (3, 3) matrix R with ``R v ≈ v + θ × v`` (Rodrigues)."""
    angle = jnp.sqrt(jnp.sum(theta**2) + 1e-30)
    k = theta / angle
    kx = jnp.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], theta.dtype)
    kx2 = precise.small_matmul(kx, kx)
    return jnp.eye(3, dtype=theta.dtype) + jnp.sin(angle) * kx + (1.0 - jnp.cos(angle)) * kx2


def _du_dtheta(v, vz):
    """(N, 2, 3): d(v_x / v_z, v_y / v_z) / dθ for a small rotation ``dv = θ × v`` (the image-plane
    part of the Gauss–Newton Jacobians of :func:`fit_scaled` and :func:`fit_distorted`)."""
    vx, vy = v[:, 0], v[:, 1]
    return jnp.stack([
        jnp.stack([-vx * vy / vz**2, 1.0 + vx**2 / vz**2, -vy / vz], -1),
        jnp.stack([-(1.0 + vy**2 / vz**2), vx * vy / vz**2, vx / vz], -1)], 1)


def fit_scaled(xy, ref, weights, camera, fit_scale=True, *, start=None, iterations: int = ITERATIONS):
    """Attitude and focal scale by least squares on the pixel residuals (module doc), one scene.

    Wahba's solution with the nominal focal length starts :data:`ITERATIONS` Gauss–Newton steps
    on the four parameters (a small rotation θ in the camera frame and the scale s) of the pixel
    residuals ``xy − (c + s f (v_x, v_y) / v_z)``, ``v = R(θ) C r``. Alternating Wahba and the
    scale's closed form converges slowly where the names lie to one side of the frame (a scale
    change there looks like a tilt); the joint step does not.

    Args:
        xy: (N, 2) detections (px). ref: (N, 3) ICRS unit vectors of their names.
        weights: (N,) float, 0 for detections left out.
        camera: the nominal :class:`~jstarid.camera.Camera` (static under jit).
        fit_scale: () bool; False keeps the nominal focal length (Wahba's solution alone).
        start: ``(C, scale)`` to start the Gauss–Newton steps from (a previous fit of nearly the
            same names) instead of Wahba's solution at the nominal focal length.
        iterations: Gauss–Newton steps (static).

    Returns:
        ``(C, scale, residual_px)``: (3, 3), (), (N,) px (angles × the fitted focal length).
    """
    n = jnp.sum(weights > 0)
    centre = jnp.array([[camera.cx, camera.cy]], xy.dtype)
    centred = xy - centre
    lever = jnp.sqrt(jnp.sum(weights * jnp.sum(centred**2, -1)) / jnp.maximum(jnp.sum(weights), 1.0))
    use_scale = fit_scale & (n >= MIN_SCALE_STARS) & (lever > MIN_LEVER * camera.f_px)
    f = camera.f_px
    if isinstance(fit_scale, bool) and not fit_scale:  # static: Wahba's solution is the fit
        c = solve_wahba(camera.unproject(xy), ref, weights)
        return c, jnp.float32(1.0), angle_between(camera.unproject(xy), precise.small_matmul(ref, c.T)) * f
    if start is None:
        c, scale = solve_wahba(camera.unproject(xy), ref, weights), jnp.float32(1.0)
    else:
        c, scale = start[0], jnp.where(use_scale, start[1], 1.0).astype(jnp.float32)
    def step(_, state):  # one Gauss–Newton step: a 4×4 solve and a few sums over the names
        c, scale = state
        v = precise.small_matmul(ref, c.T)  # (N, 3) rotated catalog stars
        front = v[:, 2] > 0.5  # a name far outside the frame carries no information here
        w = jnp.where(front, weights, 0.0)
        vz = jnp.where(front, v[:, 2], 1.0)
        u = v[:, :2] / vz[:, None]  # (N, 2) ideal image-plane coordinates
        resid = centred - f * scale * u  # (N, 2) px
        # d(v_x / v_z) / dθ for dv = θ × v, times f s; and d/ds = f u
        du_dtheta = _du_dtheta(v, vz)  # (N, 2, 3)
        jac = jnp.concatenate([f * scale * du_dtheta, f * u[:, :, None]], axis=2)  # (N, 2, 4)
        normal = precise.einsum("n,nai,naj->ij", w, jac, jac)
        rhs = precise.einsum("n,nai,na->i", w, jac, resid)
        # the scale held where it cannot be fitted: a stiff prior on δs
        stiff = jnp.where(use_scale, 0.0, 1e6 * (jnp.trace(normal) + 1.0))
        normal = normal + jnp.diag(jnp.array([0.0, 0.0, 0.0, 1.0], normal.dtype)) * stiff
        normal = normal + jnp.eye(4, dtype=normal.dtype) * (1e-9 * jnp.trace(normal) + 1e-12)
        delta = cholesky_solve(normal, rhs)
        delta = jnp.where(jnp.all(jnp.isfinite(delta)), delta, 0.0)
        c = precise.small_matmul(_rotation_from_vector(delta[:3]), c)
        return c, jnp.clip(scale + delta[3], SCALE_RANGE[0], SCALE_RANGE[1]).astype(jnp.float32)

    # a loop, not unrolled: the fit is called a dozen times per scene and compile time adds up
    c, scale = jax.lax.fori_loop(0, iterations, step, (c, scale))
    body = unproject_scaled(camera, xy, scale)
    c = jnp.where(use_scale, c, solve_wahba(body, ref, weights))  # scale held: Wahba is exact
    resid = angle_between(body, precise.small_matmul(ref, c.T)) * (f * scale)
    return c, scale, resid


def fit_distorted(xy, ref, weights, camera, *, start, iterations: int = DISTORTION_ITERATIONS):
    """Attitude, focal scale and radial distortion ``k1`` (:func:`project_scaled`) by Gauss–Newton
    on the pixel residuals, one scene, from ``start`` (a fit of :func:`fit_scaled`, or an earlier
    one of this function).

    ``k1`` is fitted only from :data:`DISTORTION_MIN_STARS` names on, the farthest of them at least
    :data:`DISTORTION_MIN_REACH` of the half diagonal from the principal point: the term grows
    with r³, and names near the centre cannot tell it from the scale. Elsewhere it is held at 0 (a
    stiff prior), and so is the scale where :func:`fit_scaled` would hold it.

    Args:
        xy: (N, 2) px. ref: (N, 3) ICRS unit vectors. weights: (N,) float, 0 for left out.
        camera: the nominal camera (static). start: ``(C, scale)`` or ``(C, scale, k1)`` (a fit of
            nearly the same names: the steps start near the answer). iterations: steps (static).

    Returns:
        ``(C, scale, k1, residual_px, fitted)``: (3, 3), (), (), (N,) pixel distances of the
        detections from their names' projections, and () bool, whether ``k1`` was fitted and
        lies :data:`K1_SIGNIFICANCE` standard errors from 0 (otherwise the caller keeps the
        4-parameter fit).
    """
    n = jnp.sum(weights > 0)
    f = camera.f_px
    centred = xy - jnp.array([[camera.cx, camera.cy]], xy.dtype)
    radius2 = jnp.sum(centred**2, -1)
    lever = jnp.sqrt(jnp.sum(weights * radius2) / jnp.maximum(jnp.sum(weights), 1.0))
    reach = jnp.sqrt(jnp.max(jnp.where(weights > 0, radius2, 0.0))) / f
    use_scale = (n >= MIN_SCALE_STARS) & (lever > MIN_LEVER * f)
    use_k1 = ((n >= DISTORTION_MIN_STARS)
              & (reach >= DISTORTION_MIN_REACH * _tan_half_diagonal(camera)))

    def linearize(c, scale, k1):  # normal equations of the pixel residuals, (5, 5) and (5,)
        v = precise.small_matmul(ref, c.T)
        front = v[:, 2] > 0.5  # a name far outside the frame carries no information here
        w = jnp.where(front, weights, 0.0)
        vz = jnp.where(front, v[:, 2], 1.0)
        u = v[:, :2] / vz[:, None]
        r2 = jnp.sum(u**2, -1)
        d = 1.0 + k1 * r2
        resid = centred - f * scale * u * d[:, None]  # (N, 2) px
        du_dtheta = _du_dtheta(v, vz)  # (N, 2, 3)
        # d(u d(u)) / du = d I + 2 k1 u uᵀ
        dpu = d[:, None, None] * jnp.eye(2, dtype=u.dtype)[None] + 2.0 * k1 * u[:, :, None] * u[:, None, :]
        dpu_dtheta = (dpu[:, :, 0, None] * du_dtheta[:, None, 0, :]
                      + dpu[:, :, 1, None] * du_dtheta[:, None, 1, :])  # (N, 2, 3), written out
        jac = jnp.concatenate([f * scale * dpu_dtheta,
                               (f * u * d[:, None])[:, :, None],
                               (f * scale * u * r2[:, None])[:, :, None]], axis=2)  # (N, 2, 5)
        normal = precise.einsum("n,nai,naj->ij", w, jac, jac)
        # a held parameter: a stiff prior on its step
        big = 1e6 * (jnp.trace(normal) + 1.0)
        held = jnp.stack([0.0, 0.0, 0.0, jnp.where(use_scale, 0.0, big), jnp.where(use_k1, 0.0, big)])
        normal = normal + jnp.diag(held) + jnp.eye(5, dtype=normal.dtype) * (1e-9 * jnp.trace(normal) + 1e-12)
        return normal, precise.einsum("n,nai,na->i", w, jac, resid), resid, front, w

    def step(_, state):
        c, scale, k1 = state
        normal, rhs, _, _, _ = linearize(c, scale, k1)
        delta = cholesky_solve(normal, rhs)
        delta = jnp.where(jnp.all(jnp.isfinite(delta)), delta, 0.0)
        c = precise.small_matmul(_rotation_from_vector(delta[:3]), c)
        scale = jnp.clip(scale + delta[3], SCALE_RANGE[0], SCALE_RANGE[1]).astype(jnp.float32)
        return c, scale, jnp.clip(k1 + delta[4], K1_RANGE[0], K1_RANGE[1]).astype(jnp.float32)

    k1_start = start[2] if len(start) > 2 else jnp.float32(0.0)
    c, scale, k1 = jax.lax.fori_loop(0, iterations, step, (start[0], start[1], k1_start))
    normal, _, resid, front, w = linearize(c, scale, k1)
    r = jnp.linalg.norm(resid, axis=-1)
    # k1's standard error from the covariance σ̂² N⁻¹: kept only where it is significant, since a
    # free k1 trades off against the scale where the names lie to one side, and would cost the
    # scale its precision on a lens without distortion
    sigma2 = jnp.sum(w * r**2) / jnp.maximum(2.0 * n.astype(jnp.float32) - 5.0, 1.0)
    n_inv_44 = cholesky_solve(normal, jnp.eye(5, dtype=normal.dtype)[4])[4]  # (N⁻¹)₄₄
    k1_se = jnp.sqrt(jnp.maximum(n_inv_44 * sigma2, 0.0))
    significant = use_k1 & (jnp.abs(k1) >= K1_SIGNIFICANCE * k1_se)
    return c, scale, k1, jnp.where(front, r, jnp.inf), significant


def _tan_half_diagonal(camera):
    """tan of :attr:`~jstarid.camera.Camera.half_diagonal_rad`, written with array operations so that
    it holds for a :meth:`~jstarid.camera.Camera.traced` camera too."""
    dx = jnp.maximum(camera.cx, camera.width - 1 - camera.cx)
    dy = jnp.maximum(camera.cy, camera.height - 1 - camera.cy)
    return jnp.hypot(dx, dy) / camera.f_px


def fit_named(xy, ref, named, camera, *, k_sigma, min_tol_px, max_tol_px, fit_scale=True,
              few: bool | None = None, fit_distortion: bool = False, studentized=False) -> CameraFit:
    """The robust fit of one scene (module doc): all names, the better half, then the inliers.

    Args:
        xy: (N, 2) px. ref: (N, 3) ICRS vectors of the names. named: (N,) bool.
        camera: nominal camera (static). k_sigma: inlier radius in σ̂. min_tol_px, max_tol_px: its
            clip (px). fit_scale: fit the focal length.
        studentized: () bool (may be traced): the radius is :func:`studentized_k` ``(k_sigma, dof)``
            σ̂, where σ̂ has ``dof`` degrees of freedom, rather than ``k_sigma`` σ̂ (which holds for a
            known σ only).

    Returns:
        :class:`CameraFit`.
    """
    def radius(sigma, dof):  # px, before the clip
        return jnp.where(studentized, studentized_k(k_sigma, dof), k_sigma) * sigma

    # the first fit is the attitude alone: with a gross outlier among the names a free scale
    # could run away, and even a rotation is pulled by degrees by one name from elsewhere in the
    # sky, so the better half of the names is chosen twice (the second time from a fit without
    # the outlier) before the scale is fitted to it
    r = fit_scaled(xy, ref, named.astype(jnp.float32), camera, False)[2]
    for scaled in (False, fit_scale):
        better = named & (r <= masked_median(r, named))
        use = jnp.where(jnp.sum(better) >= 3, better, named)
        r = fit_scaled(xy, ref, use.astype(jnp.float32), camera, scaled)[2]
    # a few names (MLV names at most its 10 brightest): half of them cannot fit the scale, so a
    # wrong name is found by deletion instead: each name is left out in turn, and the one whose
    # absence shrinks the others' residuals most is dropped when they shrink DELETION_RATIO-fold
    # and the left-out name then lies beyond k_sigma of them (and min_tol_px). One wrong name among
    # five bends a 4-parameter fit to 1.5–2 px residuals on all of them; without it they are 0.2.
    is_few = jnp.sum(named) <= FEW_NAMES if few is None else few
    if few is not False:
        r_few = _few_names_fit(xy, ref, named, camera, fit_scale, k_sigma=k_sigma, min_tol_px=min_tol_px)
        r = jnp.where(is_few, r_few, r)
    # σ̂ from the median over every name: robust while fewer than half of the names are wrong
    sigma = masked_median(r, named) / RAYLEIGH_MEDIAN
    p = 4.0 if fit_scale is not False else 3.0  # parameters fitted: rotation (+ scale)
    # (the median's σ̂ is given the dof of an RMS over every name: an approximation, for the first
    # radius only; the deletions of _few_names_fit keep their plain k_sigma, stricter is safe there)
    tol = jnp.clip(radius(sigma, 2.0 * jnp.sum(named).astype(jnp.float32) - p), min_tol_px, max_tol_px)
    # with many names the refits grow from the better half under the current fit (a clean core):
    # wrong names that lie together on one side pull a fit of every name towards themselves, and
    # inflate the median with the right names' residuals
    core = named & (r <= masked_median(r, named))
    inlier = jnp.where(is_few, named & (r <= tol), core)
    # then refitted on the inliers, REFITS times: at a large scale error the better half lies near
    # the principal point and fixes the scale roughly; the fit on every inlier reaches the edge
    # stars the first radius left out. σ comes from the inliers' RMS over their degrees of freedom
    # (2n − 3, or 2n − 4 with the scale): with a dozen names the median alone can come out at half
    # the true σ and would take right names back. Each inlier is judged by the σ of the *others*
    # (an externally studentized residual): a wrong name's own residual would widen its own radius
    # — one 9 px name among twenty right ones at 0.5 px inflates the plain RMS to 1.5 px, a 9 px
    # radius — and it pulls the fitted scale by a few tenths of a percent while it stays.

    def refit(_, state):
        inlier = state[0]
        c, scale, r = fit_scaled(xy, ref, inlier.astype(jnp.float32), camera, fit_scale)
        dof = 2.0 * jnp.sum(inlier).astype(jnp.float32) - p
        ss = jnp.sum(jnp.where(inlier, r**2, 0.0))
        ss_others = jnp.where(inlier, ss - r**2, ss)
        dof_others = jnp.where(inlier, dof - 2.0, dof)
        sigma_others = jnp.sqrt(jnp.maximum(ss_others, 0.0) / jnp.maximum(dof_others, 1.0))
        # … and by a trimmed σ̂ (two wrong names side by side would each widen the other's radius).
        # Both come from the inliers, which grow from the better half: names chosen for their small
        # residuals, whose RMS under a fit to themselves understates σ — at σ = 1.5 px the radius
        # sat at min_tol_px with σ̂ = 0.4–0.5 px, a fixed point that took back right names 3–5 px
        # out. The trimmed σ̂ over every name does not depend on the inliers (robust while fewer
        # than 1 − TRIM_SHARE of the names are wrong) and bounds σ̂ from below.
        sigma_i = jnp.maximum(jnp.minimum(sigma_others, _trimmed_sigma(r, inlier)),
                              _trimmed_sigma(r, named))
        grown = named & (r <= jnp.clip(radius(sigma_i, dof_others), min_tol_px, max_tol_px))
        return grown, inlier, c, scale, r

    # loops, not unrolled (here and below): each fit traced once keeps a fresh process's tracing and
    # compilation of the check's kernels short. The last of the REFITS + 1 rounds is the fit on the
    # last inliers (the inliers it chooses are not used)
    start = (inlier, inlier, jnp.eye(3, dtype=jnp.float32), jnp.float32(1.0),
             jnp.zeros(named.shape, jnp.float32))
    _, inlier, c, scale, r = jax.lax.fori_loop(0, REFITS + 1, refit, start)
    dof = jnp.maximum(2.0 * jnp.sum(inlier).astype(jnp.float32) - p, 1.0)
    sigma = jnp.sqrt(jnp.sum(jnp.where(inlier, r**2, 0.0)) / dof)
    tol = jnp.clip(radius(sigma, dof), min_tol_px, max_tol_px)
    inlier = named & (r <= tol)
    if not fit_distortion:
        return CameraFit(c, scale, r, inlier, sigma, tol, jnp.float32(0.0))
    # a lens's radial distortion moves the edge stars by pixels, which the 4-parameter fit can only
    # reject: a fit with k1 on the inliers, the inliers chosen again under it, and refitted
    def distorted(_, state):
        start, c, scale, r, sigma, tol, inlier, k1_out = state
        c_d, s_d, k1, r_d, fitted = fit_distorted(xy, ref, inlier.astype(jnp.float32), camera, start=start)
        dof_d = jnp.maximum(2.0 * jnp.sum(inlier).astype(jnp.float32) - p - 1.0, 1.0)
        sigma_d = jnp.sqrt(jnp.sum(jnp.where(inlier, r_d**2, 0.0)) / dof_d)
        tol_d = jnp.clip(radius(sigma_d, dof_d), min_tol_px, max_tol_px)
        inlier_d = named & (r_d <= tol_d)
        keep = fitted & (jnp.sum(inlier_d) >= DISTORTION_MIN_STARS)
        return ((c_d, s_d, k1), jnp.where(keep, c_d, c), jnp.where(keep, s_d, scale),
                jnp.where(keep, r_d, r), jnp.where(keep, sigma_d, sigma), jnp.where(keep, tol_d, tol),
                jnp.where(keep, inlier_d, inlier), jnp.where(keep, k1, k1_out))

    zero = jnp.zeros((), scale.dtype)
    state = ((c, scale, zero), c, scale, r, sigma, tol, inlier, zero)
    _, c, scale, r, sigma, tol, inlier, k1_out = jax.lax.fori_loop(0, 2, distorted, state)
    return CameraFit(c, scale, r, inlier, sigma, tol, k1_out)


def studentized_k(k_sigma, dof):
    """The radius, in σ̂, that a right name exceeds as rarely as it exceeds ``k_sigma`` σ when σ̂ is
    estimated from ``dof`` degrees of freedom.

    For a 2-D Gaussian error of σ per axis, ``P(r > k σ) = exp(−k²/2)``; with σ̂² an independent
    χ²_dof / dof estimate, ``r² / (2 σ̂²)`` is F(2, dof) distributed, whose tail is
    ``(1 + r² / (dof σ̂²))^(−dof/2)``. Equal tails give ``k' = √(dof (exp(k²/dof) − 1))``, which
    tends to ``k`` as dof grows (k = 6: 11.6 at dof 16, 8.8 at 26, 6.6 at 100). With a dozen names
    σ̂ scatters by about 15 % (1 / √(2 dof)), and ``k σ̂`` alone took back right names 3–4 px out
    at σ = 1 px (SGM's paper scenes: σ̂ 0.50 px over 11 names, a right name 3.09 px out).

    Args:
        k_sigma: the radius for a known σ. dof: σ̂'s degrees of freedom (≥ 1 is used).

    Returns:
        The radius in σ̂ (same shape as ``dof``).
    """
    d = jnp.maximum(jnp.asarray(dof, jnp.float32), 1.0)
    # exp(80) ≈ 5.5e34 is still finite in float32 and far beyond any radius clip
    return jnp.sqrt(d * jnp.expm1(jnp.minimum(k_sigma**2 / d, 80.0)))


def _trimmed_sigma(r, mask):
    """σ̂ (px per axis) from the smallest :data:`TRIM_SHARE` of the residual lengths ``r[mask]``:
    for a 2-D Gaussian error, ``E[r² | r below its q-quantile] = 2σ² (1 − (1 − q)(1 − ln(1 − q))) / q``
    (1.196 σ² at q = 0.8), robust while under 1 − q of the names are wrong."""
    n = jnp.sum(mask)
    keep = jnp.maximum(jnp.floor(TRIM_SHARE * n), 1.0)
    smallest = jnp.sort(jnp.where(mask, r, jnp.inf))
    first = jnp.arange(r.shape[0]) < keep
    mean_sq = jnp.sum(jnp.where(first, smallest**2, 0.0)) / keep
    q = TRIM_SHARE
    factor = 2.0 * (1.0 - (1.0 - q) * (1.0 - math.log(1.0 - q))) / q
    return jnp.where(n >= 2, jnp.sqrt(mean_sq / factor), jnp.inf)


def _few_names_fit(xy, ref, named, camera, fit_scale, *, k_sigma, min_tol_px):
    """Residuals (N,) px of the fit on the names of a scene with at most :data:`FEW_NAMES` names,
    after up to :data:`DROP_STEPS` deletions (see :func:`fit_named`)."""
    n = named.shape[0]
    slots = jnp.argsort(~named, stable=True)[:min(FEW_NAMES, n)]  # the names first (static size)
    use = named[slots]
    sxy, sref = xy[slots], ref[slots]
    k = slots.shape[0]
    p = 4.0 if fit_scale is not False else 3.0

    def rms(r, mask):
        dof = jnp.maximum(2.0 * jnp.sum(mask).astype(jnp.float32) - p, 1.0)
        return jnp.sqrt(jnp.sum(jnp.where(mask, r**2, 0.0)) / dof)

    def deletion(_, use):
        # row 0 every name in use, row i + 1 all but name i: one vmapped fit (one copy in the program)
        masks = jnp.concatenate([use[None, :], use[None, :] & ~jnp.eye(k, dtype=bool)])
        r_masks = jax.vmap(lambda m: fit_scaled(sxy, sref, m.astype(jnp.float32), camera, fit_scale)[2])(
            masks)
        r_all, without, r_wo = r_masks[0], masks[1:], r_masks[1:]
        rms_wo = jax.vmap(rms)(r_wo, without)
        i = jnp.argmin(jnp.where(use, rms_wo, jnp.inf))
        drop = ((jnp.sum(use) > MIN_SCALE_STARS) & (rms_wo[i] * DELETION_RATIO < rms(r_all, use))
                & (r_wo[i, i] > jnp.maximum(k_sigma * rms_wo[i], min_tol_px)))
        return use & ~(drop & (jnp.arange(k) == i))

    use = jax.lax.fori_loop(0, DROP_STEPS, deletion, use)
    mask = jnp.zeros_like(named).at[slots].set(use)
    return fit_scaled(xy, ref, mask.astype(jnp.float32), camera, fit_scale)[2]


def verify_names(star_vectors, camera, xy, valid, ids, ok, *, k_sigma: float = K_SIGMA,
                 min_tol_px: float = MIN_TOL_PX, max_tol_px: float = MAX_TOL_PX, max_scale_error: float = 0.1,
                 min_named: int = 3, fit_scale: bool = True, fit_distortion: bool = True,
                 studentized: bool = False):
    """Fit attitude and focal length to each scene's names and take back the names the fit cannot
    explain (module doc). Batched over scenes.

    The work is split on the host so that each scene pays only for the steps it needs: scenes of
    at most :data:`FEW_NAMES` names are fitted with the leave-one-out deletions, the others with
    the plain robust fit, each scene's names packed first and each call cut to the columns its
    names fill; only the fits of at most :data:`FIELD_MAX_NAMES` inliers go on to the field check
    (:func:`field_seen`, which projects the catalog once per scene). Calls hold at most
    :data:`CHECK_CHUNK` scenes, padded to a power of two (at least :data:`CHECK_MIN_CALL`: one
    program per size class), on one device. On RpNet's benchmark (4,096 scenes, 2 CPU cores) the
    grouping took the check from 1,751 to ≈ 19,000 scenes/s with its calls split over both
    devices (8f28d36, experiments/RESULTS.md), before they stalled there and moved to one.

    Args:
        star_vectors: (M, 3) ICRS unit vectors; ``ids`` are rows of it.
        camera: the nominal :class:`~jstarid.camera.Camera` (static).
        xy: (B, N, 2) px. valid: (B, N) bool. ids: (B, N) int32, −1 unnamed. ok: (B,) bool.
        k_sigma, min_tol_px, max_tol_px: a name is kept within ``clip(k_sigma · σ̂, min, max)`` px
            (the check is for names that are far off, not for the last fraction of a pixel). The
            cap matters where σ̂ itself is unreliable: with 3 names, one of them wrong, the median
            residual is large.
        max_scale_error: largest ``|s − 1|`` of a solved scene.
        min_named: fewest names a solved scene keeps.
        fit_scale: fit the focal length (False: the nominal camera, attitude only).
        fit_distortion: with ``fit_scale``, also fit one radial distortion term where a scene's
            inliers allow it (:func:`fit_distorted`); ``fit.k1`` is 0 elsewhere.
        studentized: the radius allows for the scatter of σ̂ (:func:`studentized_k`). It is
            26.7 σ̂ over 6 names with the scale (dof 8) and 180 σ̂ over 4, so a few names' radius
            sits at ``max_tol_px`` and a wrong name a few pixels off is then caught only by the
            leave-one-out deletions: SGM turns it on (its full-size
            Table 2 has no wrong name with it); MLV and RpNet, which name at most 10 stars and
            often 3–6, keep the plain radius.

    Returns:
        ``(ids, ok, fit)``: (B, N) the kept names (all −1 in a scene that is not solved), (B,) bool,
        and the batched :class:`CameraFit` (its attitude NaN where not solved; scale 1 and residuals,
        σ̂ and radius NaN in scenes that were not claimed).
    """
    # host copies: the groups are chosen on the host (scenes sharded by simulate(shard=True) are
    # gathered here)
    star_vectors, xy, valid, ids, ok = (np.asarray(a) for a in (star_vectors, xy, valid, ids, ok))
    xy = xy.astype(np.float32)
    ids = ids.astype(np.int32)
    b, n = ids.shape
    named = valid & (ids >= 0) & ok[:, None]
    count = named.sum(axis=1)
    # traced, studentized too: the check's and the naming's kernels are one program per shape
    limits = (jnp.float32(k_sigma), jnp.float32(min_tol_px), jnp.float32(max_tol_px), jnp.bool_(studentized))
    attitude = np.full((b, 3, 3), np.nan, np.float32)
    scale = np.ones(b, np.float32)
    residual = np.full((b, n), np.nan, np.float32)
    inlier = np.zeros((b, n), bool)
    sigma = np.full(b, np.nan, np.float32)
    tol = np.full(b, np.nan, np.float32)
    k1 = np.zeros(b, np.float32)
    vectors = jnp.asarray(star_vectors, jnp.float32)
    # the camera travels as traced numbers and the names' vectors are gathered here: one program
    # serves every camera and catalog of the same shapes (compiling one took ≈ 4 s on 2 cores)
    optics = camera.pinhole_numbers()
    ref = star_vectors.astype(np.float32)[np.clip(ids, 0, len(star_vectors) - 1)]
    one = batch_mesh(jax.devices()[:1])
    static = dict(fit_scale=bool(fit_scale),
                  fit_distortion=bool(fit_scale and fit_distortion))
    # each scene's names packed first, and each call cut to the columns its names need (a power
    # of two, at most FEW_NAMES for the few-names group): the fits' work follows the names, not
    # the scenes' capacity
    order = np.argsort(~named, axis=1, kind="stable")
    packed = tuple(np.take_along_axis(a, order if a.ndim == 2 else order[..., None], axis=1)
                   for a in (xy, named, ref))

    def width(call, filled):
        return check_width(call, filled, n)

    def columns(call, few):
        return min(FEW_NAMES, n) if few else width(call, count)

    for few in (True, False):
        rows = np.flatnonzero(ok & ((count <= FEW_NAMES) == few))
        if not rows.size:
            continue
        rows = rows[np.argsort(count[rows], kind="stable")]  # calls of similar widths

        def args(call, few=few):
            cut = columns(call, few)
            return tuple(a[:, :cut] for a in take_rows(packed, call))

        # on one device: split over several CPU devices (shard_map around these loops) the
        # kernels stalled now and then, every device idle (seen in SGM's benchmark)
        fit = CameraFit(*run_calls(
            _fit_kernel, chunk_calls(rows, CHECK_CHUNK, size=check_call_size), args, (optics, *limits),
            n_rows=b,
            tails=[(3, 3), (), (n,), (n,), (), (), ()],
            fills=[np.nan, 1.0, np.nan, False, np.nan, np.nan, 0.0], static=dict(static, few=few), mesh=one))
        attitude[rows], scale[rows] = fit.attitude[rows], fit.scale[rows]
        sigma[rows], tol[rows], k1[rows] = fit.sigma_px[rows], fit.tol_px[rows], fit.k1[rows]
        residual[rows[:, None], order[rows]] = fit.residual_px[rows]
        inlier[rows[:, None], order[rows]] = fit.inlier[rows]
    filled = columns_in_use(valid)
    # a few names' fit bends towards a wrong one (a false detection beside its star, whose own
    # detection the algorithm never saw): a name whose star has a second detection within the
    # radius is one the fit cannot decide between, and is taken back
    rows = np.flatnonzero(ok & (count <= FEW_NAMES))
    if rows.size:
        width_few = min(FEW_NAMES, n)
        own = order[:, :width_few].astype(np.int32)  # the names' columns (names packed first)
        names = (packed[2][:, :width_few], np.take_along_axis(inlier, own, axis=1), own, xy, valid, ref,
                 inlier, attitude, scale, k1, tol)

        def rival_args(call):  # the detections cut to the columns they fill
            ref_c, named_c, own_c, xy_c, valid_c, their_ref, theirs, *rest = take_rows(names, call)
            cut = width(call, filled)
            return (ref_c, named_c, own_c, xy_c[:, :cut], valid_c[:, :cut], their_ref[:, :cut],
                    theirs[:, :cut], *rest)

        rival, = run_calls(_rival_kernel, chunk_calls(rows, CHECK_CHUNK, size=check_call_size), rival_args,
                           (optics,), n_rows=b, tails=[(width_few,)], fills=[False], mesh=one)
        inlier[rows[:, None], own[rows]] &= ~rival[rows]
    solved = (ok & (inlier.sum(axis=1) >= min_named) & (np.abs(scale - 1.0) <= max_scale_error))
    # the field check only where a handful of names could fit a wrong sky (field_seen)
    rows = np.flatnonzero(solved & (inlier.sum(axis=1) <= FIELD_MAX_NAMES))
    fitted = (xy, valid, np.where(inlier, ids, -1), attitude, scale, tol)

    def field_args(call):  # each call cut to the columns its detections fill, as the fits' are
        cut = width(call, filled)
        xy_c, valid_c, ids_c, *rest = take_rows(fitted, call)
        return (xy_c[:, :cut], valid_c[:, :cut], ids_c[:, :cut], *rest)
    # first under the fitted focal length alone, then, for the scenes that fail there, under the
    # FIELD_SCALES others too: the same answer (a pass under one scale passes the maximum), and most
    # right skies pass at once (the scale search was 2/3 of MLV's identify time)
    for n_scales in (0, FIELD_SCALES):
        if not rows.size:
            break
        seen, = run_calls(_field_kernel, chunk_calls(rows, CHECK_CHUNK, size=check_call_size),
                          field_args, (vectors, optics, jnp.float32(max_scale_error)),
                          n_rows=b, tails=[()], fills=[False], static=dict(n_scales=n_scales), mesh=one)
        rows = rows[~seen[rows]]
    solved[rows] = False
    kept = np.where(solved[:, None] & inlier, ids, -1).astype(np.int32)
    fit = CameraFit(attitude=jnp.asarray(np.where(solved[:, None, None], attitude, np.nan)),
                    scale=jnp.asarray(scale), residual_px=jnp.asarray(residual),
                    inlier=jnp.asarray(inlier & solved[:, None]), sigma_px=jnp.asarray(sigma),
                    tol_px=jnp.asarray(tol), k1=jnp.asarray(k1))
    return jnp.asarray(kept), jnp.asarray(solved), fit


@functools.partial(stored_jit, static_argnames=("fit_scale", "few", "fit_distortion"))
def _fit_kernel(xy, named, ref, optics, k_sigma, min_tol_px, max_tol_px, studentized, *, fit_scale, few,
                fit_distortion):
    """:func:`fit_named` of each scene (B, N) of :func:`verify_names` (``few``: its static branch);
    ``ref`` (B, N, 3) the names' ICRS vectors, ``optics`` the camera's
    :meth:`~jstarid.camera.Camera.pinhole_numbers`."""
    camera = Camera.traced(optics)

    def one(xy_i, named_i, ref_i):
        return fit_named(xy_i, ref_i, named_i, camera, k_sigma=k_sigma, min_tol_px=min_tol_px,
                         max_tol_px=max_tol_px, fit_scale=fit_scale, few=few,
                         fit_distortion=fit_distortion and not few, studentized=studentized)

    return jax.vmap(one)(xy, named, ref)


@functools.partial(stored_jit, static_argnames=("n_scales",))
def _field_kernel(xy, valid, ids, attitude, scale, tol, star_vectors, optics, span, *, n_scales):
    """(B,) bool: :func:`field_seen` of each scene, in :data:`FIELD_GROUP`-scene groups (each
    projects the whole catalog); ``optics`` the camera's :meth:`~jstarid.camera.Camera.pinhole_numbers`."""
    camera = Camera.traced(optics)

    def one(a):
        xy_i, valid_i, ids_i, att_i, scale_i, tol_i = a
        fit = CameraFit(att_i, scale_i, None, None, None, tol_i)
        return field_seen(star_vectors, camera, xy_i, valid_i, ids_i, fit, span, n_scales=n_scales)

    return jax.lax.map(one, (xy, valid, ids, attitude, scale, tol), batch_size=min(FIELD_GROUP, xy.shape[0]))


@stored_jit
def _rival_kernel(ref, named, own, xy, valid, their_ref, theirs, attitude, scale, k1, tol, optics):
    """(B, K) bool: the names (``ref`` (B, K, 3) their stars, ``named`` (B, K), ``own`` (B, K) int32
    their detections' columns) whose star, under the fit, has another valid detection of ``xy``
    (B, N, 2) within the radius ``tol`` (B,) px — unless the fit explains that detection as another
    star's light: it is named (``theirs`` (B, N) bool, ``their_ref`` (B, N, 3) its star) and lies
    nearer its own star than this one. Distances as the fit's residuals: the angle between the
    detection's ray (:func:`unproject_scaled`, fitted scale and k1) and the star, times the fitted
    focal length."""
    camera = Camera.traced(optics)
    rays = unproject_scaled(camera, xy, scale[:, None], k1[:, None])  # (B, N, 3)
    stars = precise.einsum("bij,bkj->bki", attitude, ref)  # (B, K, 3) camera frame
    dist = angle_between(stars[:, :, None, :], rays[:, None, :, :])  # (B, K, N) rad
    their_stars = precise.einsum("bij,bnj->bni", attitude, their_ref)  # (B, N, 3)
    explained = theirs[:, None, :] & (angle_between(their_stars, rays)[:, None, :] < dist)  # (B, K, N)
    others = valid[:, None, :] & (jnp.arange(xy.shape[1])[None, None, :] != own[..., None]) & ~explained
    near = dist * (camera.f_px * scale)[:, None, None] <= tol[:, None, None]
    return named & jnp.any(others & near, axis=2)


def field_seen(star_vectors, camera, xy, valid, ids, fit: CameraFit, span=0.0, *,
               n_scales: int = FIELD_SCALES):
    """() bool: the fitted camera sees the sky it claims — of the :data:`FIELD_STARS` brightest
    catalog stars it puts inside the frame, those not named (if :data:`FIELD_MIN` or more) have a
    detection within the fit's radius ``fit.tol_px`` in at least :data:`FIELD_FRACTION` of cases.

    A handful of names can fit a wrong attitude (4 names and 4 parameters); the other bright stars
    of that wrong sky then land where nothing was detected. :func:`verify_names` asks only fits of
    at most :data:`FIELD_MAX_NAMES` names: more names within k σ̂ of a 4-parameter fit leave no
    doubt, and where an algorithm names every detection the bright stars left unnamed are exactly
    the undetected ones, so a right sky with missing stars would fail (RpNet's Fig. 11 with
    5 missing stars, ``quick`` network, 200 scenes: 104 solved with the check on every fit, 185
    without it, none wrong either way). The named stars themselves prove
    nothing and are left out, but the window stays the brightest stars of the frame (a frame cut
    to its brightest detections lacks the faint ones). ``star_vectors`` rows must run brightest
    first (a :class:`~jstarid.catalog.Catalog`'s do).

    Args:
        ids: (N,) the names the fit used (−1 elsewhere).
        span: the window is also looked for under ``n_scales`` focal scales over ``1 ± span``
            (the largest focal-length error allowed).
        n_scales: how many (static; 0: under the fitted scale alone).
    """
    v = precise.small_matmul(star_vectors, fit.attitude.T)  # (M, 3) camera frame
    pred, inside = project_scaled(camera, v, fit.scale)
    named = jnp.zeros(star_vectors.shape[0], bool).at[jnp.where(ids >= 0, ids, star_vectors.shape[0])].set(
        True, mode="drop")
    inside = inside & camera.contains(pred, fit.tol_px)
    rank = jnp.cumsum(inside)
    rows = jnp.nonzero(inside & (rank <= FIELD_STARS), size=FIELD_STARS, fill_value=0)[0]
    have = (jnp.arange(FIELD_STARS) < jnp.minimum(rank[-1], FIELD_STARS)) & ~named[rows]
    radius = jnp.maximum(fit.tol_px, MIN_TOL_PX)
    # a few central names fix the focal length poorly, and the edge of a right sky then misses its
    # stars by pixels: the window is looked for under every scale of 1 ± span (the names' attitude
    # refitted under each); a wrong sky matches under none
    ref = star_vectors[jnp.clip(ids, 0, star_vectors.shape[0] - 1)]
    weight = (ids >= 0).astype(jnp.float32)

    def seen_under(s):
        c = solve_wahba(unproject_scaled(camera, xy, s), ref, weight)
        p, _ = project_scaled(camera, precise.small_matmul(star_vectors[rows], c.T), s)
        gap = jnp.linalg.norm(p[:, None, :] - xy[None, :, :], axis=-1)  # (K, N) px
        return jnp.sum(have & jnp.any(valid[None, :] & (gap <= radius), axis=1))

    scales = jnp.concatenate([fit.scale[None],
                              1.0 + span * jnp.linspace(-1.0, 1.0, n_scales, dtype=jnp.float32)])
    seen = jnp.max(jax.vmap(seen_under)(scales))
    n = jnp.sum(have)
    # one or two unnamed stars in the window may be undetected (a close pair, a missed star)
    return (n < FIELD_MIN) | (seen >= FIELD_FRACTION * n)


def project_scaled(camera, v_cam, scale, k1=0.0):
    """Camera-frame vectors (..., 3) → ``(xy, in_field)`` with the focal length ``scale · f_px``
    and one radial distortion term (Brown–Conrady, OpenCV's ``k1``): the ideal normalised
    coordinates ``u = (v_x, v_y) / v_z`` land at ``c + scale · f_px · u (1 + k1 |u|²)``."""
    front = v_cam[..., 2] > 0
    vz = jnp.where(front, v_cam[..., 2], 1.0)
    f = camera.f_px * scale
    u, v = v_cam[..., 0] / vz, v_cam[..., 1] / vz
    d = 1.0 + k1 * (u**2 + v**2)
    x = camera.cx + f * u * d
    y = camera.cy + f * v * d
    inside = (x >= 0) & (x <= camera.width - 1) & (y >= 0) & (y <= camera.height - 1)
    return jnp.stack([x, y], axis=-1), front & inside


def check_identification(star_vectors, camera, scenes, result, *, max_scale_error: float = 0.1,
                         min_named: int = 3, k_sigma: float = K_SIGMA, max_tol_px: float = MAX_TOL_PX,
                         star_mags=None, studentized: bool = False):
    """An algorithm's last step: :func:`verify_names` on the scenes it claims with at least
    ``min_named`` names (fewer cannot be checked: those are returned as they are).

    Args:
        star_vectors: (M, 3) ICRS unit vectors of the rows ``result.ids`` names.
        camera: the nominal camera. scenes: (B, N) scenes. result: the algorithm's
            :class:`~jstarid.scene.Identification`.
        max_scale_error, min_named, k_sigma, max_tol_px: as in :func:`verify_names`. An algorithm
            whose own verification accepts residuals beyond :data:`MAX_TOL_PX` passes its cap
            here (SGM: ``verify.cap_deg``, 15 px on ``sgm2022``), so that the check does not take
            back names at a noise the algorithm was tuned for.
        star_mags: (M,) catalog V of those rows (mag); given, names far brighter than their star
            are taken back first (:func:`check_claims`).
        studentized: as in :func:`verify_names` (SGM's check; MLV and RpNet keep the plain radius).

    Returns:
        The :class:`~jstarid.scene.Identification` with far-off names taken back, scenes whose fit
        fails unclaimed (ids −1), the fitted attitude, ``focal_scale`` and ``distortion_k1`` (NaN
        where not fitted).
    """
    from jstarid.scene import Identification

    ids, ok, fit, enough = check_claims(star_vectors, camera, scenes, result, k_sigma=k_sigma,
                                        max_tol_px=max_tol_px, max_scale_error=max_scale_error,
                                        min_named=min_named, star_mags=star_mags, studentized=studentized)
    attitude = fit.attitude
    if result.attitude is not None:
        attitude = jnp.where(enough[:, None, None], attitude, result.attitude)
    return Identification(ids=ids, ok=ok, attitude=jnp.where(ok[:, None, None], attitude, jnp.nan),
                          focal_scale=jnp.where(enough & ok, fit.scale, jnp.nan),
                          distortion_k1=jnp.where(enough & ok, fit.k1, jnp.nan))


def check_claims(star_vectors, camera, scenes, result, *, min_named: int = 3, star_mags=None, **kwargs):
    """:func:`verify_names` on the claimed scenes with at least ``min_named`` names, the others as
    given.

    With ``star_mags`` ((M,) catalog V, mag), a claimed scene's names observed far brighter than
    their star (:func:`~jstarid.robust.brighter_than_named`: by :data:`BRIGHTER_MAG`, or
    :data:`BRIGHTER_SIGMAS` σ̂ of the scene's magnitude offsets where they scatter more, from 4
    names on) are taken back before the fit: a bright false star or planet next to the position of
    an undetected faint star fits the geometry, not the brightness.

    Returns:
        ``(ids, ok, fit, checked)``: (B, N), (B,), the :class:`CameraFit` of :func:`verify_names`,
        and (B,) bool, the scenes that were checked.
    """
    given = jnp.where(scenes.valid, result.ids, -1)
    if star_mags is not None:
        given = call_padded(_drop_brighter, (jnp.asarray(scenes.mag, jnp.float32), given, result.ok),
                            jnp.asarray(star_mags, jnp.float32))
    checked = result.ok & (jnp.sum(given >= 0, axis=1) >= min_named)
    ids, ok, fit = verify_names(star_vectors, camera, scenes.xy, scenes.valid, given, checked,
                                min_named=min_named, **kwargs)
    return jnp.where(checked[:, None], ids, result.ids), jnp.where(checked, ok, result.ok), fit, checked


@stored_jit
def _drop_brighter(mag, ids, ok, star_mags):
    """(B, N) ids without the names of claimed scenes far brighter than their star (check_claims)."""
    named = (ids >= 0) & ok[:, None]
    far = jax.vmap(functools.partial(brighter_than_named, tol_mag=BRIGHTER_MAG, sigmas=BRIGHTER_SIGMAS))(
        mag, star_mags[jnp.maximum(ids, 0)], named)
    return jnp.where(far, -1, ids)


def rescale_scenes(scenes, camera, scale):
    """The scenes as the nominal camera would see them if its focal length were ``scale · f_px``:
    centroids moved to ``c + (xy − c) / scale`` about the principal point ``c``.

    Unprojecting the moved centroids with the nominal camera gives the directions the original
    centroids have under the camera of focal length ``scale · f_px``.

    Args:
        scale: one factor for every scene, or (B,) one per scene.
    """
    factor = np.asarray(scale, np.float32)
    factor = factor.reshape(-1, 1, 1) if factor.ndim == 1 else factor
    return _move_about_centre(scenes, camera, lambda offset: offset / factor)


def distort_scenes(scenes, camera, k1: float):
    """The scenes as a lens with the radial distortion ``k1`` would show them
    (:func:`project_scaled`): each centroid ``c + f u`` moved to ``c + f u (1 + k1 |u|²)``.

    For probes and tests: the simulator's pinhole scenes seen through a distorting lens.
    """
    def distort(offset):
        r2 = np.sum((offset / np.float32(camera.f_px)) ** 2, -1, keepdims=True)
        return offset * (1.0 + np.float32(k1) * r2)

    return _move_about_centre(scenes, camera, distort)


def _move_about_centre(scenes, camera, move):
    """The scenes with each valid centroid's offset from the principal point replaced by
    ``move(offset)`` ((B, N, 2) px → (B, N, 2) px, host arrays)."""
    centre = np.array([camera.cx, camera.cy], np.float32)
    xy = np.asarray(scenes.xy, np.float32)
    moved = np.where(np.asarray(scenes.valid)[..., None], centre + move(xy - centre), xy)
    return dataclasses.replace(scenes, xy=jnp.asarray(moved, jnp.float32))


def check_width(call, filled: np.ndarray, n: int) -> int:
    """The columns a call of the camera check's kernels keeps (also :mod:`jstarid.rival_stars`'s):
    those its scenes fill (``filled``, :func:`~jstarid.runtime.columns_in_use`) as a power of two ≥
    :data:`CHECK_MIN_WIDTH`, or all ``n`` in a call of the smallest size (:data:`CHECK_MIN_CALL`):
    there the cut saves little and every new width compiled each kernel again (seconds each, in
    fresh batches of 1 scene), so one program per kernel serves every small batch."""
    if call.size <= CHECK_MIN_CALL:
        return int(n)
    return call_width(filled, call.rows, n, CHECK_MIN_WIDTH)


def check_call_size(n: int) -> int:
    """The padded size of a call of the camera check's kernels holding ``n`` scenes (also
    :mod:`jstarid.rival_stars`'s, which runs in the same plan)."""
    return next_power_of_two(n, floor=CHECK_MIN_CALL)




def search_focal(run, result, scenes, camera, scales, *, min_named: int = LADDER_MIN_NAMES):
    """Retry the scenes ``result`` leaves unsolved as if the focal length were each of ``scales`` ×
    the nominal one in turn (:func:`rescale_scenes`), keeping the first solution of each scene.
    Where the retries (scenes × factors) are no more than :data:`BATCH_RETRIES` × the batch or
    :data:`FEW_RETRIES`, they run in one call with the same outcome: a call's fixed cost (SGM's
    search rounds, the kernels' dispatch) outweighs the retries of scenes an earlier factor would
    have solved, and memory stays that of the batch.

    For methods whose features are angles (triangle singular values, pair distances, network
    patterns), a focal length off by more than their tolerance (≈ 1 % for MLV's) loses the scene;
    a ladder of 1 % steps brings it back. The ids of a retry are aligned with the same detections,
    so the camera check that follows (:func:`check_identification`, nominal camera, original
    centroids) fits the actual focal length.

    Args:
        run: ``run(scenes, rows) -> Identification``: the algorithm on moved scenes, ``rows`` their
            indices in the batch (for per-scene settings).
        result: the algorithm's :class:`~jstarid.scene.Identification` of ``scenes``.
        scenes: (B, N) scenes. camera: the nominal camera.
        scales: focal-length factors to try, in order (e.g. ``(0.99, 1.01, 0.98, 1.02)``).
        min_named: fewest names a retry's solution needs to be kept. More tries are more chances
            of a chance match, and a solution under a corrected focal length is checked by a
            4-parameter fit: five names (one of them wrong) can fit it within 2 px.

    Returns:
        The merged :class:`~jstarid.scene.Identification` (``attitude`` as each call gave it).
    """
    ids, ok = np.array(result.ids), np.array(result.ok)
    att = None if result.attitude is None else np.array(result.attitude)
    todo = np.flatnonzero(~ok)
    if 0 < todo.size * len(scales) <= max(FEW_RETRIES, BATCH_RETRIES * scenes.batch_size):
        # few scenes left: every factor in one call (a call's fixed cost dominates there), then
        # each scene keeps the first factor, in order, that solved it: the sequential outcome
        factor = np.repeat(np.asarray(scales, np.float32), todo.size)
        rows = np.tile(todo, len(scales))
        padded = padded_indices(rows, floor=RETRY_FLOOR, coarse=True)
        size = padded.size
        factor = np.concatenate([factor, np.full(size - rows.size, factor[-1])])
        # empty padding scenes: they fail at once, where copies of a scene would repeat its search
        moved = rescale_scenes(pad_with_empty(scenes[rows], size), camera, factor)
        retry = run(moved, padded)
        retry_ids = np.asarray(retry.ids)[: rows.size].reshape(len(scales), todo.size, -1)
        solved = (np.asarray(retry.ok)[: rows.size].reshape(len(scales), todo.size)
                  & (np.sum(retry_ids >= 0, axis=2) >= min_named))
        first = np.argmax(solved, axis=0)  # the first factor that solved each scene
        hit = solved.any(axis=0)
        pick = first[hit], np.flatnonzero(hit)
        ids[todo[hit]], ok[todo[hit]] = retry_ids[pick], True
        if att is not None and retry.attitude is not None:
            att[todo[hit]] = np.asarray(retry.attitude)[: rows.size].reshape(
                len(scales), todo.size, 3, 3)[pick]
        relieve()
        scales = ()
    for scale in scales:
        todo = np.flatnonzero(~ok)
        if not todo.size:
            break
        # the retried batch padded to a coarse size with empty scenes (they fail at once): every
        # new batch size compiles the algorithm's kernels again, and a long run of retries on
        # batches of many sizes would otherwise fill memory with executables
        padded = padded_indices(todo, floor=RETRY_FLOOR, coarse=True)
        retry = run(rescale_scenes(pad_with_empty(scenes[todo], padded.size), camera, float(scale)), padded)
        retry_ids = np.asarray(retry.ids)[: todo.size]
        solved = np.asarray(retry.ok)[: todo.size] & (np.sum(retry_ids >= 0, axis=1) >= min_named)
        rows = todo[solved]
        ids[rows], ok[rows] = retry_ids[solved], True
        if att is not None and retry.attitude is not None:
            att[rows] = np.asarray(retry.attitude)[: todo.size][solved]
        relieve()
    return dataclasses.replace(result, ids=jnp.asarray(ids), ok=jnp.asarray(ok),
                               attitude=None if att is None else jnp.asarray(att))
