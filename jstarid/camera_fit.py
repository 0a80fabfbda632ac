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
residuals on a 20° frame, checked by the probes in ``tests/test_camera_errors.py``).

**Robust fit** (:func:`fit_named`). A wrong name among the right ones would pull the fit towards
itself, so a first fit of the attitude alone ranks the names, the attitude and the scale are then
fitted to the better half of them (least trimmed squares, one step),
the centroid noise σ̂ is taken from the median residual (Rayleigh: median = σ √(2 ln 2)), and the
final fit uses only the names within ``k_sigma`` σ̂ (clipped to ``[min_tol_px, max_tol_px]``).

**Verification** (:func:`verify_names`). Names outside that radius under the final fit are taken
back; a scene keeps its claim only with ``min_named`` names left and a fitted focal length within
``max_scale_error`` of the nominal one (``--fov-max-error`` in tetra3's terms). A failure is always
better than a wrong name.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jstarid.attitude import solve_wahba
from jstarid.geometry import precise
from jstarid.geometry.angles import angle_between
from jstarid.robust import masked_median

__all__ = ["CameraFit", "check_claims", "check_identification", "fit_named", "fit_scaled", "project_scaled",
           "unproject_scaled", "verify_names"]

ITERATIONS = 4  # Gauss–Newton steps of the joint attitude and scale fit
MIN_SCALE_STARS = 4  # fewest names from which the focal length is fitted (3 rotation + 1 scale)
MIN_LEVER = 0.05  # the names' RMS distance from the principal point must exceed this × f_px
SCALE_RANGE = (0.5, 2.0)  # the fitted scale is clipped to this range (a verification rejects far less)
MAX_TOL_PX = 10.0  # largest verification radius (px): 5 σ at 2 px per axis, beyond any real tracker
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))  # median / σ of a 2-D Gaussian error's length


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
    """

    attitude: jax.Array
    scale: jax.Array
    residual_px: jax.Array
    inlier: jax.Array
    sigma_px: jax.Array
    tol_px: jax.Array


def unproject_scaled(camera, xy, scale):
    """Pixels (..., 2) → camera-frame unit vectors (..., 3) with the focal length ``scale · f_px``.

    ``scale`` broadcasts against ``xy[..., 0]`` (a scalar, or one per scene with a trailing axis).
    """
    f = camera.f_px * scale
    u = (xy[..., 0] - camera.cx) / f
    v = (xy[..., 1] - camera.cy) / f
    ray = jnp.stack([u, v, jnp.ones_like(u)], axis=-1)
    return ray / jnp.linalg.norm(ray, axis=-1, keepdims=True)


def _rotation_from_vector(theta):
    """(3,) rotation vector → (3, 3) matrix R with ``R v ≈ v + θ × v`` (Rodrigues)."""
    angle = jnp.sqrt(jnp.sum(theta**2) + 1e-30)
    k = theta / angle
    kx = jnp.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], theta.dtype)
    return jnp.eye(3, dtype=theta.dtype) + jnp.sin(angle) * kx + (1.0 - jnp.cos(angle)) * (kx @ kx)


def fit_scaled(xy, ref, weights, camera, fit_scale=True):
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

    Returns:
        ``(C, scale, residual_px)``: (3, 3), (), (N,) px (angles × the fitted focal length).
    """
    n = jnp.sum(weights > 0)
    centre = jnp.array([[camera.cx, camera.cy]], xy.dtype)
    centred = xy - centre
    lever = jnp.sqrt(jnp.sum(weights * jnp.sum(centred**2, -1)) / jnp.maximum(jnp.sum(weights), 1.0))
    use_scale = fit_scale & (n >= MIN_SCALE_STARS) & (lever > MIN_LEVER * camera.f_px)
    c = solve_wahba(camera.unproject(xy), ref, weights)
    f = camera.f_px
    if isinstance(fit_scale, bool) and not fit_scale:  # static: Wahba's solution is the fit
        return c, jnp.float32(1.0), angle_between(camera.unproject(xy), precise.small_matmul(ref, c.T)) * f
    scale = jnp.float32(1.0)
    for _ in range(ITERATIONS):  # unrolled: each step a 4×4 solve and a few sums over the names
        v = precise.small_matmul(ref, c.T)  # (N, 3) rotated catalog stars
        front = v[:, 2] > 0.5  # a name far outside the frame carries no information here
        w = jnp.where(front, weights, 0.0)
        vz = jnp.where(front, v[:, 2], 1.0)
        u = v[:, :2] / vz[:, None]  # (N, 2) ideal image-plane coordinates
        resid = centred - f * scale * u  # (N, 2) px
        # d(v_x / v_z) / dθ for dv = θ × v, times f s; and d/ds = f u
        vx, vy, vzz = v[:, 0], v[:, 1], vz
        du_dtheta = jnp.stack([
            jnp.stack([-vx * vy / vzz**2, 1.0 + vx**2 / vzz**2, -vy / vzz], -1),
            jnp.stack([-(1.0 + vy**2 / vzz**2), vx * vy / vzz**2, vx / vzz], -1)], 1)  # (N, 2, 3)
        jac = jnp.concatenate([f * scale * du_dtheta, f * u[:, :, None]], axis=2)  # (N, 2, 4)
        normal = jnp.einsum("n,nai,naj->ij", w, jac, jac)
        rhs = jnp.einsum("n,nai,na->i", w, jac, resid)
        # the scale held where it cannot be fitted: a stiff prior on δs
        stiff = jnp.where(use_scale, 0.0, 1e6 * (jnp.trace(normal) + 1.0))
        normal = normal + jnp.diag(jnp.array([0.0, 0.0, 0.0, 1.0], normal.dtype)) * stiff
        normal = normal + jnp.eye(4, dtype=normal.dtype) * (1e-9 * jnp.trace(normal) + 1e-12)
        step = jnp.linalg.solve(normal, rhs)
        step = jnp.where(jnp.all(jnp.isfinite(step)), step, 0.0)
        c = _rotation_from_vector(step[:3]) @ c
        scale = jnp.clip(scale + step[3], SCALE_RANGE[0], SCALE_RANGE[1]).astype(jnp.float32)
    body = unproject_scaled(camera, xy, scale)
    c = jnp.where(use_scale, c, solve_wahba(body, ref, weights))  # scale held: Wahba is exact
    resid = angle_between(body, precise.small_matmul(ref, c.T)) * (f * scale)
    return c, scale, resid


def fit_named(xy, ref, named, camera, *, k_sigma, min_tol_px, max_tol_px, fit_scale=True) -> CameraFit:
    """The robust fit of one scene (module doc): all names, the better half, then the inliers.

    Args:
        xy: (N, 2) px. ref: (N, 3) ICRS vectors of the names. named: (N,) bool.
        camera: nominal camera (static). k_sigma: inlier radius in σ̂. min_tol_px, max_tol_px: its
            clip (px). fit_scale: fit the focal length.

    Returns:
        :class:`CameraFit`.
    """
    # the first fit is the attitude alone: with a gross outlier among the names a free scale
    # could run away, and even a rotation is pulled by degrees by one name from elsewhere in the
    # sky, so the better half of the names is chosen twice (the second time from a fit without
    # the outlier) before the scale is fitted to it
    r = fit_scaled(xy, ref, named.astype(jnp.float32), camera, False)[2]
    for scaled in (False, fit_scale):
        better = named & (r <= masked_median(r, named))
        use = jnp.where(jnp.sum(better) >= 3, better, named)
        r = fit_scaled(xy, ref, use.astype(jnp.float32), camera, scaled)[2]
    # σ̂ from the median over every name: robust while fewer than half of the names are wrong
    sigma = masked_median(r, named) / RAYLEIGH_MEDIAN
    tol = jnp.clip(k_sigma * sigma, min_tol_px, max_tol_px)
    inlier = named & (r <= tol)
    # twice: at a large scale error the better half lies near the principal point and fixes the
    # scale roughly; the fit on every inlier reaches the edge stars the first radius left out
    for _ in range(2):
        c, scale, r = fit_scaled(xy, ref, inlier.astype(jnp.float32), camera, fit_scale)
        inlier = named & (r <= tol)
    return CameraFit(c, scale, r, inlier, sigma, tol)


def verify_names(star_vectors, camera, xy, valid, ids, ok, *, k_sigma: float = 5.0,
                 min_tol_px: float = 1.0, max_tol_px: float = MAX_TOL_PX, max_scale_error: float = 0.1,
                 min_named: int = 3, fit_scale: bool = True):
    """Fit attitude and focal length to each scene's names and take back the names the fit cannot
    explain (module doc). Batched over scenes.

    Args:
        star_vectors: (M, 3) ICRS unit vectors; ``ids`` are rows of it.
        camera: the nominal :class:`~jstarid.camera.Camera` (static).
        xy: (B, N, 2) px. valid: (B, N) bool. ids: (B, N) int32, −1 unnamed. ok: (B,) bool.
        k_sigma, min_tol_px, max_tol_px: a name is kept within ``clip(k_sigma · σ̂, min, max)`` px
            (5 σ̂ loses one right name in 270,000: the check is for names that are far off). The
            cap matters where σ̂ itself is unreliable: with 3 names, one of them wrong, the median
            residual is large.
        max_scale_error: largest ``|s − 1|`` of a solved scene.
        min_named: fewest names a solved scene keeps.
        fit_scale: fit the focal length (False: the nominal camera, attitude only).

    Returns:
        ``(ids, ok, fit)``: (B, N) the kept names (all −1 in a scene that is not solved), (B,) bool,
        and the batched :class:`CameraFit` (its attitude NaN where not solved).
    """
    return _verify(jnp.asarray(star_vectors, jnp.float32), jnp.asarray(xy, jnp.float32),
                   jnp.asarray(valid), jnp.asarray(ids, jnp.int32), jnp.asarray(ok),
                   jnp.float32(k_sigma), jnp.float32(min_tol_px), jnp.float32(max_tol_px),
                   jnp.float32(max_scale_error), camera=camera, min_named=int(min_named),
                   fit_scale=bool(fit_scale))


@functools.partial(jax.jit, static_argnames=("camera", "min_named", "fit_scale"))
def _verify(star_vectors, xy, valid, ids, ok, k_sigma, min_tol_px, max_tol_px, max_scale_error, *,
            camera, min_named, fit_scale):
    def one(xy_i, valid_i, ids_i, ok_i):
        named = valid_i & (ids_i >= 0) & ok_i
        ref = star_vectors[jnp.clip(ids_i, 0, star_vectors.shape[0] - 1)]
        fit = fit_named(xy_i, ref, named, camera, k_sigma=k_sigma, min_tol_px=min_tol_px,
                        max_tol_px=max_tol_px, fit_scale=fit_scale)
        solved = (ok_i & (jnp.sum(fit.inlier) >= min_named)
                  & (jnp.abs(fit.scale - 1.0) <= max_scale_error))
        kept = jnp.where(solved & fit.inlier, ids_i, -1).astype(jnp.int32)
        fit = fit._replace(attitude=jnp.where(solved, fit.attitude, jnp.nan),
                           inlier=fit.inlier & solved)
        return kept, solved, fit

    return jax.vmap(one)(xy, valid, ids, ok)


def project_scaled(camera, v_cam, scale):
    """Camera-frame vectors (..., 3) → ``(xy, in_field)`` with the focal length ``scale · f_px``
    (:meth:`~jstarid.camera.Camera.project` of the fitted camera)."""
    front = v_cam[..., 2] > 0
    vz = jnp.where(front, v_cam[..., 2], 1.0)
    f = camera.f_px * scale
    x = camera.cx + f * v_cam[..., 0] / vz
    y = camera.cy + f * v_cam[..., 1] / vz
    inside = (x >= 0) & (x <= camera.width - 1) & (y >= 0) & (y <= camera.height - 1)
    return jnp.stack([x, y], axis=-1), front & inside


def check_identification(star_vectors, camera, scenes, result, *, max_scale_error: float = 0.1,
                         min_named: int = 3, k_sigma: float = 5.0):
    """An algorithm's last step: :func:`verify_names` on the scenes it claims with at least
    ``min_named`` names (fewer cannot be checked: those are returned as they are).

    Args:
        star_vectors: (M, 3) ICRS unit vectors of the rows ``result.ids`` names.
        camera: the nominal camera. scenes: (B, N) scenes. result: the algorithm's
            :class:`~jstarid.scene.Identification`.
        max_scale_error, min_named, k_sigma: as in :func:`verify_names`.

    Returns:
        The :class:`~jstarid.scene.Identification` with far-off names taken back, scenes whose fit
        fails unclaimed (ids −1), the fitted attitude and ``focal_scale`` (NaN where not fitted).
    """
    from jstarid.scene import Identification

    ids, ok, fit, enough = check_claims(star_vectors, camera, scenes, result, k_sigma=k_sigma,
                                        max_scale_error=max_scale_error, min_named=min_named)
    attitude = fit.attitude
    if result.attitude is not None:
        attitude = jnp.where(enough[:, None, None], attitude, result.attitude)
    return Identification(ids=ids, ok=ok, attitude=jnp.where(ok[:, None, None], attitude, jnp.nan),
                          focal_scale=jnp.where(enough & ok, fit.scale, jnp.nan))


def check_claims(star_vectors, camera, scenes, result, *, min_named: int = 3, **kwargs):
    """:func:`verify_names` on the claimed scenes with at least ``min_named`` names, the others as
    given.

    Returns:
        ``(ids, ok, fit, checked)``: (B, N), (B,), the :class:`CameraFit` of :func:`verify_names`,
        and (B,) bool, the scenes that were checked.
    """
    given = jnp.where(scenes.valid, result.ids, -1)
    checked = result.ok & (jnp.sum(given >= 0, axis=1) >= min_named)
    ids, ok, fit = verify_names(star_vectors, camera, scenes.xy, scenes.valid, given, checked,
                                min_named=min_named, **kwargs)
    return jnp.where(checked[:, None], ids, result.ids), jnp.where(checked, ok, result.ok), fit, checked
