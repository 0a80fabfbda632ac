"""RpNet training data, drawn on the fly from a PRNG key (§II-C); nothing is stored on disk.

A batch of B samples: B guide stars drawn uniformly from the guide catalog, one simulated scene each
(:func:`jstarid.simulate` mode (b): boresight on the guide, random roll). The paper's four noise
families take fixed quarters of the batch (sample i has family i mod 4, level index j = i // 4), so
every batch of a size has the same layout and the simulator compiles once:

* 0, position: σ = 0.2, 0.4, …, 1.6 px on every detection (§II-C.1);
* 1, magnitude: σ ∈ {0.323, 0.484, 0.646, 0.807, 0.969} mag before the V 6.0 limit, from the V 7.0
  simulation list (§II-C.2; needs a catalog loaded with ``sim_margin = 1``);
* 2, missing: 1–5 detected true stars removed (§II-C.3);
* 3, false: 1–5 false stars uniform in the disk of radius f_px·tan ρ about the image centre (the
  guide), magnitude uniform 0–6 (§II-C.4).

The guide S is noise-free as in the paper: the guide vector is the boresight and S's own detection
(by ``truth``) is left out of the neighbours. Departure: the missing-star family may remove S's own
detection, which then removes one neighbour fewer than asked.

Extension (``Config.sim_by_family``, wide fields): the magnitude family's scenes and the other three
families' scenes come from two samplers, the latter over the stars to the camera's limit only.

Extension (``Config.guide_in_frame``, narrow fields): the guide sits at a uniform random position
of the frame and the neighbours that position puts outside the frame are dropped from the noisy
input, as for a guide anywhere in a real frame; the clean target keeps the whole circle.

Extension (``Config.train_detection``, off by default): every family's scenes are drawn from a
detection model (:class:`jstarid.DetectionModel`: the camera's sensor's, or a fitted one) with
the family's knob on top — position and magnitude σ as the model's floors, the missing and false
stars as they are — from a simulation list as deep as the model detects, without blends
(their cost, in :func:`_batch_drawer`). Each scene keeps its brightest detections, as many as the
paper's scene of the same key holds (the catalog's stars to the camera's limit, the family's knob
applied): the model decides which stars a pattern holds — noisy magnitudes reorder them, stars
near the threshold go missing, fainter ones and false stars take their places — but not how many.
Why: identification reads its patterns from the brightest detections a scene keeps, and a
network trained on every detection of a model that sees far past the catalog reads its
neighbours among fainter stars (docs/design/rpnet.md). The clean target stays the catalog's stars
within the camera's limit.

The clean input (the DAE target) is built once per catalog from catalog vectors: the stars within ρ
of the guide with V ≤ the camera's limit (ρ = 6° < the 7.1° half side of the rpnet2019 field, so
the whole pattern circle is in view at any roll).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.rpnet.config import Config
from jstarid.algorithms.rpnet.pattern import config_kwargs, initial_input
from jstarid.catalog import FULL_DEPTH, with_simulation_depth
from jstarid.runtime import device_cache
from jstarid.runtime.program_store import stored_jit
from jstarid.simulator import NoiseConfig, scene_sampler

__all__ = ["Batch", "Tables", "build_tables", "family_noise", "make_batch", "scene_training_inputs"]

FAMILIES = ("position", "magnitude", "missing", "false")


class Batch(NamedTuple):
    """One training batch.

    Attributes:
        noisy: (B, 2⌊ρ/e⌋) float32 inputs from the noisy scenes.
        clean: (B, 2⌊ρ/e⌋) float32 noise-free inputs of the same guide stars.
        label: (B,) int32 class (index into the guide catalog).
        family: (B,) int32 noise family (index into :data:`FAMILIES`).
    """

    noisy: jax.Array
    clean: jax.Array
    label: jax.Array
    family: jax.Array


@dataclasses.dataclass(frozen=True, eq=False)
class Tables:
    """Per-guide tables for the data generator.

    Attributes:
        guide_rows: (K,) int32 catalog row of each class.
        clean: (K, 2⌊ρ/e⌋) float32 clean inputs (device array).
    """

    guide_rows: np.ndarray
    clean: jax.Array


def build_tables(catalog, camera, config: Config, guide_rows) -> Tables:
    """Clean inputs of every guide star from catalog vectors (see the module docstring).

    Args:
        catalog: :class:`~jstarid.catalog.Catalog`.
        camera: :class:`~jstarid.camera.Camera`; its ``mag_limit`` decides which neighbours are seen.
        config: :class:`Config` (ρ, m, e).
        guide_rows: (K,) catalog rows of the guides.
    """
    from scipy.spatial import cKDTree

    guide_rows = np.asarray(guide_rows, np.int32)
    vec = np.asarray(catalog.unit_vectors, np.float64)
    seen = np.nonzero(np.asarray(catalog.mag) <= camera.mag_limit + 1e-6)[0]
    n_query = int(min(len(seen), 4 * config.m + 8))  # the m nearest visible stars, with room for S
    _, nbr = cKDTree(vec[seen]).query(vec[guide_rows], k=n_query)
    nbr = seen[np.asarray(nbr).reshape(len(guide_rows), n_query)]
    mask = nbr != guide_rows[:, None]
    kw = config_kwargs(config)
    fn = jax.jit(jax.vmap(functools.partial(initial_input, **kw)))
    clean = fn(jnp.asarray(vec[guide_rows], jnp.float32), jnp.asarray(vec[nbr], jnp.float32),
               jnp.asarray(mask))
    return Tables(guide_rows=guide_rows, clean=clean)


def family_noise(batch_size: int, camera, config: Config) -> tuple[NoiseConfig, np.ndarray]:
    """The fixed noise layout of a batch (module docstring): per-sample NoiseConfig and family codes."""
    t = config.training
    i = np.arange(batch_size)
    fam, j = i % 4, i // 4
    pos = np.where(fam == 0, np.asarray(t.position_sigmas_px)[j % len(t.position_sigmas_px)], 0.0)
    mag = np.where(fam == 1, np.asarray(t.magnitude_sigmas)[j % len(t.magnitude_sigmas)], 0.0)
    miss = np.where(fam == 2, 1 + j % t.max_missing, 0)
    false = np.where(fam == 3, 1 + j % t.max_false, 0)
    noise = NoiseConfig(
        position_sigma_px=pos.astype(np.float32), magnitude_sigma=mag.astype(np.float32),
        n_missing=miss.astype(np.int32), n_false=false.astype(np.int32),
        false_mag_min=float(t.false_mag_range[0]), false_mag_max=float(t.false_mag_range[1]),
        false_radius_px=float(camera.f_px * math.tan(math.radians(config.rho_deg))))
    return noise, fam.astype(np.int32)


@functools.partial(stored_jit, static_argnames=("camera", "rho_rad", "e_rad", "m", "n_bins"))
def scene_training_inputs(xy, valid, truth, guide_row, shift=None, *, camera, rho_rad, e_rad, m, n_bins):
    """Inputs of mode-(b) scenes: guide at the principal point, its own detection left out.

    Args:
        xy: (B, N, 2) centroids (px); valid: (B, N) bool; truth: (B, N) int32 catalog rows.
        guide_row: (B,) int32 catalog row on the boresight of each scene.
        shift: optional (B, 2) px: where the guide sits in the frame, minus the principal point
            (``Config.guide_in_frame``); neighbours that the shift moves out of the frame are
            dropped. The shift is a translation in pixels, not a rotation of the camera: on the
            narrow fields it serves, the two put the frame's edge within a fraction of a pixel of
            each other near the guide.

    Returns:
        (B, 2·n_bins) float32 inputs.
    """
    vec = camera.unproject(xy)
    guide = camera.unproject(jnp.array([camera.cx, camera.cy], jnp.float32))  # the boresight (0, 0, 1)
    mask = valid & (truth != guide_row[:, None])
    if shift is not None:
        mask = mask & camera.contains(xy + shift[:, None, :])
    fn = functools.partial(initial_input, rho_rad=rho_rad, e_rad=e_rad, m=m, n_bins=n_bins)
    return jax.vmap(fn, in_axes=(None, 0, 0))(guide, vec, mask)


def make_batch(key, catalog, camera, config: Config, tables: Tables, batch_size: int) -> Batch:
    """Draw one batch: random guide stars, random roll, the four noise families (module docstring); a pure
    function of ``key`` and the settings.

    Args:
        key: PRNG key.
        catalog: the catalog the guide rows refer to (with a V 7.0 simulation list).
        camera: :class:`~jstarid.camera.Camera`.
        config: :class:`Config`.
        tables: :func:`build_tables` output for this catalog, camera and config.
        batch_size: B, a multiple of 4.

    Returns:
        :class:`Batch`.
    """
    if batch_size % 4:
        raise ValueError(f"batch_size must be a multiple of 4, got {batch_size}")
    drawers = device_cache.cached(tables, "rpnet_batch_drawers", dict)  # kept while the tables live
    setting = (catalog.fingerprint, camera, config, int(batch_size))
    if setting not in drawers:
        drawers[setting] = _batch_drawer(catalog, camera, config, tables, int(batch_size))
    draw, arrays = drawers[setting]
    return draw(arrays, key)


def _batch_drawer(catalog, camera, config: Config, tables: Tables, batch_size: int):
    """``(draw, arrays)``: ``draw(arrays, key)`` is the whole batch as one compiled call (labels,
    scenes, inputs), so a training loop dispatches one call per step and never waits on the host;
    the tables travel as arguments, not as constants folded into the program."""
    noise, fam = family_noise(batch_size, camera, config)
    capacity = config.training.sim_capacity
    detection = config.training_detection(camera)
    deep, quiet = catalog, contextlib.nullcontext()
    if detection is not None:
        # Blends are left out: their x-order merge over a deep sky costs ≈ 10× the rest of a draw
        # (tetra3_test: 105 against 10 ms per 256 scenes), and a 4 px radius blends ≈ 2 of the
        # ≈ 250 stars of such a frame. The model detects past the catalog's limit: a deeper list.
        # A scene keeps as many detections as the paper's scene of the same key (module docstring).
        detection = detection.replace(merge_radius_px=0.0)
        depth = detection.simulation_depth(float(np.max(config.training.magnitude_sigmas)))
        if math.isfinite(depth):  # (the ideal model cuts at the camera's limit)
            deep = with_simulation_depth(catalog, depth)
        if FULL_DEPTH < depth < math.inf:
            # the widest magnitude family scatters stars up from past Hipparcos's depth; those are
            # missing, as stars past V 7.0 are from the paper's own list (§II-C.2): said here, once
            quiet = warnings.catch_warnings()
            warnings.filterwarnings("ignore", message="the detection model still detects")
    if config.sim_by_family:
        # the magnitude family needs the stars past the limit; the others only those within it
        # (the simulator's list stops at the limit where σ_m = 0)
        parts = [np.nonzero(fam == 1)[0], np.nonzero(fam != 1)[0]]
        order = np.argsort(np.concatenate(parts), kind="stable")  # back to the batch's layout
    else:
        parts, order = [np.arange(batch_size)], None
    with quiet:
        samplers = [scene_sampler(deep, camera, _noise_subset(noise, idx), batch_size=len(idx),
                                     capacity=capacity, mode_b=True, detection=detection) for idx in parts]
    # under a model, the paper's scene of the same key counts the detections a scene keeps
    counters = [] if detection is None else [
        scene_sampler(catalog, camera, _noise_subset(noise, idx), batch_size=len(idx),
                         capacity=capacity, mode_b=True) for idx in parts]
    arrays = (tuple(s.arrays for s in samplers), tuple(c.arrays for c in counters),
              jnp.asarray(tables.guide_rows, jnp.int32), tables.clean, jnp.asarray(fam))
    size = jnp.array([[camera.width, camera.height]], jnp.float32)
    centre = jnp.array([[camera.cx, camera.cy]], jnp.float32)
    kw = config_kwargs(config)

    def draw_part(i, sim_arrays, count_arrays, key, rows):
        scenes = samplers[i].draw(sim_arrays[i], key, rows)
        valid = scenes.valid
        if counters:  # the brightest detections (scenes keep them first), as many as the paper's
            count = jnp.sum(counters[i].draw(count_arrays[i], key, rows).valid, axis=1)
            valid = valid & (jnp.arange(valid.shape[1])[None, :] < count[:, None])
        return scenes.xy, valid, scenes.truth

    @jax.jit
    def draw(arrays, key):
        sim_arrays, count_arrays, guide_rows, clean, family = arrays
        k_label, k_sim = jax.random.split(key)
        label = jax.random.randint(k_label, (batch_size,), 0, guide_rows.shape[0], dtype=jnp.int32)
        rows = guide_rows[label]
        if order is None:
            xy, valid, truth = draw_part(0, sim_arrays, count_arrays, k_sim, rows)
        else:
            drawn = [draw_part(i, sim_arrays, count_arrays, jax.random.fold_in(k_sim, i), rows[idx])
                     for i, idx in enumerate(parts)]
            xy, valid, truth = (jnp.concatenate(f)[order] for f in zip(*drawn, strict=True))
        shift = None
        if config.guide_in_frame:  # the guide anywhere in the frame: a uniform pixel position
            where = jax.random.uniform(jax.random.fold_in(key, 2), (batch_size, 2), maxval=size)
            shift = where - centre
        noisy = scene_training_inputs(xy, valid, truth, rows, shift, camera=camera, **kw)
        return Batch(noisy=noisy, clean=clean[label], label=label, family=family)

    return draw, arrays


def _noise_subset(noise: NoiseConfig, idx) -> NoiseConfig:
    """The per-sample settings of ``noise`` at the batch positions ``idx`` (scalars kept)."""
    if len(idx) == np.size(noise.position_sigma_px):
        return noise
    return NoiseConfig(**{f.name: (np.asarray(v)[idx] if np.ndim(v) == 1 else v)
                             for f in dataclasses.fields(noise) for v in [getattr(noise, f.name)]})
