"""The solution as a FITS world coordinate system (astropy): what DS9, astropy and astrometry.net read.

**Model.** A solved frame's pixel ``(x, y)`` (docs/conventions.md §1: column, row, origin at the
centre of pixel (0, 0)) is FITS pixel ``(x + 1, y + 1)``. Through the attitude ``C`` (ICRS → camera,
conventions §1) and the pinhole of focal length ``f = focal_scale · f_px`` about the principal point
``c``, the ideal pixel of an ICRS direction ``r`` is ``c + f (v_x, v_y) / v_z`` with ``v = C r``.
The camera frame's x and y axes (rows 0 and 1 of ``C``) lie in the tangent plane at the boresight
(row 2), as do the local east and north directions ``e``, ``n`` of that point, so the gnomonic
standard coordinates ``(ξ, η)`` (east, north) of a direction are a 2×2 orthogonal map of the
camera's ``(v_x, v_y) / v_z``: ``ξ = e·C₀ u + e·C₁ v``, ``η = n·C₀ u + n·C₁ v``. That is FITS' TAN
projection with ``CRVAL`` = the boresight's RA and Dec, ``CRPIX`` = ``c + 1``, ``LONPOLE`` = 180° and
``CD = (180/π) / f · [[e·C₀, e·C₁], [n·C₀, n·C₁]]`` (deg/px), exact, whatever the roll.

**Distortion (TAN-SIP).** Measured pixels are not ideal ones where the lens distorts. Two layers are
composed, as the solve applies them: the camera's own Brown–Conrady coefficients
(:meth:`jstarid.Camera.distort` / ``undistort``, normalised by the nominal ``f_px``), undone before
identification, and the radial term ``k1`` the finishing stage fits with the focal scale
(:func:`jstarid.camera_fit.project_scaled`: OpenCV's ``k1`` on the ideal normalised coordinates of
the *fitted* focal length, ``c + f u (1 + k1 |u|²)``). SIP's forward polynomials ``A``, ``B`` (terms
of order 2 and up) map a measured pixel's offset from ``CRPIX`` to the ideal one, the inverse ``AP``,
``BP`` (every order) back; both are fitted by least squares on a grid over the frame, order by order
from 3 until both reproduce the lens within ``tol_px`` at every point of a finer grid (a k1-only
lens of a 17° field needs order 5 for 1 mpx).

Writing: :func:`write_wcs` (a ``.wcs`` file as astrometry.net writes: a primary header without data)
and :func:`write_fits_with_wcs` (a FITS image with the solution in its header).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from pathlib import Path

import numpy as np

__all__ = ["solution_wcs", "wcs_from_solution", "write_fits_with_wcs", "write_wcs"]

SIP_MAX_ORDER = 9  # beyond this the grid's float32 lens evaluations, not the polynomial, limit the fit
_FIT_POINTS = 33  # per axis: the grid the SIP polynomials are fitted on
_CHECK_POINTS = 57  # per axis: the finer grid they are checked on (points between the fit's)

#: Keywords of an existing WCS that :func:`write_fits_with_wcs` removes before writing ours (any
#: axis, any alternate description letter), so no stale CDi_j, PCi_j, CDELTi or SIP term survives.
_WCS_KEY = re.compile(r"^(WCSAXES|WCSNAME|CTYPE|CRVAL|CRPIX|CDELT|CUNIT|CROTA|CD\d+_\d+|PC\d+_\d+|"
                      r"PV\d+_\d+|PS\d+_\d+|A_|B_|AP_|BP_|LONPOLE|LATPOLE|RADESYS|EQUINOX)")


def _rotation(attitude) -> np.ndarray:
    """The nearest rotation to ``attitude`` (float64): a solution saved as float32 JSON is orthogonal
    only to ~1e-7, which would shear the CD matrix by as much."""
    u, _, vt = np.linalg.svd(np.asarray(attitude, np.float64).reshape(3, 3))
    c = np.matmul(u, vt)
    if np.linalg.det(c) < 0:
        raise ValueError("the attitude is a reflection, not a rotation")
    return c


def solution_wcs(camera, attitude, *, focal_scale: float = 1.0, k1: float = 0.0, tol_px: float = 1e-3):
    """The WCS of a solved frame (module docstring): TAN, or TAN-SIP where a lens distorts.

    Args:
        camera: the :class:`~jstarid.Camera` the frame was solved with (its distortion included).
        attitude: (3, 3) ``C``, ICRS → camera (conventions §1).
        focal_scale: fitted focal length / ``camera.f_px`` (``Identification.focal_scale``).
        k1: the radial distortion the finishing stage fitted (``Identification.distortion_k1``;
            normalised coordinates of the fitted focal length); 0 or NaN for none.
        tol_px: largest error (px) the SIP polynomials may leave over the frame.

    Returns:
        An ``astropy.wcs.WCS`` with ``pixel_shape = (W, H)``; ICRS RA/Dec in degrees.

    Raises:
        ValueError: a non-finite or non-positive focal scale, or an attitude that is no rotation.
    """
    from astropy.wcs import WCS, Sip

    if not (math.isfinite(focal_scale) and focal_scale > 0):
        raise ValueError(f"focal_scale must be a positive number, got {focal_scale}")
    k1 = 0.0 if not math.isfinite(k1) else float(k1)
    c = _rotation(attitude)
    boresight = c[2]
    ra0 = math.atan2(boresight[1], boresight[0]) % (2 * math.pi)
    dec0 = math.asin(float(np.clip(boresight[2], -1.0, 1.0)))
    east = np.array([-math.sin(ra0), math.cos(ra0), 0.0])
    north = np.array([-math.sin(dec0) * math.cos(ra0), -math.sin(dec0) * math.sin(ra0), math.cos(dec0)])
    f = camera.f_px * focal_scale
    cd = np.degrees(np.matmul(np.stack([east, north]), c[:2].T)) / f  # [[e·C₀, e·C₁], [n·C₀, n·C₁]]
    sip = k1 != 0.0 or bool(camera.distortion)
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"] if sip else ["RA---TAN", "DEC--TAN"]
    w.wcs.cunit = ["deg", "deg"]
    w.wcs.crval = [math.degrees(ra0), math.degrees(dec0)]
    w.wcs.crpix = [camera.cx + 1.0, camera.cy + 1.0]
    w.wcs.cd = cd
    w.wcs.radesys = "ICRS"
    w.wcs.lonpole = 180.0
    w.pixel_shape = (camera.width, camera.height)
    if sip:
        a, b, ap, bp = _fit_sip(camera, f, k1, tol_px)
        w.sip = Sip(a, b, ap, bp, w.wcs.crpix)
    w.wcs.set()
    return w


def wcs_from_solution(camera, solution: dict):
    """:func:`solution_wcs` of one solved entry of ``jstarid solve``'s JSON (``attitude`` and, where
    the finishing stage fitted them, ``focal_scale`` and ``distortion_k1``)."""
    return solution_wcs(camera, solution["attitude"], focal_scale=solution.get("focal_scale", 1.0),
                        k1=solution.get("distortion_k1", 0.0))


def _undistort(camera, f: float, k1: float):
    """Measured pixels (N, 2) → ideal pixels (N, 2) of focal length ``f`` (float64): the camera's own
    distortion undone, then the fitted ``k1`` (a :class:`~jstarid.Camera` lens of focal length ``f``:
    :func:`jstarid.camera_fit.project_scaled`'s model)."""
    fitted = dataclasses.replace(camera.pinhole(), f_px=f, distortion=(k1,) if k1 else ())
    return lambda measured: np.asarray(fitted.undistort(camera.undistort(measured)), np.float64)


def _terms(order: int, lowest: int):
    return [(p, q) for p in range(order + 1) for q in range(order + 1 - p) if p + q >= lowest]


def _poly_fit(offsets, target, order: int, lowest: int, scale: float):
    """Least-squares coefficients (order+1, order+1) × 2 of ``target`` (N, 2) as polynomials in
    ``offsets`` (N, 2) px; columns scaled by ``scale`` so the normal matrix stays well conditioned."""
    terms = _terms(order, lowest)
    t = offsets / scale
    design = np.stack([t[:, 0] ** p * t[:, 1] ** q for p, q in terms], axis=1)
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    out = np.zeros((2, order + 1, order + 1))
    for (p, q), row in zip(terms, coef, strict=True):
        out[:, p, q] = row / scale ** (p + q)
    return out


def _poly_eval(coef, offsets):
    order = coef.shape[-1] - 1
    return np.stack([sum(coef[k, p, q] * offsets[:, 0] ** p * offsets[:, 1] ** q
                         for p, q in _terms(order, 0)) for k in range(2)], axis=1)


def _grid(camera, n: int) -> np.ndarray:
    """(n², 2) pixels evenly over the frame, its outer pixel edges included."""
    x = np.linspace(-0.5, camera.width - 0.5, n)
    y = np.linspace(-0.5, camera.height - 0.5, n)
    return np.stack(np.meshgrid(x, y), axis=-1).reshape(-1, 2)


def _fit_sip(camera, f: float, k1: float, tol_px: float):
    """SIP ``(A, B, AP, BP)`` (each (order+1, order+1)) reproducing the lens within ``tol_px`` (module
    docstring; the highest order tried, :data:`SIP_MAX_ORDER`, where none does)."""
    undistort = _undistort(camera, f, k1)  # the grid is of measured pixels: one direction suffices
    centre = np.array([camera.cx, camera.cy])
    fit_m, check_m = _grid(camera, _FIT_POINTS), _grid(camera, _CHECK_POINTS)
    fit_i, check_i = undistort(fit_m), undistort(check_m)
    scale = float(np.abs(fit_m - centre).max())
    for order in range(3, SIP_MAX_ORDER + 1):
        forward = _poly_fit(fit_m - centre, fit_i - fit_m, order, 2, scale)
        inverse = _poly_fit(fit_i - centre, fit_m - fit_i, order, 0, scale)
        err_forward = np.abs(check_m + _poly_eval(forward, check_m - centre) - check_i).max()
        err_inverse = np.abs(check_i + _poly_eval(inverse, check_i - centre) - check_m).max()
        if max(err_forward, err_inverse) <= tol_px:
            break
    return forward[0], forward[1], inverse[0], inverse[1]


def _header(wcs):
    header = wcs.to_header(relax=True)
    if wcs.wcs.has_cd():
        # astropy writes PCi_j and CDELTi; the SIP convention (and astrometry.net) states CDi_j, which
        # every reader takes, so the matrix is written as it was given
        for key in [k for k in header if re.match(r"^(PC\d_\d|CDELT\d)$", k)]:
            del header[key]
        previous = "CRPIX2"
        for i in range(2):
            for j in range(2):
                key = f"CD{i + 1}_{j + 1}"
                header.insert(previous, (key, float(wcs.wcs.cd[i, j]), "linear transformation (deg/px)"),
                              after=True)
                previous = key
    if wcs.pixel_shape is not None:  # astrometry.net's record of the frame size
        header["IMAGEW"] = (int(wcs.pixel_shape[0]), "image width (px)")
        header["IMAGEH"] = (int(wcs.pixel_shape[1]), "image height (px)")
    return header


def write_wcs(wcs, path) -> Path:
    """Write ``wcs`` as a ``.wcs`` file: a FITS primary HDU without data, holding the WCS header (as
    astrometry.net does). Returns the path."""
    from astropy.io import fits

    path = Path(path)
    fits.PrimaryHDU(header=_header(wcs)).writeto(path, overwrite=True)
    return path


def write_fits_with_wcs(source, wcs, path) -> Path:
    """A FITS image with ``wcs`` in its header.

    Args:
        source: a FITS file (copied HDU by HDU, its stored values and BZERO/BSCALE untouched; the
            solution goes into the header of the image :func:`jstarid.read_image` reads, any WCS
            there before removed), another image file, or a (H, W) array (written as float32).
        wcs: the solution (:func:`solution_wcs`).
        path: the FITS file to write (replaced if it exists; it may be ``source`` itself).

    Returns:
        The path.

    Raises:
        ValueError: an unreadable source, or an image whose size is not the WCS's.
    """
    from astropy.io import fits

    from jstarid.image_files import image_hdu_index, is_fits, read_image

    path = Path(path)
    if isinstance(source, str | os.PathLike) and is_fits(source):
        try:
            # the data as stored (no scaling: the copy is exact) and all in memory, so the copy may
            # replace the source file
            hdus = fits.open(source, do_not_scale_image_data=True, memmap=False)
            hdus.readall()
        except (OSError, ValueError, TypeError) as err:
            raise ValueError(f"cannot read an image from {source}: {err}") from err
        with hdus:
            k = image_hdu_index(hdus)
            _check_size(hdus[k].shape[-2:], wcs, source)
            header = hdus[k].header
            for key in [key for key in header if _WCS_KEY.match(key)]:
                del header[key]
            header.extend(_header(wcs), update=True)
            hdus.writeto(path, overwrite=True)
        return path
    pixels = read_image(source) if isinstance(source, str | os.PathLike) else np.asarray(source)
    _check_size(pixels.shape, wcs, "the image")
    fits.PrimaryHDU(pixels.astype(np.float32), header=_header(wcs)).writeto(path, overwrite=True)
    return path


def _check_size(shape, wcs, what) -> None:
    if wcs.pixel_shape is not None and tuple(shape) != (wcs.pixel_shape[1], wcs.pixel_shape[0]):
        raise ValueError(f"{what} is {shape[1]}×{shape[0]} px but the solution is for "
                         f"{wcs.pixel_shape[0]}×{wcs.pixel_shape[1]} px")
