"""Image files in (jstarid.image_files): FITS values, orientation and header, Pillow formats, bad files."""

import gzip
import math

import numpy as np
import pytest
from astropy.io import fits

import jstarid as js
from jstarid.image_files import LUMINANCE, read_image, read_image_file


def _frame(h=30, w=40):
    """A frame whose every pixel differs, rows and columns told apart (a flip or transpose shows)."""
    return (np.arange(h * w, dtype=np.int64).reshape(h, w) * 37 % 65000).astype(np.uint16)


def test_tiff_round_trip(tmp_path):
    from PIL import Image

    data = _frame()
    Image.fromarray(data).save(tmp_path / "frame.tiff")
    out = read_image(tmp_path / "frame.tiff")
    assert out.dtype == np.float32 and out.shape == (30, 40)
    np.testing.assert_array_equal(out, data.astype(np.float32))
    assert js.read_image is read_image


def test_fits_unsigned_16_bit_reads_its_true_values_unflipped(tmp_path):
    """uint16 is stored as int16 with BZERO = 32768: the sky at 1,000 and a star at 40,000 ADU read
    back as such (not 33,768 and 7,232), row r of the array still row r."""
    data = 1000 + _frame() % 7
    data[3, 5] = 40000
    fits.PrimaryHDU(data).writeto(tmp_path / "frame.fits")
    assert fits.getheader(tmp_path / "frame.fits")["BZERO"] == 32768
    out = read_image_file(tmp_path / "frame.fits")
    assert out.pixels.dtype == np.float32
    np.testing.assert_array_equal(out.pixels, data.astype(np.float32))
    assert out.pixels[3, 5] == 40000 and out.header["NAXIS1"] == 40
    assert out.epoch is None and out.focal_px is None


def test_fits_float_cube_extension_and_compression(tmp_path):
    data = _frame().astype(np.float32) / 7.0
    fits.PrimaryHDU(data).writeto(tmp_path / "f32.fit")
    np.testing.assert_array_equal(read_image(tmp_path / "f32.fit"), data)
    # the first 2-D image after an empty primary HDU, a compressed one, and a gzipped file
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(data)]).writeto(tmp_path / "ext.fts")
    np.testing.assert_array_equal(read_image(tmp_path / "ext.fts"), data)
    ints = _frame()
    fits.HDUList([fits.PrimaryHDU(), fits.CompImageHDU(ints)]).writeto(tmp_path / "tiles.fits")
    np.testing.assert_array_equal(read_image(tmp_path / "tiles.fits"), ints.astype(np.float32))
    (tmp_path / "z.fits.gz").write_bytes(gzip.compress((tmp_path / "f32.fit").read_bytes()))
    np.testing.assert_array_equal(read_image(tmp_path / "z.fits.gz"), data)
    # a FITS file under another name is still FITS (not Pillow's flipped reading)
    (tmp_path / "f32.img").write_bytes((tmp_path / "f32.fit").read_bytes())
    np.testing.assert_array_equal(read_image(tmp_path / "f32.img"), data)
    # blank pixels take the median; 3 planes are R, G, B; other cubes are refused
    holed = data.copy()
    holed[0, 0] = np.nan
    fits.PrimaryHDU(holed).writeto(tmp_path / "holed.fits")
    assert read_image(tmp_path / "holed.fits")[0, 0] == np.median(data.ravel()[1:])
    rgb = np.stack([data, 2 * data, 3 * data])
    fits.PrimaryHDU(rgb).writeto(tmp_path / "rgb.fits")
    np.testing.assert_allclose(read_image(tmp_path / "rgb.fits"), data * (np.arange(1, 4) @ LUMINANCE),
                               rtol=1e-6)
    fits.PrimaryHDU(np.stack([data] * 4)).writeto(tmp_path / "cube.fits")
    with pytest.raises(ValueError, match="3-D image"):
        read_image(tmp_path / "cube.fits")


def test_fits_header_gives_epoch_and_focal_length(tmp_path):
    hdu = fits.PrimaryHDU(_frame())
    hdu.header.update({"DATE-OBS": "2018-05-18T06:00:00", "FOCALLEN": 16.0, "XPIXSZ": 3.75,
                       "YPIXSZ": 3.75, "XBINNING": 1})
    hdu.writeto(tmp_path / "a.fits")
    out = read_image_file(tmp_path / "a.fits")
    assert out.epoch == pytest.approx(2018.0 + (31 + 28 + 31 + 30 + 17.25 - 0.5) / 365.25, abs=2e-3)
    assert out.focal_px == pytest.approx(16000.0 / 3.75)
    # INDI's unbinned PIXSIZE1 times the binning; the date in the primary header of an extension
    primary = fits.PrimaryHDU()
    primary.header.update({"DATE-OBS": "2019-07-29", "TIME-OBS": "12:00:00"})
    ext = fits.ImageHDU(_frame())
    ext.header.update({"FOCALLEN": 50.0, "PIXSIZE1": 6.9, "XBINNING": 2})
    fits.HDUList([primary, ext]).writeto(tmp_path / "b.fits")
    out = read_image_file(tmp_path / "b.fits")
    assert out.epoch == pytest.approx(2019.0 + (181 + 28.5 - 0.5) / 365.25, abs=2e-3)
    assert out.focal_px == pytest.approx(50000.0 / 13.8)
    # a date that does not parse warns and gives no epoch; PNG has no header
    hdu.header["DATE-OBS"] = "yesterday"
    hdu.writeto(tmp_path / "c.fits")
    with pytest.warns(UserWarning, match="DATE-OBS"):
        assert read_image_file(tmp_path / "c.fits").epoch is None
    assert not math.isnan(read_image_file(tmp_path / "c.fits").focal_px)


def test_colour_png_becomes_luminance(tmp_path):
    from PIL import Image

    rgb = np.stack([_frame() % 256 for _ in range(3)], axis=-1).astype(np.uint8)
    rgb[..., 1] //= 2
    rgb[..., 2] //= 3
    Image.fromarray(rgb).save(tmp_path / "rgb.png")
    Image.fromarray(np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 9, np.uint8)], -1)).save(
        tmp_path / "rgba.png")
    want = rgb.astype(np.float32) @ np.asarray(LUMINANCE, np.float32)
    for name in ("rgb.png", "rgba.png"):
        out = read_image_file(tmp_path / name)
        assert out.header is None and out.pixels.dtype == np.float32
        np.testing.assert_allclose(out.pixels, want, rtol=1e-6)
    gray16 = _frame()
    Image.fromarray(gray16).save(tmp_path / "g16.png")
    np.testing.assert_array_equal(read_image(tmp_path / "g16.png"), gray16.astype(np.float32))


@pytest.mark.parametrize("name, content", [("missing.fits", None), ("missing.png", None),
                                           ("bad.fits", b"SIMPLE  = T\nnonsense"), ("bad.png", b"x" * 50),
                                           ("empty.fits", "primary")])
def test_bad_files_give_one_clear_error(tmp_path, name, content):
    path = tmp_path / name
    if content == "primary":
        fits.PrimaryHDU().writeto(path)
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(ValueError, match="cannot read an image") as err:
        read_image_file(path)
    assert "\n" not in str(err.value) and name in str(err.value)
    with pytest.raises(ValueError, match="directory"):
        read_image(tmp_path)
