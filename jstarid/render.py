"""Star images from scenes: photons → electrons → counts, the pixels between the sky and the centroids.

:func:`render` turns a batch of :class:`~jstarid.scene.Scene` (every valid detection, true or false
star, at its ``xy`` with its ``mag``) into detector frames (B, H, W) float32 in counts, for a
:class:`SensorConfig`. Per frame (jit-compiled, vmapped, the batch sharded over the devices like
``js.simulate``):

1. **Photometry.** A star of magnitude m delivers ``photons_v0 · 10^(−0.4 m)`` photons/s/m² (V = 0:
   ≈ 1.9·10¹⁰, Liebe 2002, "Accuracy performance of star trackers — a tutorial", §2), times the
   entrance pupil area, transmission, quantum efficiency, exposure and the vignetting at its position
   → electrons.
2. **PSF, pixel-integrated.** A Gaussian of σ px, integrated over each pixel exactly (erf differences:
   separable), in a fixed window about the star (:attr:`SensorConfig.window_px`), scattered into the
   frame (pixels outside the frame dropped): the cost is a star's window, not a frame per star.
   Defocus and motion smear are the Gaussian convolved with a ring of radius ``defocus_px`` and with
   a segment of ``smear_px`` along ``smear_angle_rad``, each written as the mean of Gaussians at
   evenly spaced points of the ring and segment (spaced ≤ σ/1.5 apart, so the sum is smooth), so
   every shape stays pixel-integrated exactly. The smear is centred on the star: the centroid of a
   smeared star is its mid-exposure position.
3. **Background.** Sky (× vignetting) and dark current per pixel, plus ``hot_pixels`` fixed pixels
   with a high dark rate (the same pixels in every frame of a sensor: drawn from ``hot_pixel_seed``).
4. **Noise.** Shot noise on everything collected and read noise: by default one Gaussian per pixel
   with variance ``mean + read²`` (the normal approximation to Poisson: exact in the mean and
   variance, off only in the skew of pixels holding a few electrons, where read noise dominates);
   ``shot_noise="poisson"`` draws exact Poisson counts instead (several times slower).
5. **Detector.** Electrons clipped to the full well (saturation), converted at ``gain_e_per_adu``
   with ``bias_adu``, rounded to integers and clipped to the ADC's ``bit_depth``; a file that stores
   the counts in more bits (``stored_bits``: e.g. 12-bit counts × 16 in a 16-bit TIFF) is scaled up.

Simulate the scenes without position noise (``NoiseConfig(position_sigma_px=0)``) and, for faint
stars to appear in the frame as they do in the sky, with a camera limit deeper than the detection
limit you expect (``camera.replace(mag_limit=…)``): the centroid errors, missed and false
detections then come from the pixels (:func:`jstarid.extract_centroids`).

Pixels as everywhere in jstarid: x = column, y = row, origin at the centre of pixel (0, 0), so pixel
(i, j) covers x ∈ [j − ½, j + ½], y ∈ [i − ½, i + ½].
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.camera import Camera
from jstarid.geometry import precise
from jstarid.random_streams import normals, scene_seed
from jstarid.runtime import map_batch
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Scene

__all__ = ["SensorConfig", "mean_electrons", "psf_offsets", "render", "sensor_for_camera", "vignette"]

PIXEL_NOISE_STREAM = 101  # the frame's counter stream for pixel noise (random_streams: scene draws < 100)
LIEBE_PHOTONS_V0 = 1.91e10  # photons/s/m² from a V = 0 star, visible band (Liebe 2002, §2)


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    """Frozen settings of :func:`render` (hashable: a static jit argument).

    Attributes:
        exposure_s: exposure time (s).
        aperture_mm: entrance pupil diameter (mm; focal length / f-number).
        transmission: fraction of the photons the optics (and atmosphere) pass.
        quantum_efficiency: electrons per photon reaching the detector.
        photons_v0: photons/s/m² from a V = 0 star in the sensor's band.
        psf_sigma_px: σ of the Gaussian PSF (px), > 0.
        defocus_px: radius of the defocus ring (px; 0: in focus).
        smear_px: length of the motion smear during the exposure (px; 0: none).
        smear_angle_rad: direction of the smear from the +x (column) axis (rad).
        sky_e_per_s: sky background per pixel at the optical axis (e⁻/s).
        dark_e_per_s: dark current per pixel (e⁻/s).
        read_noise_e: read noise σ (e⁻).
        vignetting: fractional loss at the farthest corner, falling off as r² from the principal
            point; applied to the sky and to the stars.
        hot_pixels: number of hot pixels (fixed per sensor).
        hot_pixel_e_per_s: dark rate of a hot pixel (e⁻/s).
        hot_pixel_seed: seed of the hot pixels' positions.
        full_well_e: saturation level (e⁻).
        gain_e_per_adu: electrons per count.
        bias_adu: offset added to every pixel (counts).
        bit_depth: ADC resolution (bits): counts are integers in [0, 2^bit_depth − 1].
        stored_bits: bits of the stored frame (``None``: ``bit_depth``); counts are multiplied by
            2^(stored_bits − bit_depth).
        shot_noise: ``"gaussian"`` (normal approximation, default) or ``"poisson"`` (exact).
    """

    exposure_s: float = 0.1
    aperture_mm: float = 13.0
    transmission: float = 0.8
    quantum_efficiency: float = 0.6
    photons_v0: float = LIEBE_PHOTONS_V0
    psf_sigma_px: float = 0.8
    defocus_px: float = 0.0
    smear_px: float = 0.0
    smear_angle_rad: float = 0.0
    sky_e_per_s: float = 0.0
    dark_e_per_s: float = 50.0
    read_noise_e: float = 10.0
    vignetting: float = 0.0
    hot_pixels: int = 0
    hot_pixel_e_per_s: float = 20_000.0
    hot_pixel_seed: int = 0
    full_well_e: float = 20_000.0
    gain_e_per_adu: float = 5.0
    bias_adu: float = 100.0
    bit_depth: int = 12
    stored_bits: int | None = None
    shot_noise: str = "gaussian"

    def __post_init__(self):
        positive = ("exposure_s", "aperture_mm", "transmission", "quantum_efficiency", "photons_v0",
                    "psf_sigma_px", "full_well_e", "gain_e_per_adu")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"SensorConfig.{name} must be a positive finite number, got {value}")
        non_negative = ("defocus_px", "smear_px", "sky_e_per_s", "dark_e_per_s", "read_noise_e",
                        "hot_pixel_e_per_s", "bias_adu")
        for name in non_negative:
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"SensorConfig.{name} must be ≥ 0 and finite, got {value}")
        for name in ("transmission", "quantum_efficiency"):
            if getattr(self, name) > 1:
                raise ValueError(f"SensorConfig.{name} is a fraction ≤ 1, got {getattr(self, name)}")
        if self.psf_sigma_px < 0.1:
            raise ValueError(f"SensorConfig.psf_sigma_px must be ≥ 0.1 px, got {self.psf_sigma_px}")
        if not 0 <= self.vignetting < 1:
            raise ValueError(f"SensorConfig.vignetting must be in [0, 1), got {self.vignetting}")
        if int(self.hot_pixels) != self.hot_pixels or self.hot_pixels < 0:
            raise ValueError(f"SensorConfig.hot_pixels must be a count ≥ 0, got {self.hot_pixels}")
        if not 1 <= int(self.bit_depth) <= 24:
            raise ValueError(f"SensorConfig.bit_depth must be 1–24 bits, got {self.bit_depth}")
        if self.stored_bits is not None and not self.bit_depth <= self.stored_bits <= 32:
            raise ValueError(f"SensorConfig.stored_bits must be from bit_depth ({self.bit_depth}) to "
                             f"32, got {self.stored_bits}")
        if self.shot_noise not in ("gaussian", "poisson"):
            raise ValueError(f"SensorConfig.shot_noise must be 'gaussian' or 'poisson', got "
                             f"{self.shot_noise!r}")
        if self.window_px > 64:
            raise ValueError(f"the PSF window would be {2 * self.window_px + 1} px wide (defocus "
                             f"{self.defocus_px} px, smear {self.smear_px} px): at most 129 px")

    def replace(self, **changes) -> SensorConfig:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    @property
    def window_px(self) -> int:
        """Half-width of the square window a star is rendered in (px): the PSF beyond it holds
        < 10⁻⁶ of the flux (4.9 σ past the ring and the smear's ends)."""
        return int(math.ceil(4.9 * self.psf_sigma_px + self.defocus_px + self.smear_px / 2)) + 1

    @property
    def star_e_per_s_v0(self) -> float:
        """Electrons per second from a V = 0 star on the optical axis."""
        area = math.pi * (self.aperture_mm * 1e-3 / 2) ** 2
        return self.photons_v0 * area * self.transmission * self.quantum_efficiency

    @property
    def counts_per_e(self) -> float:
        """Stored counts per electron (the gain and the stored-bits scale)."""
        return 2.0 ** ((self.stored_bits or self.bit_depth) - self.bit_depth) / self.gain_e_per_adu

    def zero_point(self) -> float:
        """The magnitude of a star whose whole flux is one stored count on the optical axis: give it
        to :class:`jstarid.CentroidConfig` (``zero_point``) and extracted magnitudes are V."""
        return 2.5 * math.log10(self.star_e_per_s_v0 * self.exposure_s * self.counts_per_e)

    def star_electrons(self, mag):
        """Electrons collected from stars of magnitude ``mag`` on the optical axis (array-like)."""
        return self.star_e_per_s_v0 * self.exposure_s * 10.0 ** (-0.4 * np.asarray(mag, np.float64))


# The detection target of a generic sensor (sensor_for_camera): a star at the camera's limit gives
# this many electrons, ≈ 2.6× the 5 σ threshold of jstarid.extract_centroids with the generic
# sensor's noise (10 e⁻ read, 5 e⁻ dark per frame; σ = 0.8 px: 88 % of the flux in the 3 × 3 box).
LIMIT_ELECTRONS = 500.0

# tetra3_test (FLIR BFS-U3-31S4M-C, Sony IMX265, 2×2 binned, 35 mm f/1.9, from the ground), fitted
# to the four frames of shared/data/real (experiments/render_validation.py measures the match):
# 12-bit counts stored ×16 in 16-bit TIFFs (every value a multiple of 16); the local noise
# (134 stored counts at a 3,344 median, 201 at 6,416) against the background gives 7.4 stored
# counts per electron (2.15 e⁻ per 12-bit count, near the IMX265's unity gain) and a bias of ≈ 60
# 12-bit counts; a round Gaussian fitted to unsaturated stars has σ 0.62–0.66 px, i.e. 0.57 px
# before pixel integration; the extractor's zero point V 16.7 sets the exposure × throughput
# (0.33 s, 0.7 × 0.65 through the 18.4 mm pupil); the sky rate gives a 3,200-count median; the
# background tiles fall to ≈ 50 % at the corners (bias removed).
_TETRA3_TEST = dict(
    exposure_s=0.33, aperture_mm=35.0 / 1.9, transmission=0.7, quantum_efficiency=0.65,
    psf_sigma_px=0.57, sky_e_per_s=1070.0, dark_e_per_s=5.0, read_noise_e=2.2, vignetting=0.5,
    hot_pixels=0, full_well_e=10_500.0, gain_e_per_adu=2.15, bias_adu=60.0, bit_depth=12,
    stored_bits=16)


def sensor_for_camera(camera: Camera, **overrides) -> SensorConfig:
    """The default sensor of a camera.

    ``tetra3_test`` gets the sensor fitted to its real frames (module constant ``_TETRA3_TEST``:
    calibration in the comment above it). Any other camera gets a generic space star tracker: no sky,
    12-bit ADC at 5 e⁻/count, 20,000 e⁻ full well, 10 e⁻ read noise, 50 e⁻/s dark current,
    σ = 0.8 px, 0.1 s, and an entrance pupil sized so that a star at the camera's ``mag_limit`` gives
    ``LIMIT_ELECTRONS`` (500 e⁻): detected comfortably, as the simulator assumes (a V 6 limit gives a
    13 mm pupil).

    Args:
        camera: a :class:`~jstarid.Camera`.
        **overrides: :class:`SensorConfig` fields to change.

    Returns:
        :class:`SensorConfig`.
    """
    if camera.name == "tetra3_test":
        return SensorConfig(**{**_TETRA3_TEST, **overrides})
    base = SensorConfig()
    per_area = base.photons_v0 * base.transmission * base.quantum_efficiency * base.exposure_s
    area = LIMIT_ELECTRONS / (per_area * 10.0 ** (-0.4 * camera.mag_limit))
    aperture = 2e3 * math.sqrt(area / math.pi)
    return SensorConfig(**{"aperture_mm": aperture, **overrides})


def render(key, scenes: Scene, camera: Camera, sensor: SensorConfig | None = None, *,
           shard: bool = True) -> jax.Array:
    """Detector frames of a batch of scenes (module docstring).

    Args:
        key: a PRNG key (split into one per frame) or a (B,) array of frame keys: frame i depends only
            on its key and scene, so ``render(keys[i:i+1], scenes[i:i+1])`` is row i of the batch.
        scenes: (B, N) :class:`~jstarid.Scene`: every valid detection is rendered at ``xy`` (px) with
            ``mag`` (V mag); ``truth`` is not read (false stars are rendered like stars).
        camera: the :class:`~jstarid.Camera` (frame size, principal point for the vignetting).
        sensor: :class:`SensorConfig` (default: :func:`sensor_for_camera`).
        shard: split the batch over every device (:func:`jstarid.runtime.map_batch`).

    Returns:
        (B, H, W) float32 frames in stored counts (integers).

    Raises:
        ValueError: scenes of the wrong shape, keys that do not match the batch, or more hot pixels
            than the frame has.
    """
    sensor = sensor_for_camera(camera) if sensor is None else sensor
    xy, mag, valid = (jnp.asarray(a) for a in (scenes.xy, scenes.mag, scenes.valid))
    if xy.ndim != 3 or xy.shape[-1] != 2 or mag.shape != xy.shape[:2] or valid.shape != mag.shape:
        raise ValueError(f"render expects a batch of scenes: xy (B, N, 2), mag and valid (B, N); got "
                         f"{xy.shape}, {mag.shape}, {valid.shape}")
    if sensor.hot_pixels > camera.height * camera.width:
        raise ValueError(f"{sensor.hot_pixels} hot pixels do not fit a {camera.width}×{camera.height} frame")
    b = xy.shape[0]
    seeds = _frame_seeds(key, b)
    hot_rows, hot_cols = _hot_pixels(sensor, camera)
    static = dict(sensor=sensor, height=camera.height, width=camera.width,
                  cx=float(camera.cx), cy=float(camera.cy))
    args = (seeds, xy.astype(jnp.float32), mag.astype(jnp.float32), valid)
    if b == 0:
        return jnp.zeros((0, camera.height, camera.width), jnp.float32)
    if shard:
        return map_batch(_render_batch, args, (hot_rows, hot_cols), static=static)
    return _render_batch_jit(*args, hot_rows, hot_cols, **static)


def _frame_seeds(key, b: int):
    """(B, 2) uint32 Threefry seeds, one per frame, from one key or (B,) keys."""
    key = jnp.asarray(key) if not isinstance(key, jax.Array) else key
    typed = jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key)
    single = key.ndim == 0 if typed else key.shape == (2,)
    if single:
        key = jax.random.split(key, b)
    n = key.shape[0] if key.ndim else 0
    if n != b:
        raise ValueError(f"render got {n} frame keys for {b} scenes")
    return jax.vmap(scene_seed)(key)


def _hot_pixels(sensor: SensorConfig, camera: Camera):
    """(k,) int32 rows and columns of the sensor's hot pixels (a fixed draw from its seed)."""
    rng = np.random.default_rng(sensor.hot_pixel_seed)
    flat = rng.choice(camera.height * camera.width, size=int(sensor.hot_pixels), replace=False)
    return (jnp.asarray(flat // camera.width, jnp.int32), jnp.asarray(flat % camera.width, jnp.int32))


def psf_offsets(sensor: SensorConfig) -> np.ndarray:
    """(K, 2) offsets (dx, dy) in px of the Gaussians whose mean is the PSF: the defocus ring's
    points (spaced ≤ σ/1.5 along it) convolved with the smear's (the midpoints of equal parts of
    the segment, ≤ σ/1.5 long: the segment's variance L²/12 is kept to a factor 1 − 1/n²)."""
    step = sensor.psf_sigma_px / 1.5
    ring = np.zeros((1, 2))
    if sensor.defocus_px > 0:
        n = max(8, math.ceil(2 * math.pi * sensor.defocus_px / step))
        t = 2 * math.pi * np.arange(n) / n
        ring = sensor.defocus_px * np.stack([np.cos(t), np.sin(t)], axis=1)
    line = np.zeros((1, 2))
    if sensor.smear_px > 0:
        n = math.ceil(sensor.smear_px / step)
        s = ((np.arange(n) + 0.5) / n - 0.5) * sensor.smear_px  # midpoints of n equal parts
        line = s[:, None] * np.array([[math.cos(sensor.smear_angle_rad), math.sin(sensor.smear_angle_rad)]])
    return (ring[:, None, :] + line[None, :, :]).reshape(-1, 2)


def _pixel_fractions(centre, lo, n: int, sigma: float):
    """(…, n) fraction of a 1-D Gaussian (mean ``centre`` (…,), σ px) in pixels lo, …, lo + n − 1."""
    steps = jnp.arange(n + 1, dtype=jnp.float32).reshape((1,) * lo.ndim + (n + 1,))
    edges = lo[..., None] + steps - 0.5 - centre[..., None]
    cdf = 0.5 * jax.lax.erf(edges / np.float32(sigma * math.sqrt(2.0)))
    return cdf[..., 1:] - cdf[..., :-1]


def vignette(x, y, fraction, *, height: int, width: int, cx: float, cy: float):
    """Fraction of the light reaching pixel position (x, y): 1 − v (r / r_corner)², v = ``fraction``
    lost at the frame's farthest corner (a scalar; traceable), r from the principal point (cx, cy)."""
    corner2 = max((u - cx) ** 2 + (w - cy) ** 2 for u in (-0.5, width - 0.5) for w in (-0.5, height - 0.5))
    per_r2 = fraction / corner2
    per_r2 = np.float32(per_r2) if isinstance(per_r2, float) else per_r2  # a sensor's: float32 once
    return 1.0 - per_r2 * ((x - cx) ** 2 + (y - cy) ** 2)


def _vignette(x, y, *, sensor: SensorConfig, height: int, width: int, cx: float, cy: float):
    """:func:`vignette` of the sensor's vignetting (ones when it has none)."""
    if sensor.vignetting == 0:
        return jnp.ones_like(x)
    return vignette(x, y, float(sensor.vignetting), height=height, width=width, cx=cx, cy=cy)


def _mean_electrons(xy, mag, valid, hot_rows, hot_cols, *, sensor: SensorConfig, height: int,
                    width: int, cx: float, cy: float):
    """Expected electrons (H, W) float32 of one frame before noise: stars, sky, dark, hot pixels."""
    geometry = dict(sensor=sensor, height=height, width=width, cx=cx, cy=cy)
    t = np.float32(sensor.exposure_s)
    # 1. electrons of each star (0 for padding)
    electrons = np.float32(sensor.star_e_per_s_v0) * t * 10.0 ** (-0.4 * mag)
    electrons = jnp.where(valid, electrons * _vignette(xy[:, 0], xy[:, 1], **geometry), 0.0)
    # 2. each star's window: the PSF as the mean of K pixel-integrated Gaussians (psf_offsets)
    half = sensor.window_px
    side = 2 * half + 1
    offsets = jnp.asarray(psf_offsets(sensor), jnp.float32)  # (K, 2)
    centre = jnp.where(valid[:, None], xy, -1e4)  # padding far off the frame: its window is dropped
    lo = jnp.round(centre) - half  # (N, 2) first column and row of the window
    at = centre[:, None, :] + offsets[None, :, :]  # (N, K, 2)
    fx = _pixel_fractions(at[..., 0], lo[:, None, 0], side, sensor.psf_sigma_px)  # (N, K, side)
    fy = _pixel_fractions(at[..., 1], lo[:, None, 1], side, sensor.psf_sigma_px)
    stamp = precise.einsum("nky,nkx->nyx", fy, fx) * (electrons / offsets.shape[0])[:, None, None]
    rows = (lo[:, 1, None] + jnp.arange(side)[None, :]).astype(jnp.int32)  # (N, side)
    cols = (lo[:, 0, None] + jnp.arange(side)[None, :]).astype(jnp.int32)
    # 3. background: sky × vignetting + dark current, hot pixels
    ys = jnp.arange(height, dtype=jnp.float32)[:, None]
    xs = jnp.arange(width, dtype=jnp.float32)[None, :]
    frame = (np.float32(sensor.sky_e_per_s) * _vignette(xs, ys, **geometry)
             + np.float32(sensor.dark_e_per_s)) * t
    frame = jnp.broadcast_to(frame, (height, width))
    frame = frame.at[hot_rows, hot_cols].add(np.float32(sensor.hot_pixel_e_per_s) * t)
    # out-of-frame pixels of a window are dropped (a negative index would wrap around, so it is
    # sent past the end first)
    rows = jnp.where(rows < 0, height, rows)
    cols = jnp.where(cols < 0, width, cols)
    return frame.at[rows[:, :, None], cols[:, None, :]].add(stamp, mode="drop")


def _detector(seed, mean, *, sensor: SensorConfig):
    """Stored counts (H, W) float32 of a frame of expected electrons ``mean``: shot and read noise,
    full well, gain, bias, ADC, stored bits."""
    z = normals(seed, PIXEL_NOISE_STREAM, mean.shape)
    if sensor.shot_noise == "poisson":
        key = jax.random.wrap_key_data(seed, impl="threefry2x32")
        frame = jax.random.poisson(key, mean).astype(jnp.float32) + np.float32(sensor.read_noise_e) * z
    else:
        frame = mean + jnp.sqrt(jnp.maximum(mean, 0.0) + np.float32(sensor.read_noise_e ** 2)) * z
    electrons = jnp.clip(frame, 0.0, np.float32(sensor.full_well_e))
    adu = jnp.round(electrons / np.float32(sensor.gain_e_per_adu) + np.float32(sensor.bias_adu))
    adu = jnp.clip(adu, 0.0, np.float32(2 ** sensor.bit_depth - 1))
    return adu * np.float32(2 ** ((sensor.stored_bits or sensor.bit_depth) - sensor.bit_depth))


def _render_batch(seeds, xy, mag, valid, hot_rows, hot_cols, **static):
    """Frames of a batch (vmap of :func:`_mean_electrons` then :func:`_detector`; hot pixels shared)."""
    def one(seed, xy1, mag1, valid1):
        mean = _mean_electrons(xy1, mag1, valid1, hot_rows, hot_cols, **static)
        return _detector(seed, mean, sensor=static["sensor"])

    return jax.vmap(one)(seeds, xy, mag, valid)


_STATIC = ("sensor", "height", "width", "cx", "cy")
_render_batch_jit = stored_jit(_render_batch, static_argnames=_STATIC)


def mean_electrons(scenes: Scene, camera: Camera, sensor: SensorConfig | None = None) -> jax.Array:
    """Expected electrons (B, H, W) float32 of each frame before noise and the detector (stars, sky,
    dark current, hot pixels): what :func:`render` draws its noise about (for tests and bounds)."""
    sensor = sensor_for_camera(camera) if sensor is None else sensor
    hot_rows, hot_cols = _hot_pixels(sensor, camera)
    return _mean_batch(jnp.asarray(scenes.xy, jnp.float32), jnp.asarray(scenes.mag, jnp.float32),
                       jnp.asarray(scenes.valid), hot_rows, hot_cols, sensor=sensor,
                       height=camera.height, width=camera.width, cx=float(camera.cx), cy=float(camera.cy))


@functools.partial(stored_jit, static_argnames=_STATIC)
def _mean_batch(xy, mag, valid, hot_rows, hot_cols, **static):
    return jax.vmap(lambda p, m, v: _mean_electrons(p, m, v, hot_rows, hot_cols, **static))(xy, mag, valid)
