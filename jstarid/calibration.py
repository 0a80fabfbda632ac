"""A camera calibrated on the sky: focal length, principal point and lens distortion from solved frames.

A camera known only roughly (a field of view to ±10 %, no distortion) solves most frames anyway (the
finishing stage fits the focal length and a radial term per frame). :func:`calibrate` then fits one
camera to every frame's names at once: the focal length ``f``, the principal point ``(cx, cy)`` and
OpenCV's Brown–Conrady coefficients ``(k1, k2, p1, p2)`` (:class:`jstarid.Camera`'s model), with one
attitude per frame, by robust least squares (``scipy.optimize.least_squares``, soft-L1 loss at
:data:`LOSS_SCALE_PX`, so that a wrong name weighs like a few pixels, not its square). The residual
of a named star is the pixel it was measured at minus where the camera puts its catalog direction:
``c + f · distort(X/Z, Y/Z)`` of ``v = C r``.

Stars reported as blends (:class:`jstarid.solution.Star`) are left out: their centroid is the light
of two stars. The principal point and the tangential terms are nearly interchangeable with a small
rotation of each frame in a narrow field, so they are fitted only with enough frames and stars
(:data:`MIN_STARS_FOR_ALL`); otherwise the fit keeps ``(cx, cy)``, ``p1``, ``p2`` as given and says so.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from jstarid.catalog import load_every_star

__all__ = ["Calibration", "calibrate"]

LOSS_SCALE_PX = 1.0  # soft-L1 scale: residuals beyond ≈ 1 px count linearly, not squared
MIN_STARS_FOR_ALL = 60  # named stars over all frames before principal point and p1, p2 are fitted
MIN_STARS_PER_FRAME = 4
_NAMES = ("f_px", "cx", "cy", "k1", "k2", "p1", "p2")


@dataclasses.dataclass(frozen=True)
class Calibration:
    """What :func:`calibrate` found.

    Attributes:
        camera: the fitted :class:`~jstarid.Camera` (distortion ``(k1, k2, p1, p2)``).
        fitted: the parameters fitted (names of :class:`~jstarid.Camera` fields or coefficients).
        rms_before_px: RMS pixel residual of the given camera, each frame's attitude refitted (px).
        rms_after_px: RMS pixel residual of the fitted camera (px).
        frames: frames used. stars: named stars used.
        attitudes: (frames, 3, 3) fitted attitudes (``v_cam = C r``).
    """

    camera: object
    fitted: tuple[str, ...]
    rms_before_px: float
    rms_after_px: float
    frames: int
    stars: int
    attitudes: np.ndarray


def calibrate(solutions: Sequence, camera, *, epoch: float | None = None,
              fit: Sequence[str] | None = None) -> Calibration:
    """Fit ``camera`` to the named stars of solved frames (module docstring).

    Args:
        solutions: :class:`~jstarid.solution.Solution` of frames taken with ``camera`` (unsolved ones
            and frames with fewer than :data:`MIN_STARS_PER_FRAME` names are skipped).
        camera: the rough :class:`~jstarid.Camera` they were solved with (its size is kept).
        epoch: the star positions' epoch (default: the solutions' own).
        fit: the parameters to fit, a subset of ``f_px, cx, cy, k1, k2, p1, p2``; ``None``: all of
            them with at least :data:`MIN_STARS_FOR_ALL` stars, else ``f_px, k1, k2``.

    Returns:
        A :class:`Calibration`.

    Raises:
        ValueError: no frame has enough names, or an unknown parameter.
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    import jstarid as js

    used = [s for s in solutions if s.solved and sum(not st.blend for st in s.stars) >= MIN_STARS_PER_FRAME]
    if not used:
        raise ValueError(f"no solved frame with {MIN_STARS_PER_FRAME} or more named stars to calibrate on")
    if epoch is None:
        epoch = used[0].epoch
    cat = load_every_star(epoch)
    frame_of, xy, ref = [], [], []
    for k, sol in enumerate(used):
        stars = [st for st in sol.stars if not st.blend]
        rows = cat.row_of_hip([st.hip for st in stars])
        keep = rows >= 0
        frame_of += [k] * int(keep.sum())
        xy += [(st.x, st.y) for st, ok in zip(stars, keep, strict=True) if ok]
        ref.append(cat.unit_vectors[rows[keep]])
    frame_of, xy, ref = np.asarray(frame_of), np.asarray(xy, np.float64), np.concatenate(ref)
    if fit is None:
        fit = _NAMES if len(xy) >= MIN_STARS_FOR_ALL else ("f_px", "k1", "k2")
    unknown = sorted(set(fit) - set(_NAMES))
    if unknown:
        raise ValueError(f"cannot fit {', '.join(unknown)}; choose from {', '.join(_NAMES)}")
    fit = tuple(n for n in _NAMES if n in fit)
    k1, k2, p1, p2, k3 = tuple(camera.distortion) + (0.0,) * (5 - len(camera.distortion))
    given = dict(f_px=camera.f_px, cx=camera.cx, cy=camera.cy, k1=k1, k2=k2, p1=p1, p2=p2, k3=k3)
    start = dict(given)  # k3, never fitted, stays as given
    if any(s.focal_scale is not None for s in used):  # the frames' own fits: a better start
        start["f_px"] = camera.f_px * float(np.median([s.focal_scale or 1.0 for s in used]))
    rotations = Rotation.from_matrix(np.stack([s.attitude for s in used])).as_rotvec().ravel()
    step = {"f_px": camera.f_px * 0.01, "cx": 1.0, "cy": 1.0, "k1": 0.01, "k2": 0.01, "p1": 1e-3,
            "p2": 1e-3}  # the parameters' natural sizes: the solver works in these units

    def camera_values(p):
        return {**start, **{n: start[n] + step[n] * p[i] for i, n in enumerate(fit)}}

    def residuals(values, rotvecs):
        c = Rotation.from_rotvec(rotvecs.reshape(-1, 3)).as_matrix()[frame_of]  # (n, 3, 3)
        return (project(values, np.einsum("nij,nj->ni", c, ref)) - xy).ravel()

    robust = dict(loss="soft_l1", f_scale=LOSS_SCALE_PX)
    # the given camera's residual, each frame's attitude refitted to it
    before = least_squares(lambda q: residuals(given, q), rotations, **robust)
    after = least_squares(lambda p: residuals(camera_values(p), p[len(fit):]),
                          np.concatenate([np.zeros(len(fit)), rotations]), x_scale="jac", **robust)
    values = camera_values(after.x)
    rot = Rotation.from_rotvec(after.x[len(fit):].reshape(-1, 3))
    name = camera.name if camera.name.endswith(" calibrated") else f"{camera.name} calibrated"
    fitted = js.Camera(camera.width, camera.height, values["f_px"], cx=values["cx"], cy=values["cy"],
                       mag_limit=camera.mag_limit, name=name,
                       distortion=tuple(values[k] for k in ("k1", "k2", "p1", "p2", "k3")))
    return Calibration(camera=fitted, fitted=fit, rms_before_px=_rms(before.fun),
                       rms_after_px=_rms(after.fun), frames=len(used), stars=len(xy),
                       attitudes=rot.as_matrix())


def project(values: dict, v_cam: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) of camera-frame directions ``v_cam`` (n, 3) through a Brown–Conrady lens
    (``values``: ``f_px, cx, cy, k1, k2, p1, p2, k3``).

    :meth:`jstarid.Camera.project` and :meth:`~jstarid.Camera.distort` in float64 NumPy: the least
    squares' finite-difference Jacobian steps parameters by ~1e-8 of their size, below float32's
    resolution (``tests/test_calibration.py`` checks the two agree).
    """
    u, w = v_cam[:, 0] / v_cam[:, 2], v_cam[:, 1] / v_cam[:, 2]
    r2 = u * u + w * w
    radial = 1.0 + r2 * (values["k1"] + r2 * (values["k2"] + r2 * values["k3"]))
    ud = u * radial + 2.0 * values["p1"] * u * w + values["p2"] * (r2 + 2.0 * u * u)
    wd = w * radial + values["p1"] * (r2 + 2.0 * w * w) + 2.0 * values["p2"] * u * w
    return np.stack([values["cx"] + values["f_px"] * ud, values["cy"] + values["f_px"] * wd], axis=-1)


def _rms(fun: np.ndarray) -> float:
    pairs = fun.reshape(-1, 2)
    return float(math.sqrt(np.mean(np.sum(pairs**2, axis=1))))
