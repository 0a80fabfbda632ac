"""Star centroids from raw star-tracker images: the front end before identification.

:func:`extract_centroids` turns a batch of images (B, H, W) into a :class:`~jstarid.scene.Scene`
(centroids in px, instrumental magnitudes, ``truth = −1``), jit-compiled and vmapped, static sizes.
Per image:

1. **Background.** The median of each ``tile_px``² tile, interpolated bilinearly between tile centres
   and extrapolated linearly beyond the outer ones (sky glow and vignetting vary; the median ignores
   a star's few pixels). Residual ``r`` = image − background.
2. **Noise.** ``σ = 1.4826 · median |s|`` of the 3×3-box-filtered residual ``s`` over the frame (a
   Gaussian's MAD). Medians use every ``sample_stride``-th row and column (sorting is the costly part
   on a CPU; the subsampled medians stay accurate, docs/design/sgm.md "Shared pieces"). The box
   filter is a cheap matched filter for a compact PSF and divides a hot pixel's significance by 9, a
   star's by ≈ 2.
3. **Peaks.** Pixels of ``s`` above ``threshold_sigma · σ`` that are the maximum of their
   ``(2 peak_radius_px + 1)²`` neighbourhood; the ``max_peaks`` highest are examined (more set
   ``overflow``: never silently dropped).
4. **Centroid.** Centre of gravity of ``r`` over the ``(2 window_px + 1)²`` window about the peak,
   pixels under ``pixel_sigma · σ_pix`` (MAD noise of ``r``) set to zero, so background noise does
   not pull it to the window centre (thresholded CoG). Flux = the window's thresholded sum. A peak is
   dropped when fewer than ``min_pixels`` pixels pass, or when its brightest core pixel holds more
   than ``max_sharpness`` of the 3×3 core's sum: a hot pixel or cosmic ray (≈ 1), not a star (≈ 0.25
   for a Gaussian PSF of σ = 0.8 px, 0.47 at 0.5 px). The pixel count alone does not reject a hot
   pixel (noise puts ≈ 2 of a 9×9 window's pixels above 2 σ).
5. **Duplicates.** A saturated star is a plateau of peaks: a peak within ``window_px`` (Chebyshev) of
   a higher-ranked one (filtered peak value, ties by raster order) is dropped.
6. **Output.** The ``capacity`` brightest by flux, ``mag = zero_point − 2.5 log10(flux)``;
   ``overflow`` when more were found.

Pixels as everywhere in jstarid (docs/conventions.md §1): x = column, y = row, origin at the centre
of pixel (0, 0).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.runtime import map_batch
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Scene, undistort_scenes

__all__ = ["CentroidConfig", "extract_centroids"]

_MAD_TO_SIGMA = 1.4826  # σ / median|x| for a zero-mean Gaussian


@dataclasses.dataclass(frozen=True)
class CentroidConfig:
    """Frozen settings of :func:`extract_centroids` (hashable: a static jit argument).

    Attributes:
        tile_px: side of the background tiles (px).
        threshold_sigma: detection threshold on the 3×3-box-filtered residual, in its noise σ.
        peak_radius_px: a peak is the maximum of its (2 peak_radius_px + 1)² neighbourhood (px).
        window_px: half-width of the centroid window (px); also the duplicate radius.
        pixel_sigma: pixels under this many σ_pix of the residual do not weigh in the centroid.
        min_pixels: fewest window pixels above ``pixel_sigma`` for a peak to count as a star.
        max_sharpness: largest fraction of the 3×3 sum about a peak its own pixel may hold
            (hot pixels and cosmic rays: ≈ 1).
        max_peaks: static number of peaks examined per image (highest first).
        zero_point: magnitude of a flux of 1 (image units); 0 gives instrumental magnitudes.
        sample_stride: the background medians use every ``sample_stride``-th pixel of a tile in
            each direction, the noise medians every ``2 · sample_stride``-th of the frame.
    """

    tile_px: int = 32
    threshold_sigma: float = 5.0
    peak_radius_px: int = 2
    window_px: int = 4
    pixel_sigma: float = 2.0
    min_pixels: int = 3
    max_sharpness: float = 0.7
    max_peaks: int = 256
    zero_point: float = 0.0
    sample_stride: int = 2

    def __post_init__(self):
        checks = {
            "tile_px": self.tile_px >= 4, "threshold_sigma": self.threshold_sigma > 0,
            "peak_radius_px": self.peak_radius_px >= 1, "window_px": self.window_px >= 1,
            "pixel_sigma": self.pixel_sigma >= 0, "min_pixels": self.min_pixels >= 1,
            "max_peaks": self.max_peaks >= 1, "max_sharpness": 0 < self.max_sharpness <= 1,
            "zero_point": np.isfinite(self.zero_point),
            "sample_stride": 1 <= self.sample_stride <= self.tile_px // 2,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"CentroidConfig.{name} out of range: {getattr(self, name)!r}")


def extract_centroids(images, config: CentroidConfig = CentroidConfig(), *,
                      capacity: int = 64, shard: bool = False, camera=None) -> Scene:
    """Centroids of the stars in a batch of images (module doc), brightest first.

    Args:
        images: (B, H, W) or (H, W) pixel values (any real dtype; converted to float32).
        config: :class:`CentroidConfig`.
        capacity: static N, detections kept per image.
        shard: split the batch over every device (:func:`jstarid.runtime.map_batch`); the result is
            the same as the single-device call's.
        camera: the :class:`~jstarid.Camera` that took the images; its lens distortion, if any, is
            undone on the centroids (:func:`jstarid.scene.undistort_scenes`), and the images must be
            its size. ``None``: centroids stay in measured pixels.

    Returns:
        A :class:`~jstarid.scene.Scene` of B scenes: ``xy`` (B, N, 2) px, ``mag`` (B, N) from the
        flux, ``valid``, ``truth = −1``, ``attitude`` NaN, ``overflow`` when an image had more than N
        stars or more than ``config.max_peaks`` peaks.

    Raises:
        ValueError: not a 2-D / 3-D array, non-finite pixels, an image smaller than a tile or the
            centroid window, or a bad capacity.
    """
    arr = np.asarray(images)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[0] < 1:
        raise ValueError(f"images must have shape (B, H, W) or (H, W), got {np.shape(images)}")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise ValueError(f"images must hold real pixel values, got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("images contain NaN or inf pixels")
    h, w = arr.shape[1:]
    if min(h, w) < max(config.tile_px, 2 * config.window_px + 1):
        raise ValueError(f"images of {h}×{w} px are smaller than a background tile "
                         f"({config.tile_px} px) or the centroid window")
    if not isinstance(capacity, int | np.integer) or capacity < 1:
        raise ValueError(f"capacity must be a positive integer, got {capacity!r}")
    if camera is not None and (h, w) != (camera.height, camera.width):
        raise ValueError(f"images are {h}×{w} px but camera {camera.name} is "
                         f"{camera.height}×{camera.width}")
    batch = jnp.asarray(arr, jnp.float32)
    if shard:
        scenes = map_batch(_extract_batch, (batch,),
                           static=dict(config=config, capacity=int(capacity)))
    else:
        scenes = _extract_batch(batch, config=config, capacity=int(capacity))
    return scenes if camera is None else undistort_scenes(scenes, camera)


@functools.partial(stored_jit, static_argnames=("config", "capacity"))
def _extract_batch(images, *, config, capacity):
    fn = functools.partial(_extract_one, config=config, capacity=capacity)
    xy, mag, valid, overflow = jax.vmap(fn)(images)
    b = images.shape[0]
    return Scene(xy=xy, mag=mag, truth=jnp.full((b, capacity), -1, jnp.int32), valid=valid,
                 attitude=jnp.full((b, 3, 3), jnp.nan, jnp.float32), overflow=overflow)


def background(image, tile_px: int, stride: int = 1):
    """(H, W) background: tile medians (every ``stride``-th row and column of a tile) interpolated
    bilinearly between tile centres (step 1)."""
    h, w = image.shape
    th, tw = -(-h // tile_px), -(-w // tile_px)
    padded = jnp.pad(image, ((0, th * tile_px - h), (0, tw * tile_px - w)), mode="reflect")
    tiles = padded.reshape(th, tile_px, tw, tile_px)[:, ::stride, :, ::stride]
    tiles = tiles.transpose(0, 2, 1, 3).reshape(th, tw, -1)
    med = jnp.median(tiles, axis=-1)
    # tile i's sampled pixels are centred on pixel i·tile_px + c ((tile_px − 1) / 2 at stride 1)
    c = stride * (-(-tile_px // stride) - 1) / 2.0
    ys = (jnp.arange(h) - c) / tile_px
    xs = (jnp.arange(w) - c) / tile_px
    return _bilinear(med, ys, xs)


def _bilinear(grid, ys, xs):
    """Grid (Th, Tw) sampled at fractional rows ys (H,) × columns xs (W,).

    Beyond the outer tile centres the nearest two centres are extrapolated linearly: held constant,
    a sky gradient would leave a half-tile band along the border above the threshold.
    """
    def axis_weights(t, n):
        i0 = jnp.clip(jnp.floor(t).astype(jnp.int32), 0, max(n - 2, 0))
        frac = t - i0 if n > 1 else jnp.zeros_like(t)
        return i0, jnp.minimum(i0 + 1, n - 1), frac

    y0, y1, fy = axis_weights(ys, grid.shape[0])
    x0, x1, fx = axis_weights(xs, grid.shape[1])
    fx = fx[None, :]
    top = grid[y0][:, x0] * (1 - fx) + grid[y0][:, x1] * fx
    bottom = grid[y1][:, x0] * (1 - fx) + grid[y1][:, x1] * fx
    return top * (1 - fy)[:, None] + bottom * fy[:, None]


def _box3(x):
    """3×3 box mean with zero padding (a cheap matched filter for a compact PSF)."""
    total = jax.lax.reduce_window(x, 0.0, jax.lax.add, (3, 3), (1, 1), "SAME")
    return total / 9.0


def _extract_one(image, *, config: CentroidConfig, capacity: int):
    """One (H, W) image → xy (N, 2), mag (N,), valid (N,), overflow ()."""
    h, w = image.shape
    resid = image - background(image, config.tile_px, config.sample_stride)
    smooth = _box3(resid)
    sub = 2 * config.sample_stride
    sigma = _MAD_TO_SIGMA * jnp.median(jnp.abs(smooth[::sub, ::sub]))
    sigma_pix = _MAD_TO_SIGMA * jnp.median(jnp.abs(resid[::sub, ::sub]))
    size = 2 * config.peak_radius_px + 1
    local_max = jax.lax.reduce_window(smooth, -jnp.inf, jax.lax.max, (size, size), (1, 1), "SAME")
    # strictly above: a flat (noise-free) frame has σ = 0 and no peak
    peak = (smooth > config.threshold_sigma * sigma) & (smooth >= local_max)
    n_peaks = jnp.sum(peak)
    m = min(config.max_peaks, h * w)
    score, flat = jax.lax.top_k(jnp.where(peak, smooth, -jnp.inf).reshape(-1), m)
    is_peak = jnp.isfinite(score)
    py, px = flat // w, flat % w

    # step 4: thresholded centre of gravity in a window about each peak
    hw = config.window_px
    padded = jnp.pad(resid, hw)
    wins = jax.vmap(lambda y, x: jax.lax.dynamic_slice(padded, (y, x), (2 * hw + 1, 2 * hw + 1)))(py, px)
    weight = jnp.where(wins > config.pixel_sigma * sigma_pix, wins, 0.0)
    n_pix = jnp.sum(weight > 0, axis=(1, 2))
    flux = jnp.sum(weight, axis=(1, 2))
    offs = jnp.arange(-hw, hw + 1, dtype=jnp.float32)
    safe = jnp.where(flux > 0, flux, 1.0)
    cy = py + jnp.sum(weight * offs[None, :, None], axis=(1, 2)) / safe
    cx = px + jnp.sum(weight * offs[None, None, :], axis=(1, 2)) / safe
    # the brightest pixel of the 3×3 core: for a hot pixel the filtered maximum may sit on a neighbour
    peak_pix = jnp.max(wins[:, hw - 1:hw + 2, hw - 1:hw + 2], axis=(1, 2))
    core = 9.0 * smooth.reshape(-1)[flat]  # the 3×3 sum of the residual about the peak
    sharp_ok = peak_pix <= config.max_sharpness * core
    star = is_peak & (n_pix >= config.min_pixels) & (flux > 0) & sharp_ok

    # step 5: drop a peak within window_px of a higher-ranked star (plateaus of saturated stars)
    near = ((jnp.abs(py[:, None] - py[None, :]) <= hw) & (jnp.abs(px[:, None] - px[None, :]) <= hw)
            & (jnp.arange(m)[None, :] < jnp.arange(m)[:, None]))  # (m, m): j ranks above i
    star &= ~jnp.any(near & star[None, :], axis=1)

    # step 6: the brightest `capacity` by flux
    k = min(capacity, m)
    _, keep = jax.lax.top_k(jnp.where(star, flux, -jnp.inf), k)
    valid = star[keep]
    xy = jnp.where(valid[:, None], jnp.stack([cx[keep], cy[keep]], -1), 0.0)
    mag = jnp.where(valid, config.zero_point - 2.5 * jnp.log10(jnp.where(valid, flux[keep], 1.0)), jnp.inf)
    if k < capacity:
        xy = jnp.pad(xy, ((0, capacity - k), (0, 0)))
        mag = jnp.pad(mag, (0, capacity - k), constant_values=jnp.inf)
        valid = jnp.pad(valid, (0, capacity - k))
    overflow = (jnp.sum(star) > capacity) | (n_peaks > m)
    return xy.astype(jnp.float32), mag.astype(jnp.float32), valid, overflow
