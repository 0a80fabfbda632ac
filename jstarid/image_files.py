"""Image files in: FITS through astropy, TIFF / PNG / … through Pillow, as (H, W) float32 frames.

Orientation (docs/conventions.md §1): element ``[r, c]`` of the returned array is the pixel whose
centre is ``(x, y) = (c, r)``. For FITS that is the data array as astropy gives it (FITS pixel
``(c + 1, r + 1)``, the first axis NAXIS1 running along a row): rows are never flipped, whatever a
viewer shows with its origin at the bottom. Pillow's own FITS plugin flips them and ignores BZERO,
so every FITS file goes to astropy, recognised by its name (``.fits``, ``.fit``, ``.fts``, each
optionally ``.gz``; ``.fz``) or by its first card (``SIMPLE  =``).

FITS (:func:`read_image_file`):

- **Values.** BZERO and BSCALE applied (astropy scales the data: an unsigned 16-bit frame stored as
  int16 with BZERO = 32768 reads back as 0…65535), then float32. Blank or NaN pixels (masked areas
  of a processed float frame) become the median of the others, so the centroid stage's medians and
  sums stay finite.
- **Which data.** The first HDU (primary, image extension or tile-compressed image) holding an image
  of two axes after dropping axes of length 1. Three planes (NAXIS3 = 3, an RGB frame) become
  luminance; any other cube is refused.
- **Header.** The image HDU's header; a keyword it lacks is looked up in the primary header (an
  extension inherits the observation's keywords). ``DATE-OBS`` (or ``DATE-OBS`` + ``TIME-OBS``, or
  ``MJD-OBS``) gives the epoch as a Julian year; ``FOCALLEN`` (mm) over the pixel pitch gives the
  focal length in px. The pitch is ``XPIXSZ`` (µm), which MaxIm DL, SBIG's keyword proposal and
  INDI write for the *binned* pixel, else ``PIXSIZE1`` (µm, INDI's unbinned pitch) × ``XBINNING``.

Other formats go through Pillow: 8-bit, 16-bit (kept 16-bit) and float grayscale as they are;
colour (RGB, RGBA, palette, CMYK, …) as the luminance ``0.299 R + 0.587 G + 0.114 B`` (ITU-R
BT.601, the weights of Pillow's own ``convert("L")``), computed in float so nothing is rounded to
8 bits; alpha is ignored. Pillow holds 16-bit colour PNGs as 8-bit RGB, so their low bits are lost.

Every failure is a :class:`ValueError` with one line naming the file (the CLI prints it and exits
with status 2).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path

import numpy as np

__all__ = ["ImageFile", "is_fits", "read_image", "read_image_file"]

#: Luminance weights of R, G, B (ITU-R BT.601, as Pillow's ``convert("L")``).
LUMINANCE = (0.299, 0.587, 0.114)
FITS_SUFFIXES = (".fits", ".fit", ".fts")
_GRAY_MODES = ("L", "I", "I;16", "I;16B", "I;16L", "I;16N", "F")


@dataclasses.dataclass(frozen=True, eq=False)
class ImageFile:
    """One frame read from a file, with what its header says (module docstring).

    Attributes:
        pixels: (H, W) float32 pixel values; ``pixels[r, c]`` is the pixel centred at ``(x, y) =
            (c, r)``.
        header: the FITS header of the image HDU (``astropy.io.fits.Header``), ``None`` for other
            formats.
        epoch: the observation's date as a Julian year (e.g. 2018.38), from ``DATE-OBS`` or
            ``MJD-OBS``; ``None`` when the header gives none.
        focal_px: focal length in pixels (``FOCALLEN`` mm / binned pixel pitch), ``None`` when the
            header lacks either.
    """

    pixels: np.ndarray
    header: object | None = None
    epoch: float | None = None
    focal_px: float | None = None


def is_fits(path) -> bool:
    """Whether ``path`` names a FITS file: by its suffix (module docstring) or its first card."""
    name = Path(path).name.lower()
    for packed in (".gz", ".fz"):
        if name.endswith(packed):
            name = name[: -len(packed)]
            if packed == ".fz":
                return True
    if name.endswith(FITS_SUFFIXES):
        return True
    try:
        with open(path, "rb") as f:
            return f.read(9) == b"SIMPLE  ="
    except OSError:
        return False


def read_image(path) -> np.ndarray:
    """An image file as a (H, W) float32 array (:func:`read_image_file`'s pixels).

    Raises:
        ValueError: any input that yields no image (a missing, unreadable, truncated or corrupt
            file, a directory, an unknown format, a FITS file without a 2-D image).
    """
    return read_image_file(path).pixels


def read_image_file(path) -> ImageFile:
    """An image file as pixels plus, for FITS, its header, epoch and focal length (module docstring).

    Args:
        path: a FITS, TIFF, PNG or other Pillow-readable image file.

    Returns:
        An :class:`ImageFile`.

    Raises:
        ValueError: as :func:`read_image`.
    """
    if Path(path).is_dir():
        raise ValueError(f"cannot read an image from {path}: it is a directory")
    return _read_fits(path) if is_fits(path) else ImageFile(_read_pillow(path))


def _read_pillow(path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            if im.mode in _GRAY_MODES:
                return np.asarray(im).astype(np.float32)
            if im.mode in ("1", "LA"):  # bilevel, or gray with alpha: the gray channel
                return np.asarray(im.convert("L")).astype(np.float32)
            rgb = np.asarray(im.convert("RGB"), np.float32)
            return np.matmul(rgb, np.asarray(LUMINANCE, np.float32))
    # OSError covers a permission error and a truncated file; Pillow's decoders raise SyntaxError or
    # ValueError on some corrupt headers
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as err:
        raise ValueError(f"cannot read an image from {path}: {err}") from err


def image_hdu_index(hdus) -> int:
    """Index of the first HDU of ``hdus`` (an ``HDUList``) holding a 2-D image (or an RGB cube).

    Raises:
        ValueError: no HDU holds one; or the first image is a cube of other than 3 planes.
    """
    for k, hdu in enumerate(hdus):
        if not getattr(hdu, "is_image", False):
            continue
        shape = tuple(n for n in (hdu.shape or ()) if n != 1)
        if len(shape) == 2 or (len(shape) == 3 and shape[0] == 3):
            return k
        if len(shape) >= 3:
            raise ValueError(f"HDU {k} is a {len(shape)}-D image of shape {hdu.shape}; jstarid reads "
                             "one 2-D frame (or a 3-plane RGB frame)")
    raise ValueError("no HDU holds a 2-D image")


def _read_fits(path) -> ImageFile:
    from astropy.io import fits

    try:
        with fits.open(path, memmap=False) as hdus:
            k = image_hdu_index(hdus)
            data = np.asarray(hdus[k].data)  # BZERO and BSCALE applied by astropy
            header = hdus[k].header.copy()
            primary = hdus[0].header
    # OSError: missing or truncated; the others: a corrupt header or data (ours: no 2-D image)
    except (OSError, ValueError, TypeError, KeyError, IndexError) as err:
        raise ValueError(f"cannot read an image from {path}: {err}") from err
    frame = np.squeeze(data).astype(np.float32)
    if frame.ndim == 3:  # (3, H, W): R, G, B planes
        frame = np.tensordot(np.asarray(LUMINANCE, np.float32), frame, axes=1)
    bad = ~np.isfinite(frame)
    if bad.all():
        raise ValueError(f"cannot read an image from {path}: no finite pixel")
    if bad.any():
        frame[bad] = np.median(frame[~bad])

    def card(key):
        return header.get(key, primary.get(key))

    return ImageFile(frame, header, _epoch(card, path), _focal_px(card))


def _epoch(card, path) -> float | None:
    """The Julian year of ``DATE-OBS`` (with ``TIME-OBS`` when it holds only a date) or ``MJD-OBS``;
    ``None`` with a warning when neither parses (the pixels are still good)."""
    from astropy.time import Time

    date, mjd = card("DATE-OBS"), card("MJD-OBS")
    try:
        if isinstance(date, str) and date.strip():
            date = date.strip()
            if len(date) == 8 and date[2] == "/" and date[5] == "/":  # the pre-1999 'dd/mm/yy' form
                date = f"19{date[6:8]}-{date[3:5]}-{date[0:2]}"
            time = card("TIME-OBS")
            if "T" not in date and isinstance(time, str) and time.strip():
                date = f"{date}T{time.strip()}"
            return float(Time(date, scale="utc").jyear)
        if mjd is not None:
            return float(Time(float(mjd), format="mjd", scale="utc").jyear)
    except (ValueError, TypeError) as err:
        # astropy's message lists every format it tried, over many lines: its first is enough
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        warnings.warn(f"{path}: the observation date (DATE-OBS {date!r}, MJD-OBS {mjd!r}) does not "
                      f"parse ({reason}); no epoch taken from the header", stacklevel=3)
    return None


def _focal_px(card) -> float | None:
    """``FOCALLEN`` (mm) over the binned pixel pitch (µm) (module docstring), or ``None``."""
    focal_mm, pitch_um = card("FOCALLEN"), card("XPIXSZ")
    try:
        if pitch_um is None and card("PIXSIZE1") is not None:
            pitch_um = float(card("PIXSIZE1")) * float(card("XBINNING") or 1)
        f_px = float(focal_mm) * 1000.0 / float(pitch_um)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return f_px if math.isfinite(f_px) and f_px > 0 else None
