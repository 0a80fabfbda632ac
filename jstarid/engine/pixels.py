"""Sweeps from pixels: the sky's scenes rendered, their centroids extracted and labelled.

With ``pixels=True`` a sweep's scenes are not the simulator's centroids but what a star tracker would
measure: the sky is simulated deeper than the camera's limit (:data:`RENDER_DEPTH_MAG`: faint stars
are in the frame, and the pixels decide which are detected), each frame is rendered
(:func:`jstarid.render`), its centroids extracted (:func:`jstarid.extract_centroids`) and every
detection labelled with the star it came from (:func:`label_detections`), so the outcome rules and
the attitude error are the same as for simulated centroids. The levels may vary
:class:`~jstarid.SensorConfig` fields (:data:`SENSOR_AXES`: exposure, read noise, defocus, smear …)
as well as noise fields; each level's frames are one batched render-and-extract call per chunk of
frames (a level's sensor is a static setting: one compilation per level).
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.centroid import CentroidConfig, extract_centroids
from jstarid.render import SensorConfig, render
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Scene

__all__ = ["MATCH_PX", "RENDER_DEPTH_MAG", "SENSOR_AXES", "detect_scenes", "label_detections",
           "sensor_levels"]

# SensorConfig field → how a figure labels it
SENSOR_AXES = {
    "exposure_s": "exposure (s)",
    "read_noise_e": "read noise (e⁻)",
    "defocus_px": "defocus ring radius (px)",
    "smear_px": "motion smear (px)",
    "psf_sigma_px": "PSF σ (px)",
    "sky_e_per_s": "sky background (e⁻/s/px)",
    "dark_e_per_s": "dark current (e⁻/s/px)",
    "hot_pixels": "hot pixels",
}
RENDER_DEPTH_MAG = 1.5  # stars rendered to the camera's limit + this (the generic sensor: 125 e⁻)
MATCH_PX = 1.5  # a detection within this of a rendered star's image (its ring and smear) is that star
FRAMES_PER_CALL = 32  # frames rendered and extracted per call (≈ 100 MB of 1024² float32 frames)


def sensor_levels(levels, sensor: SensorConfig) -> list[SensorConfig]:
    """Each level's sensor: ``sensor`` with the level's :data:`SENSOR_AXES` fields.

    Raises:
        ValueError: a level's value the sensor refuses (e.g. a negative exposure).
    """
    out = []
    for level in levels:
        changes = {k: (int(v) if k == "hot_pixels" else float(v)) for k, v in level.items()
                   if k in SENSOR_AXES}
        out.append(dataclasses.replace(sensor, **changes))
    return out


@stored_jit
def label_detections(det_xy, det_valid, star_xy, star_valid, star_truth, match_px=MATCH_PX):
    """Truth of each detection: the row of the nearest rendered star within ``match_px``, else −1.

    Args:
        det_xy: (B, N, 2) detections (px). det_valid: (B, N) bool.
        star_xy: (B, M, 2) rendered stars (px). star_valid: (B, M) bool. star_truth: (B, M) int32
            catalog row of each (−1: a false star, or a star the identification catalog lacks).
        match_px: reach (px; traced: a sweep over defocus reuses the compiled labeller).

    Returns:
        (B, N) int32 catalog rows (−1: no star, a false star, or padding).
    """
    d = jnp.linalg.norm(det_xy[:, :, None, :] - star_xy[:, None, :, :], axis=-1)  # (B, N, M)
    d = jnp.where(star_valid[:, None, :], d, jnp.inf)
    j = jnp.argmin(d, axis=2)
    near = jnp.take_along_axis(d, j[:, :, None], axis=2)[:, :, 0] <= match_px
    return jnp.where(det_valid & near, jnp.take_along_axis(star_truth, j, axis=1), -1).astype(jnp.int32)


def detect_scenes(keys, sky: Scene, camera, sensor: SensorConfig, centroid: CentroidConfig, *,
                  capacity: int, frames_per_call: int = FRAMES_PER_CALL) -> tuple[Scene, float]:
    """Render, extract and label a batch of sky scenes (one sensor).

    Args:
        keys: (B,) frame keys. sky: (B, M) scenes of the rendered stars; ``truth`` already in the
            identification catalog's rows (−1 where it lacks the star).
        camera, sensor, centroid: the frame size, the sensor and the extractor's settings (its
            ``zero_point`` is set to the sensor's, so magnitudes are V).
        capacity: detections kept per scene (brightest first; more set ``overflow``).
        frames_per_call: frames per render-and-extract call (the last call is padded to it).

    Returns:
        ``(scenes, seconds)``: (B, capacity) detected scenes with their truth labels (the nearest
        star within :data:`MATCH_PX` + the defocus radius + half the smear) and the sky's
        attitudes; the wall time of rendering and extraction.
    """
    centroid = dataclasses.replace(centroid, zero_point=sensor.zero_point())
    # a defocused star is a ring, a smeared one a streak: the extractor may find pieces of it, each
    # as far as the ring's radius or half the streak from the star; they are still that star
    reach = MATCH_PX + sensor.defocus_px + sensor.smear_px / 2
    b = sky.batch_size
    parts = []
    t0 = time.perf_counter()
    for lo in range(0, b, frames_per_call):
        idx = np.arange(lo, min(lo + frames_per_call, b))
        padded = np.pad(idx, (0, frames_per_call - idx.size), mode="edge")  # one compiled size
        part = jax.tree.map(lambda a, padded=padded: a[padded], sky)
        frames = render(keys[padded], part, camera, sensor)
        found = extract_centroids(frames, centroid, capacity=capacity, shard=True)
        truth = label_detections(found.xy, found.valid, part.xy, part.valid, part.truth, reach)
        scene = Scene(xy=found.xy, mag=found.mag, truth=truth, valid=found.valid,
                      attitude=part.attitude, overflow=found.overflow)
        parts.append(jax.tree.map(lambda a, n=idx.size: np.asarray(a)[:n], scene))
    out = jax.tree.map(lambda *a: np.concatenate(a), *parts)
    return jax.tree.map(jnp.asarray, out), time.perf_counter() - t0
