"""How a sensor detects stars, for centroid-level simulation: noise, completeness and bias by magnitude.

The four knobs of :class:`~jstarid.NoiseConfig` are constant over magnitude and detect by a hard cut at
the camera's limit. A real sensor does not: a star of magnitude m delivers S(m) electrons, its flux is
measured with the noise of those electrons and of the background, it is detected when the measured flux
clears a threshold, and its centroid wanders more the fainter it is. :class:`DetectionModel` writes
that down with a few numbers in electrons (all per scene: scalars or (B,) arrays, so an exposure
sweep is a batch axis), and ``js.simulate(..., detection=model)`` draws scenes from it. Per true star
(conventions §3):

1. **Band.** The catalog's V misses the sensor's band by a Gaussian σ_m (``NoiseConfig.magnitude_sigma``,
   the floor): m' = m + σ_m z₁ (the papers' magnitude noise, drawn from the same stream).
2. **Light.** f = 10^(−0.4 m') · (1 − v (r / r_corner)²) in units of a V = 0 star (vignetting v as
   :class:`~jstarid.SensorConfig`'s); stars closer than ``merge_radius_px`` blend into one detection
   at their flux-weighted centroid with their summed flux, named as the brightest of them
   (:func:`merge_close`).
3. **Measurement.** S = ``zero_point_e`` · f electrons, measured with variance S + B
   (B = ``background_e2``): S_obs = S (1 + ρ z₂), ρ = √(S + B) / S.
4. **Detection** when S (1 + ρ_d z₂) ≥ T (``threshold_e``), ρ_d = √(S + B_d) / S: a detector tests
   a peak, not the summed flux, so its background B_d (``detection_background_e2``) differs from B,
   but the noise is the same draw z₂. Completeness P = Φ((S − T) / √(S + B_d)) is a smooth function
   of magnitude, and the faintest detections are those whose noise was positive — they come out
   brighter than they are (the bias near the threshold), as in a real frame.
5. **Magnitude** m_obs = m' − 2.5 log₁₀(S_obs / S₀·10^(−0.4 m')), i.e. what the sensor measured.
6. **Position** noise σ(m) = √(σ₀² + c² (S + B_c) / S²) px per axis: the floor σ₀
   (``NoiseConfig.position_sigma_px``) and the photon term of a centroid — its error is the PSF's
   width over a signal-to-noise ratio (c = ``position_scale_px``, ≈ √2 σ_PSF for a centre of
   gravity), whose background B_c (``position_background_e2``) is that of the pixels the centroid
   weighs: its whole window, not only the PSF's core.

False detections keep :class:`~jstarid.NoiseConfig`'s clutter settings (count and brightness
distribution, conventions §3).

:meth:`DetectionModel.ideal` (``zero_point_e = inf``: no photometric noise, every star detected to the
camera's ``mag_limit``) is the papers' special case: with it, ``simulate`` gives the same scenes for
the same key as without a model. With a finite zero point the camera's ``mag_limit`` is the depth of
the identification catalog only, and the threshold decides what is detected — to V 9 or 11 on a
narrow camera, which the catalog's simulation list must reach (``load_catalog(sim_margin=…)``;
``simulate`` warns when it does not).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from jstarid import random_streams as streams
from jstarid.render import vignette as vignetting

__all__ = ["DetectionModel", "merge_close", "merge_window", "observe", "MERGE_WINDOW"]

@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DetectionModel:
    """A sensor's detection of stars (module docstring). Each field is a scalar or a (B,) array.

    Attributes:
        zero_point_e: electrons measured from a V = 0 star on the optical axis (e⁻); ``inf``: no
            photometric noise and a hard cut at the camera's ``mag_limit`` (the papers').
        background_e2: variance of a flux measurement without the star (e⁻²): sky, dark current and
            read noise over the pixels the flux is summed over.
        threshold_e: a star is detected when its detection statistic, in flux units, is at least
            this (e⁻).
        detection_background_e2: the background variance of the detection statistic (e⁻², in flux
            units).
        position_scale_px: c of the centroid's photon term c · √(S + B_c) / S (px per axis).
        position_background_e2: B_c, the background variance (e⁻²) the centroid's window holds.
        merge_radius_px: stars closer than this (px) are detected as one (0: never).
        vignetting: fraction of the light lost at the frame's farthest corner, growing as r² from the
            principal point (as :class:`~jstarid.SensorConfig`).
        sky_fraction: the part of every background that is sky light, vignetted as the stars are (the
            rest, dark current and read noise, is not): a corner's threshold falls with its sky.
    """

    zero_point_e: float = math.inf
    background_e2: float = 0.0
    threshold_e: float = 0.0
    detection_background_e2: float = 0.0
    position_scale_px: float = 0.0
    position_background_e2: float = 0.0
    merge_radius_px: float = 0.0
    vignetting: float = 0.0
    sky_fraction: float = 0.0

    @classmethod
    def ideal(cls) -> DetectionModel:
        """The papers' detection: no photometric noise, every star to the camera's limit."""
        return cls()

    @classmethod
    def from_sensor(cls, camera, sensor=None, centroid=None) -> DetectionModel:
        """The model of a rendered sensor and the centroid extractor (``js.render`` +
        ``js.extract_centroids``), from their settings alone.

        * zero point: the sensor's electrons from V = 0 in one exposure;
        * background: the per-pixel variance b = (sky + dark) t + read² over :data:`FLUX_PIXELS`
          pixels (the extractor sums the window's pixels above 2 σ: the PSF's core and a few noise
          pixels);
        * threshold: the extractor detects a peak of its 3 × 3-box-filtered frame above
          ``threshold_sigma`` times that filter's noise (√b / 3); a star centred at a random sub-pixel
          phase puts a fraction f₉ of its flux in the box, so in flux units T = 3 · threshold_sigma ·
          √b / f₉ and B_d = 9 b / f₉²;
        * position: c = √2 σ and B_c = b (2 ``window_px`` + 1)², the background of the extractor's
          whole window (the thresholded centre of gravity's error on single rendered stars,
          ``experiments/render_validation.py`` "crb": 1.7–3.7 × σ/SNR from V 2 to 7, which these two
          numbers reproduce within 12 %);
        * merge radius: the extractor drops a peak within ``window_px`` of a brighter one, whose window
          then holds both stars.

        Args:
            camera: :class:`~jstarid.Camera`.
            sensor: :class:`~jstarid.SensorConfig` (default ``js.sensor_for_camera(camera)``).
            centroid: :class:`~jstarid.CentroidConfig` (default: the extractor's defaults).
        """
        from jstarid.centroid import CentroidConfig
        from jstarid.render import sensor_for_camera

        sensor = sensor_for_camera(camera) if sensor is None else sensor
        centroid = CentroidConfig() if centroid is None else centroid
        sigma = math.sqrt(sensor.psf_sigma_px ** 2 + sensor.defocus_px ** 2 / 2 + sensor.smear_px ** 2 / 12)
        per_pixel = (sensor.sky_e_per_s + sensor.dark_e_per_s) * sensor.exposure_s + sensor.read_noise_e ** 2
        box = _box_fraction(sigma) ** 2
        return cls(zero_point_e=sensor.star_e_per_s_v0 * sensor.exposure_s,
                   background_e2=per_pixel * FLUX_PIXELS,
                   threshold_e=3.0 * centroid.threshold_sigma * math.sqrt(per_pixel) / box,
                   detection_background_e2=9.0 * per_pixel / box ** 2,
                   position_scale_px=math.sqrt(2.0) * sigma,
                   position_background_e2=per_pixel * (2 * centroid.window_px + 1) ** 2,
                   merge_radius_px=float(centroid.window_px),
                   vignetting=sensor.vignetting,
                   sky_fraction=sensor.sky_e_per_s * sensor.exposure_s / per_pixel)

    @classmethod
    def fit(cls, true_mag, detected, measured_mag=None, position_error_px=None, **options):
        """A model fitted to labelled real data: one record per catalog star that could have been
        detected (:func:`jstarid.detection_fit.fit_detection`, which documents the arguments).

        Returns:
            :class:`~jstarid.detection_fit.DetectionFit`: the model, the noise floors for
            :class:`~jstarid.NoiseConfig` (``fit.noise()``) and the magnitudes' zero-point offset.
        """
        from jstarid.detection_fit import fit_detection

        return fit_detection(true_mag, detected, measured_mag, position_error_px, **options)

    def replace(self, **changes) -> DetectionModel:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)

    def broadcast(self, batch_size: int) -> DetectionModel:
        """Every field as a (B,) float32 array."""
        def cast(name):
            arr = jnp.asarray(getattr(self, name), jnp.float32)
            if arr.ndim > 1 or (arr.ndim == 1 and arr.shape[0] not in (1, batch_size)):
                raise ValueError(f"DetectionModel.{name} must be a scalar or have shape ({batch_size},), "
                                 f"got {arr.shape}")
            return jnp.broadcast_to(arr, (batch_size,))
        return DetectionModel(**{f.name: cast(f.name) for f in dataclasses.fields(self)})

    def validate(self) -> None:
        """Raise ``ValueError`` on out-of-range settings (host side; values must be concrete)."""
        rules = {
            "zero_point_e": (lambda a: a > 0, "> 0 e⁻ (inf: no photometric noise)"),
            "background_e2": (lambda a: np.isfinite(a) & (a >= 0), "≥ 0 e⁻² and finite"),
            "threshold_e": (lambda a: np.isfinite(a) & (a >= 0), "≥ 0 e⁻ and finite"),
            "detection_background_e2": (lambda a: np.isfinite(a) & (a >= 0), "≥ 0 e⁻² and finite"),
            "position_scale_px": (lambda a: np.isfinite(a) & (a >= 0), "≥ 0 px and finite"),
            "position_background_e2": (lambda a: np.isfinite(a) & (a >= 0), "≥ 0 e⁻² and finite"),
            "merge_radius_px": (lambda a: np.isfinite(a) & (a >= 0) & (a <= 50), "in [0, 50] px"),
            "vignetting": (lambda a: (a >= 0) & (a < 1), "in [0, 1)"),
            "sky_fraction": (lambda a: (a >= 0) & (a <= 1), "in [0, 1]"),
        }
        for name, (ok, rule) in rules.items():
            try:
                a = np.asarray(getattr(self, name), np.float64)
            except (TypeError, jax.errors.TracerArrayConversionError) as err:
                raise ValueError(f"DetectionModel.{name} must be concrete for validation") from err
            if np.any(np.isnan(a)) or not np.all(ok(a)):
                raise ValueError(f"DetectionModel.{name} must be {rule}, got {getattr(self, name)}")

    # --- the model's curves (host side, NumPy; for checks, fits and figures) ---

    def relative_sigma(self, mag, background_e2=None) -> np.ndarray:
        """ρ(m) = √(S + B) / S, the flux measurement's relative noise at magnitude ``mag`` (on axis);
        ``background_e2`` replaces B (the centroid's B_c)."""
        s = self._electrons(mag)
        b = float(self.background_e2 if background_e2 is None else background_e2)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(np.isinf(s), 0.0, np.sqrt(s + b) / s)

    def completeness(self, mag, magnitude_sigma: float = 0.0, mag_limit: float = math.inf) -> np.ndarray:
        """Probability that a star of V ``mag`` on the axis is detected (merging aside):
        Φ((S − T) / √(S + B_d)) averaged over the band floor σ_m (Gauss–Hermite); the ideal model cuts
        at ``mag_limit``."""
        from scipy.special import ndtr

        mag = np.asarray(mag, np.float64)
        nodes, weights = np.polynomial.hermite_e.hermegauss(24)
        weights = weights / weights.sum()
        shifted = mag[..., None] + float(magnitude_sigma) * nodes
        if math.isinf(float(self.zero_point_e)):
            p = (shifted <= mag_limit).astype(np.float64)
        else:
            s = self._electrons(shifted)
            p = ndtr((s - float(self.threshold_e)) / np.sqrt(s + float(self.detection_background_e2)))
        return np.sum(p * weights, axis=-1)

    def position_sigma(self, mag, floor_px: float = 0.0) -> np.ndarray:
        """σ(m) = √(σ₀² + c² (S + B_c) / S²), the centroid noise per axis (px) at V ``mag`` on the axis."""
        rho = self.relative_sigma(mag, self.position_background_e2)
        return np.hypot(float(floor_px), float(self.position_scale_px) * rho)

    def magnitude_sigma(self, mag, floor: float = 0.0) -> np.ndarray:
        """Small-noise magnitude σ(m) = √(σ_m² + (1.0857 ρ(m))²) (mag) at V ``mag`` on the axis."""
        return np.hypot(float(floor), 2.5 / math.log(10.0) * self.relative_sigma(mag))

    def faintest_detectable(self, magnitude_sigma: float = 0.0, odds: float = 1e-9) -> float:
        """The magnitude past which fewer than ``odds`` of the stars are detected (V), the faintest
        over a batch of models with a finite zero point; ``inf`` when none has one (the camera's cut
        applies)."""
        from scipy.special import ndtri

        z = -float(ndtri(odds))
        zero = np.atleast_1d(np.asarray(self.zero_point_e, np.float64))
        finite = np.isfinite(zero)
        if not np.any(finite):
            return math.inf
        back = np.broadcast_to(np.asarray(self.detection_background_e2, np.float64), zero.shape)[finite]
        thresh = np.broadcast_to(np.asarray(self.threshold_e, np.float64), zero.shape)[finite]
        zero = zero[finite]
        # S − T = −z √(S + B): a quadratic in q = √(S + B), q² + z q − (T + B) = 0
        q = (-z + np.sqrt(z * z + 4.0 * (thresh + back))) / 2.0
        s = np.maximum(q * q - back, 1e-30)
        return float(np.max(-2.5 * np.log10(s / zero))) + z * float(magnitude_sigma)

    def simulation_depth(self, magnitude_sigma: float = 0.0) -> float:
        """How deep (V) a catalog's simulation list must reach for :func:`jstarid.simulate` to miss
        none of the stars this model detects more than 0.1 % of (rounded up to 0.1 mag, the cut the
        simulator itself checks); ``inf`` for the ideal model."""
        seen = self.faintest_detectable(magnitude_sigma, odds=1e-3)
        return math.ceil(10.0 * seen) / 10.0 if math.isfinite(seen) else math.inf

    def _electrons(self, mag):
        s0 = float(self.zero_point_e)
        with np.errstate(over="ignore"):
            return s0 * 10.0 ** (-0.4 * np.asarray(mag, np.float64))


# Pixels whose background a flux from jstarid.extract_centroids carries: its window's pixels above 2 σ
# are the PSF's core and a few noise pixels (chosen among 15, 25 and 40 by the magnitude scatter of
# rendered tetra3_test frames at V 7–8.5; experiments/detection_model.py compares the curves).
FLUX_PIXELS = 25.0

MERGE_WINDOW = 16  # fewest neighbours in x order each star is compared with for blends (merge_close)


def merge_window(candidates: int, radius_px: float, width_px: int) -> int:
    """The x-order window of :func:`merge_close` for scenes of up to ``candidates`` stars (static).

    A deep sky in a wide field puts many stars in a 2·radius column (thousands of V ≤ 9 stars in 25°
    of the Milky Way: 16 in 3 px of x): the window covers the mean count of a column with the candidates
    spread over the frame's width, plus 6 σ of a Poisson spread and 8 (≥ :data:`MERGE_WINDOW`); a frame
    that still needs more is flagged, never cut silently.
    """
    mean = candidates * 2.0 * radius_px / max(width_px, 1)
    return int(max(MERGE_WINDOW, math.ceil(mean + 6.0 * math.sqrt(mean) + 8.0)))


def _box_fraction(sigma: float) -> float:
    """Mean fraction of a 1-D Gaussian (σ px) in the 3 pixels about the pixel its centre falls in,
    over a uniform sub-pixel phase (the 3 × 3 box holds the square of it)."""
    from scipy.special import ndtr

    phase = (np.arange(64) + 0.5) / 64 - 0.5
    return float(np.mean(ndtr((1.5 - phase) / sigma) - ndtr((-1.5 - phase) / sigma)))


def merge_close(xy, flux, live, radius_px, window: int = MERGE_WINDOW):
    """Blends of one scene: each star joins the brightest star within ``radius_px`` of it (itself if
    none is brighter); a star that others join takes their summed flux and flux-weighted centroid.

    Stars are compared with their ``window`` neighbours on each side in x order (a pair further apart
    in that order would need > ``window`` stars in a 2·radius column of the frame: flagged).

    Args:
        xy: (K, 2) true positions (px).
        flux: (K,) fluxes (any unit; 0 for stars that give no light).
        live: (K,) bool, stars that can blend (in the field and lit).
        radius_px: scalar, blend radius (px).
        window: static, neighbours on each side.

    Returns:
        ``(xy (K, 2), flux (K,), absorbed (K,) bool, overflow)``: per star, the blend's centroid and
        flux (its own where nothing joined it), whether it joined a brighter star (and is no detection
        of its own), and whether the window was too short anywhere.
    """
    k = flux.shape[0]
    w = min(window, k - 1)
    if w < 1:
        return xy, flux, jnp.zeros((k,), bool), jnp.bool_(False)
    order = jnp.argsort(jnp.where(live, xy[:, 0], jnp.inf))
    xs, ys, fs, ls = xy[order, 0], xy[order, 1], flux[order], live[order]
    offsets = jnp.concatenate([jnp.arange(-w, 0), jnp.arange(1, w + 1)])
    raw = jnp.arange(k)[:, None] + offsets[None, :]  # (K, 2w) neighbour positions in x order
    nb = jnp.clip(raw, 0, k - 1)
    d2 = (xs[nb] - xs[:, None]) ** 2 + (ys[nb] - ys[:, None]) ** 2
    close = (raw >= 0) & (raw < k) & ls[nb] & ls[:, None] & (d2 < radius_px ** 2)
    nb_flux = jnp.where(close, fs[nb], -jnp.inf)
    best = jnp.argmax(nb_flux, axis=1)
    brighter = jnp.take_along_axis(nb_flux, best[:, None], axis=1)[:, 0] > fs
    target = jnp.where(brighter, nb[jnp.arange(k), best], jnp.arange(k))
    total = jax.ops.segment_sum(fs, target, num_segments=k)
    moment = jax.ops.segment_sum(fs[:, None] * jnp.stack([xs, ys], -1), target, num_segments=k)
    merged = jnp.where((total > fs)[:, None], moment / jnp.where(total > 0, total, 1.0)[:, None],
                       jnp.stack([xs, ys], -1))
    # the window ends before the stars within reach in x do
    last = jnp.clip(jnp.arange(k) + w, 0, k - 1)
    overflow = jnp.any(ls & ls[last] & (jnp.arange(k) + w < k) & (xs[last] - xs < radius_px))
    # back to the caller's order
    out_xy = jnp.zeros_like(xy).at[order].set(merged.astype(xy.dtype))
    out_flux = jnp.zeros_like(flux).at[order].set(jnp.where(total > fs, total, fs))
    absorbed = jnp.zeros((k,), bool).at[order].set(brighter & ls)
    return out_xy, out_flux, absorbed, overflow


def observe(seed, model: DetectionModel, noise, true_mag, xy, in_field, *, camera, merge: int):
    """Steps 1–6 of the module docstring for one scene's K candidate stars.

    Args:
        seed: (2,) uint32 scene seed (:func:`~jstarid.random_streams.scene_seed`).
        model: the scene's :class:`DetectionModel` (scalar fields).
        noise: the scene's :class:`~jstarid.NoiseConfig` (its floors ``magnitude_sigma`` and
            ``position_sigma_px``).
        true_mag: (K,) catalog V (mag; inf for padding).
        xy: (K, 2) true positions (px).
        in_field: (K,) bool.
        camera: the :class:`~jstarid.Camera` (static).
        merge: static; the blends' x-order window (:func:`merge_window`), 0 when no scene of the
            batch blends (``merge_radius_px`` 0 everywhere).

    Returns:
        ``(mag (K,), detected (K,) bool, sigma_px (K,), xy (K, 2), overflow)``: the measured magnitudes,
        which stars are detected, each one's position σ (px), the positions (blends at their
        centroid) and whether blending overflowed its window.
    """
    k = true_mag.shape[0]
    band = true_mag + noise.magnitude_sigma * streams.normals(seed, streams.MAG, k)  # step 1
    ideal = jnp.isinf(model.zero_point_e)
    # step 2: relative flux (V = 0 units), vignetted as js.render does
    vignette = vignetting(xy[:, 0], xy[:, 1], model.vignetting, height=camera.height, width=camera.width,
                          cx=camera.cx, cy=camera.cy)
    own = jnp.where(jnp.isfinite(band), 10.0 ** (-0.4 * band), 0.0) * vignette
    if merge:
        xy, lit, absorbed, overflow = merge_close(xy, own, in_field & (own > 0), model.merge_radius_px,
                                                  window=int(merge))
        blend = jnp.where(own > 0, lit / jnp.where(own > 0, own, 1.0), 1.0)
    else:
        lit, absorbed, overflow, blend = own, jnp.zeros((k,), bool), jnp.bool_(False), 1.0
    # step 3: the measurement, relative noise ρ = √(S + B) / S = √(1/S + B/S²); the sky's part of
    # every background is vignetted as the star is
    inv_s = jnp.where(ideal | (lit <= 0), 0.0, 1.0 / (model.zero_point_e * jnp.where(lit > 0, lit, 1.0)))
    dim = 1.0 - model.sky_fraction * (1.0 - vignette)
    rho = jnp.sqrt(inv_s + dim * model.background_e2 * inv_s ** 2)
    z = streams.normals(seed, streams.FLUX, k)
    measured = 1.0 + rho * z  # S_obs / S
    # step 5: the magnitude the sensor reports (exactly m' when nothing changes the light)
    gain = vignette * blend * measured
    mag = band - 2.5 * jnp.log10(jnp.maximum(gain, 1e-30))
    # step 4: detection (the ideal model cuts at the camera's limit instead)
    limit = jnp.where(ideal, camera.mag_limit, jnp.inf)
    rho_d = jnp.sqrt(inv_s + dim * model.detection_background_e2 * inv_s ** 2)
    threshold = jnp.sqrt(dim) * model.threshold_e / model.zero_point_e  # T ∝ the background's σ
    cleared = (lit * (1.0 + rho_d * z) >= threshold) & (1.0 + rho_d * z > 0)
    detected = in_field & ~absorbed & (measured > 0) & cleared & (mag <= limit) & jnp.isfinite(mag)
    # step 6: position noise σ per star
    rho_c = jnp.sqrt(inv_s + dim * model.position_background_e2 * inv_s ** 2)
    sigma = jnp.hypot(noise.position_sigma_px, model.position_scale_px * rho_c)
    return mag, detected, sigma, xy, overflow
