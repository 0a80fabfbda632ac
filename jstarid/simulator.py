"""Batched star-tracker scene simulation with the four noise models of conventions §3.

``simulate`` is a host wrapper (validation, static sizes, the sky index) around one jit-compiled pure
function of the PRNG key, written per scene and batched with ``vmap``. Every noise level is a
per-scene array, so a sweep over σ (or any mix of settings) is one call with (B,) ``NoiseConfig``
fields.

Per scene:
1. attitude: uniform over SO(3) (mode a), or boresight on a catalog star with uniform roll (mode b);
2. the K simulation stars of the boresight's sky-index cell are rotated into the camera frame and
   projected (pinhole);
3. magnitude noise (Gaussian σ_m) is added to V *before* the detection limit, using the deeper
   simulation list, so dim stars can appear and stars near the limit vanish; under a
   :class:`~jstarid.DetectionModel` (``detection=``) the sensor's photometry decides instead: flux
   noise, a detection threshold, blends and each star's position σ (:func:`jstarid.detection_model.observe`);
4. a star is in the field when its true position is (conventions §1); position noise (Gaussian σ px
   per axis) is added to the kept detections' centroids, so a centroid near the border may fall just
   outside ``[0, W−1] × [0, H−1]``, as in the papers' simulations;
5. missing stars: k of the detected true stars, chosen uniformly, are removed;
6. false stars (clutter): ``n_false`` (or a count uniform in ``[n_false, n_false_max]``), plus a
   Poisson count of mean ``false_mean``, plus ``round(p N_t / (1 − p))`` for a ratio p (RpNet eq. 12,
   N_t the true stars left), plus ``round(r N_t)`` for ``false_per_true`` r; uniform over the frame or
   over the part inside it of a disk of radius ``false_radius_px`` about the principal point;
   magnitude in ``[false_mag_min, false_mag_max]`` with density ∝ 10^(``false_mag_slope`` · m) (0:
   uniform, the papers'; :data:`CATALOG_MAG_SLOPE`: star-like, as the catalog's counts grow); no
   position noise (their position is random anyway);
7. detections are ordered by observed magnitude and the brightest ``capacity`` kept; ``overflow``
   says more were present (or false stars exceeded their buffer). Scenes do not depend on how a
   large batch is chunked.

Randomness: step 1 uses ``jax.random`` on the scene key; steps 2–7 draw from Threefry-2x32 written
out in ``jnp`` on a per-scene seed, one counter stream per kind of draw, so the draws fuse into
vectorised loops on CPU and candidate i's draws do not depend on the list width.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid import random_streams as streams
from jstarid.attitude import random_rotation, rotation_from_boresight
from jstarid.detection_model import DetectionModel, merge_window, observe
from jstarid.runtime import call_padded, device_cache, map_batch, map_by_width, on_every_device
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Scene
from jstarid.sky_index import build_sky_index, cell_of

__all__ = ["CATALOG_MAG_SLOPE", "NoiseConfig", "SceneSampler", "noise_grid", "scene_sampler", "simulate"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class NoiseConfig:
    """Noise settings (conventions §3). Each field is a scalar or a (B,) array (one value per scene).

    Attributes:
        position_sigma_px: centroid noise σ (px), independent in x and y.
        magnitude_sigma: magnitude noise σ (mag), applied before the detection limit.
        n_missing: true stars removed at random per scene.
        n_false: false stars added per scene.
        false_ratio: extra false stars as a ratio p = N_f / (N_t + N_f) ∈ [0, 1) (RpNet eq. 12).
        false_mag_min: brightest false-star magnitude (mag).
        false_mag_max: faintest false-star magnitude (mag).
        false_radius_px: false stars within this radius (px) of the principal point; ``inf`` = whole
            frame.
        n_false_max: when above ``n_false``, the fixed count becomes uniform in ``[n_false,
            n_false_max]`` per scene (clutter that varies from frame to frame).
        false_mean: mean of a Poisson number of false stars added per scene (hot pixels, cosmic
            rays).
        false_per_true: extra false stars as a multiple r of the true stars, ``round(r N_t)``
            (a false-to-true ratio of 0–10 where ``false_ratio`` stops below 1).
        false_mag_slope: false-star magnitudes have density ∝ 10^(slope · m) on ``[false_mag_min,
            false_mag_max]`` (1/mag); 0 is uniform (the papers'), :data:`CATALOG_MAG_SLOPE` draws
            them as the catalog's stars are distributed, so "the brightest" are not a defence.
        false_mag_knee: brighter than this magnitude the density has ``false_mag_slope``, fainter
            ``false_mag_slope_faint`` (continuous at the knee): a real extractor's noise peaks pile
            up just above its threshold under a sparse bright tail. ``inf`` (default): one slope.
        false_mag_slope_faint: the density's slope fainter than ``false_mag_knee`` (1/mag).
    """

    position_sigma_px: float = 0.0
    magnitude_sigma: float = 0.0
    n_missing: int = 0
    n_false: int = 0
    false_ratio: float = 0.0
    false_mag_min: float = 3.5
    false_mag_max: float = 5.5
    false_radius_px: float = math.inf
    n_false_max: int = 0
    false_mean: float = 0.0
    false_per_true: float = 0.0
    false_mag_slope: float = 0.0
    false_mag_knee: float = math.inf
    false_mag_slope_faint: float = 0.0

    def broadcast(self, batch_size: int) -> NoiseConfig:
        """Every field as a (B,) array with the simulator's dtypes."""
        def cast(name, value):
            dtype = jnp.int32 if name in _INTEGER_FIELDS else jnp.float32
            arr = jnp.asarray(value, dtype)
            if arr.ndim > 1 or (arr.ndim == 1 and arr.shape[0] not in (1, batch_size)):
                raise ValueError(f"NoiseConfig.{name} must be a scalar or have shape ({batch_size},), "
                                 f"got {arr.shape}")
            return jnp.broadcast_to(arr, (batch_size,))
        return NoiseConfig(**{f.name: cast(f.name, getattr(self, f.name))
                              for f in dataclasses.fields(self)})

    def validate(self) -> None:
        """Raise ``ValueError`` on out-of-range settings (host-side; values must be concrete)."""
        def arr(name):
            try:
                return np.asarray(getattr(self, name), dtype=np.float64)
            except (TypeError, jax.errors.TracerArrayConversionError) as err:
                raise ValueError(f"NoiseConfig.{name} must be concrete for validation") from err

        checks = {
            "position_sigma_px": lambda a: np.all((a >= 0) & (a <= 1000)),
            "magnitude_sigma": lambda a: np.all((a >= 0) & (a <= 10)),
            "n_missing": lambda a: np.all((a >= 0) & (a <= 10_000) & (a == np.round(a))),
            "n_false": lambda a: np.all((a >= 0) & (a <= 10_000) & (a == np.round(a))),
            "false_ratio": lambda a: np.all((a >= 0) & (a < 1)),
            "false_mag_min": lambda a: np.all(np.isfinite(a)),
            "false_mag_max": lambda a: np.all(np.isfinite(a)),
            "false_radius_px": lambda a: np.all(a > 0),
            "n_false_max": lambda a: np.all((a >= 0) & (a <= 10_000) & (a == np.round(a))),
            "false_mean": lambda a: np.all((a >= 0) & (a <= 1_000)),
            "false_per_true": lambda a: np.all((a >= 0) & (a <= 100)),
            "false_mag_slope": lambda a: np.all(np.abs(a) <= 5),
            "false_mag_knee": lambda a: np.all(a > -100),
            "false_mag_slope_faint": lambda a: np.all(np.abs(a) <= 5),
        }
        rules = {
            "position_sigma_px": "in [0, 1000] px", "magnitude_sigma": "in [0, 10] mag",
            "n_missing": "an integer in [0, 10000]", "n_false": "an integer in [0, 10000]",
            "false_ratio": "in [0, 1)", "false_mag_min": "finite", "false_mag_max": "finite",
            "false_radius_px": "> 0 (inf for the whole frame)",
            "n_false_max": "an integer in [0, 10000]", "false_mean": "in [0, 1000]",
            "false_per_true": "in [0, 100]", "false_mag_slope": "in [-5, 5] per mag",
            "false_mag_knee": "a magnitude (inf: no knee)", "false_mag_slope_faint": "in [-5, 5] per mag",
        }
        for name, ok in checks.items():
            a = arr(name)
            if np.any(np.isnan(a)) or not ok(a):
                raise ValueError(f"NoiseConfig.{name} must be {rules[name]}, got {getattr(self, name)}")
        if np.any(arr("false_mag_min") > arr("false_mag_max")):
            raise ValueError("NoiseConfig.false_mag_min must be ≤ false_mag_max")


def noise_grid(repeats: int, **levels) -> NoiseConfig:
    """A :class:`NoiseConfig` whose fields sweep levels, each level repeated ``repeats`` times:
    ``noise_grid(1000, position_sigma_px=[0, 0.5, 1])`` gives B = 3000 scenes, the first 1000 at σ = 0.
    Several swept fields form the Cartesian product (first field slowest); others keep their defaults or
    may be given as scalars.
    """
    swept = {k: np.atleast_1d(np.asarray(v)) for k, v in levels.items() if np.ndim(v) > 0}
    fixed = {k: v for k, v in levels.items() if np.ndim(v) == 0}
    if not swept:
        return NoiseConfig(**fixed)
    mesh = np.meshgrid(*swept.values(), indexing="ij")
    cols = {k: np.repeat(m.reshape(-1), repeats) for k, m in zip(swept, mesh, strict=True)}
    return NoiseConfig(**fixed, **cols)


# log10 N(≤ V) of Hipparcos grows 0.47 per magnitude between V 4 and 8 (529 → 41,604 stars):
# false stars drawn with this slope are as bright, relative to each other, as the stars.
CATALOG_MAG_SLOPE = 0.47

_INTEGER_FIELDS = ("n_missing", "n_false", "n_false_max")


def _false_capacity(noise: NoiseConfig, capacity: int) -> int:
    def top(name):
        return float(np.max(np.asarray(getattr(noise, name))))
    n_false = int(max(top("n_false"), top("n_false_max")))
    mean = top("false_mean")
    # A Poisson count above mean + 6√mean + 8 has odds below 1e-9; past it the scene flags overflow.
    poisson = 0 if mean <= 0 else int(math.ceil(mean + 6.0 * math.sqrt(mean) + 8.0))
    # With a ratio, false stars beyond `capacity` could never all be kept anyway: bound the buffer and
    # flag overflow when a scene asks for more.
    extra = 0 if top("false_ratio") <= 0 and top("false_per_true") <= 0 else capacity
    return int(n_false + poisson + extra)


def check_key(key) -> None:
    """Refuse anything but one PRNG key: a typed ``jax.random.key`` or a legacy (2,) uint32 key.

    Raises:
        ValueError: e.g. an integer seed, a float array or a batch of keys.
    """
    dtype = getattr(key, "dtype", None)
    if dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key):
        if np.shape(key) == ():
            return
    elif dtype is not None and np.dtype(dtype) == np.uint32 and np.shape(key) == (2,):
        return
    what = " ".join(str(x) for x in (type(key).__name__, getattr(key, "dtype", ""), np.shape(key)) if x != "")
    raise ValueError(f"key must be one PRNG key (jax.random.key(seed)), got {what}")


def simulate(key, catalog, camera, noise: NoiseConfig | None = None, *, batch_size: int | None = None,
             capacity: int = 64, boresight_ids=None, shard: bool = False,
             detection: DetectionModel | None = None, attitudes=None) -> Scene:
    """Simulate a batch of scenes (conventions §3). A pure function of ``key`` and the settings.

    Args:
        key: PRNG key (``jax.random.key`` or a legacy uint32 key).
        catalog: :class:`~jstarid.catalog.Catalog`; truth labels are its rows.
        camera: :class:`~jstarid.camera.Camera`; its ``mag_limit`` is the detection limit.
        noise: :class:`NoiseConfig` (default: noise-free); fields may be (B,) arrays.
        batch_size: B for random attitudes (mode a). Omit with ``boresight_ids``.
        capacity: static N, detections kept per scene (brightest first).
        boresight_ids: (B,) catalog rows; scene i has its boresight on that star and a random roll
            (mode b).
        shard: split the batch over every device (:func:`jstarid.runtime.map_batch`); the scenes
            are identical to the single-device call.
        detection: a :class:`~jstarid.DetectionModel` (fields scalars or (B,) arrays): photometric
            noise, completeness, bias and blends by magnitude, with ``noise``'s position and magnitude
            σ as its floors. ``None`` (or :meth:`~jstarid.DetectionModel.ideal`): the papers' hard cut
            at the camera's limit.
        attitudes: (B, 3, 3) rotations ICRS → camera, the scenes' attitudes as given (mode c: a real
            set's pointings); the key then draws everything but the attitude.

    Returns:
        A :class:`~jstarid.scene.Scene` of B scenes. Scene i depends on ``key``, i and the settings
        only, not on B: a batch below 2,048 scenes is drawn at the next power of two (at least 16)
        and cut, so one program serves every size of a bucket.

    Raises:
        ValueError: inconsistent batch settings, a bad capacity, out-of-range noise or rows, or a
            key that is not a PRNG key.
    """
    noise = _checked(noise, capacity)
    detection = _checked_model(detection)
    if attitudes is not None:
        given = np.asarray(attitudes, np.float64)
        if boresight_ids is not None or given.ndim != 3 or given.shape[1:] != (3, 3):
            raise ValueError("attitudes must be (B, 3, 3) rotations, without boresight_ids")
        if not np.all(np.isfinite(given)) or not np.allclose(
                np.einsum("bij,bkj->bik", given, given), np.eye(3), atol=1e-4):
            raise ValueError("attitudes must be finite rotation matrices")
        if batch_size is not None and batch_size != given.shape[0]:
            raise ValueError("batch_size disagrees with len(attitudes)")
        batch_size = given.shape[0]
    if boresight_ids is not None:
        rows = np.asarray(boresight_ids)
        if rows.ndim != 1 or not np.issubdtype(rows.dtype, np.integer):
            raise ValueError("boresight_ids must be a 1-D integer array of catalog rows")
        if rows.size and (rows.min() < 0 or rows.max() >= len(catalog)):
            raise ValueError(f"boresight_ids must be catalog rows in [0, {len(catalog)})")
        if batch_size is not None and batch_size != rows.shape[0]:
            raise ValueError("batch_size disagrees with len(boresight_ids)")
        batch_size = rows.shape[0]
    elif batch_size is None:
        raise ValueError("give batch_size (random attitudes), boresight_ids (mode b) or attitudes")
    if not isinstance(batch_size, int | np.integer) or batch_size < 1:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
    check_key(key)
    plan = _plan(catalog, camera, noise, batch_size=int(batch_size), capacity=int(capacity),
                 mode_b=boresight_ids is not None, detection=detection)
    rows = (jnp.zeros((batch_size,), jnp.int32) if boresight_ids is None
            else jnp.asarray(boresight_ids, jnp.int32))
    sharded = shard and jax.local_device_count() > 1
    if attitudes is not None:  # mode c: stage 1 is the given attitudes and their sky cells
        first = _given_attitudes(_scene_keys(key, batch_size), jnp.asarray(attitudes, jnp.float32),
                                 grid=plan.stage1["grid"])
        if not sharded:
            noise_b, model_b, index_arrays, star_tables, _ = plan.arrays
            return call_padded(_stage2, (*first, noise_b, model_b), *index_arrays, *star_tables,
                               **_BUCKETS, **plan.statics)
    elif not sharded:
        noise_b, model_b, index_arrays, star_tables, cat_vec = plan.arrays
        return call_padded(_draw_keys, (_scene_keys(key, batch_size), rows, noise_b, model_b),
                           index_arrays, star_tables, cat_vec, stage1=plan.stage1, statics=plan.statics,
                           **_BUCKETS)
    # both stages split over the devices, the tables placed on each device once (they are
    # long-lived: the index is memoised, the tables kept on the catalog)
    tables = _device_tables(catalog)
    replicated = (*on_every_device(plan.index, "device_arrays", plan.index.device_arrays),
                  *on_every_device(catalog, "simulator_stars", lambda: tables[:3]))
    if attitudes is None:
        cat_vec = on_every_device(catalog, "simulator_catalog", lambda: tables[3])
        first = map_batch(_attitudes_of, (_scene_keys(key, batch_size), rows), (cat_vec,),
                          static=plan.stage1)
    return map_batch(_stage2, (*first, *plan.arrays[:2]), replicated, static=plan.statics)


class SceneSampler(NamedTuple):
    """:func:`simulate` for one setting, its host-side work done (:func:`scene_sampler`).

    Attributes:
        arrays: the device arrays a draw reads (broadcast noise, sky index, star tables): a pytree.
        draw: ``draw(arrays, key, rows) -> Scene``, pure and traceable; pass ``arrays`` as an
            argument of an enclosing ``jax.jit`` rather than closing over them (they are large).
    """

    arrays: tuple
    draw: Callable

    def __call__(self, key, rows=None) -> Scene:
        """``draw(arrays, key, rows)``."""
        return self.draw(self.arrays, key, rows)


def scene_sampler(catalog, camera, noise: NoiseConfig | None = None, *, batch_size: int,
                  capacity: int = 64, mode_b: bool = False,
                  detection: DetectionModel | None = None) -> SceneSampler:
    """The host-side work of :func:`simulate` done once, for a loop that draws many batches.

    ``sampler(key, rows)`` returns the batch that
    ``simulate(key, catalog, camera, noise, capacity=capacity, boresight_ids=rows)``
    (``mode_b``) or ``simulate(key, …, batch_size=batch_size)`` (``rows`` ignored) returns;
    ``sampler.draw(sampler.arrays, key, rows)`` is the same as a pure function, to be traced inside
    a caller's ``jax.jit`` (a training step drawing its own batch: no host round trip, no
    per-call validation).

    Args:
        catalog, camera, noise, capacity: as for :func:`simulate`.
        batch_size: B, the batch every draw makes.
        mode_b: each draw takes (B,) int32 catalog rows for the boresights (their range is not
            checked per draw: give rows of ``catalog``); else random attitudes.

    Returns:
        :class:`SceneSampler`.

    Raises:
        ValueError: as :func:`simulate` for bad settings.
    """
    noise = _checked(noise, capacity)
    detection = _checked_model(detection)
    if not isinstance(batch_size, int | np.integer) or batch_size < 1:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
    plan = _plan(catalog, camera, noise, batch_size=int(batch_size), capacity=int(capacity),
                 mode_b=bool(mode_b), detection=detection)
    return SceneSampler(plan.arrays, functools.partial(_draw, batch_size=int(batch_size),
                                                       stage1=plan.stage1, statics=plan.statics))


def _draw(arrays, key, rows, *, batch_size, stage1, statics):
    noise_b, model_b, index_arrays, star_tables, cat_vec = arrays
    if not stage1["mode_b"]:
        rows = jnp.zeros((batch_size,), jnp.int32)
    elif rows is None or jnp.shape(rows) != (batch_size,):  # shapes are static: checked under jit too
        raise ValueError(f"this sampler puts the boresights on catalog rows: give rows of shape "
                         f"({batch_size},), got {None if rows is None else jnp.shape(rows)}")
    return _draw_keys(jax.random.split(key, batch_size), rows, noise_b, model_b, index_arrays, star_tables,
                      cat_vec, stage1=stage1, statics=statics)


def _draw_keys(keys, rows, noise_b, model_b, index_arrays, star_tables, cat_vec, *, stage1, statics):
    """Both stages of an unsharded call from the B scene keys (B,) and boresight rows (B,)."""
    seeds, att, cell = _attitudes(keys, rows, cat_vec, **stage1)
    return _stage2(seeds, att, cell, noise_b, model_b, *index_arrays, *star_tables, **statics)


def _checked(noise: NoiseConfig | None, capacity) -> NoiseConfig:
    """The noise (default: none), validated, and the capacity checked."""
    noise = NoiseConfig() if noise is None else noise
    noise.validate()
    if not isinstance(capacity, int | np.integer) or capacity < 1:
        raise ValueError(f"capacity must be a positive integer, got {capacity!r}")
    return noise


def _checked_model(detection: DetectionModel | None) -> DetectionModel | None:
    """The detection model validated; ``None`` for none or the ideal one (the same scenes either way,
    and the papers' programs)."""
    if detection is None:
        return None
    if not isinstance(detection, DetectionModel):
        raise ValueError(f"detection must be a DetectionModel, got {type(detection).__name__}")
    detection.validate()
    if all(np.ndim(getattr(detection, f.name)) == 0 for f in dataclasses.fields(detection)) \
            and detection == DetectionModel.ideal():
        return None
    return detection


class _Plan(NamedTuple):
    """What :func:`simulate` decides on the host for a setting: the sky index, compile-time sizes
    and the arrays a draw reads (:class:`SceneSampler`)."""

    index: object
    stage1: dict
    statics: dict
    arrays: tuple


def _plan(catalog, camera, noise: NoiseConfig, *, batch_size: int, capacity: int, mode_b: bool,
          detection: DetectionModel | None = None) -> _Plan:
    sim_limit = catalog.mag_limit + catalog.settings["sim_margin"]
    max_msig = float(np.max(np.asarray(noise.magnitude_sigma)))
    ideal = detection is None or bool(np.any(np.isinf(np.asarray(detection.zero_point_e))))
    if ideal and camera.mag_limit > sim_limit + 1e-6:
        warnings.warn(f"camera limit V {camera.mag_limit} is deeper than the catalog's simulation "
                      f"list (V ≤ {sim_limit}); stars in between are missing from the scenes",
                      stacklevel=3)
    limit = camera.mag_limit if ideal else -math.inf
    if detection is not None and not np.all(np.isinf(np.asarray(detection.zero_point_e))):
        seen = detection.faintest_detectable(max_msig, odds=1e-3)
        if seen > sim_limit + 1e-6:
            # past V 30 the model's noise alone clears its threshold (a fit to few electrons)
            where = (f"at V {seen:.1f}" if seen < 30.0
                     else "at any depth (its noise alone clears the threshold)")
            warnings.warn(f"the detection model still detects 0.1 % of the stars {where}, "
                          f"deeper than the catalog's simulation list (V ≤ {sim_limit}): the fainter "
                          f"stars are missing from the scenes (load_catalog(sim_margin=…) reaches "
                          f"deeper)", stacklevel=3)
        limit = max(limit, math.ceil(10.0 * min(detection.faintest_detectable(), sim_limit)) / 10.0)

    margin = math.atan(1.0 / camera.f_px)  # a pixel of slack against rounding at the border
    # Stars fainter than the limit by more than 5.5 σ_m (detection odds < 2e-8) are left out of the
    # per-cell lists; the cut is rounded up to 0.1 mag so nearby σ share one index and compilation.
    # Under a detection model the limit is where its odds fall below 1e-9.
    faint_cut = limit + math.ceil(55.0 * max_msig) / 10.0
    subset = np.nonzero(catalog.sim_mag <= faint_cut)[0]
    index = build_sky_index(catalog.sim_unit_vectors, camera.half_diagonal_rad, margin_rad=margin,
                            subset=subset, key=f"{catalog.fingerprint}-sim-{faint_cut:.1f}")
    tables = _device_tables(catalog)
    statics = dict(
        camera=camera, capacity=capacity,
        false_capacity=_false_capacity(noise, capacity),
        max_missing=int(np.max(np.asarray(noise.n_missing))),
        false_disk=bool(np.any(np.isfinite(np.asarray(noise.false_radius_px)))),
        n_candidates=index.capacity,
        merge=(0 if detection is None or not np.any(np.asarray(detection.merge_radius_px) > 0) else
               merge_window(index.capacity, float(np.max(detection.merge_radius_px)), camera.width)),
    )
    model_b = None if detection is None else detection.broadcast(batch_size)
    arrays = (noise.broadcast(batch_size), model_b, tuple(index.device_arrays()), tuple(tables[:3]),
              tables[3])
    return _Plan(index, dict(grid=index.grid, mode_b=mode_b), statics, arrays)


def _stage2(seeds, att, cell, noise_b, model_b, cells, counts, star_vec, star_mag, star_row, *,
            n_candidates, **statics):
    """Steps 2–7 for a batch: one vmapped call for small batches, sorted chunks for large ones."""
    if seeds.shape[0] < _CHUNK_MIN_BATCH:
        return _scenes_batch(seeds, noise_b, model_b, att, cell, cells, star_vec, star_mag, star_row,
                             n_candidates=n_candidates, **statics)
    return _scenes_chunked(seeds, noise_b, model_b, att, cell, cells, counts, star_vec, star_mag,
                           star_row, widths=_candidate_widths(n_candidates), **statics)


# Large batches are sorted by how many candidate stars their sky cell holds and processed in chunks
# whose candidate-list width fits the chunk, so a scene in a sparse region does not pay for the
# densest cell's list length. One compilation serves every batch of the same size.
_CHUNK_MIN_BATCH = 2048
# An unsharded call below the chunked path's size runs at the next power of two ≥ 16 scenes
# (runtime.call_padded): a program per batch size compiled the simulator anew for every size a
# sweep, a notebook or the algorithms' retries meet (4, 6, 12, 200 scenes …). Each scene is drawn
# from its own key, independently of the others, so the padding scenes (copies of the last) change
# no scene; the scene keys are split at the batch's own size (every prefix of a split holds the same
# keys), so a scene does not depend on the batch it is drawn in.
_BUCKETS = dict(limit=_CHUNK_MIN_BATCH, mode="edge")
_CHUNK = 256
_WIDTH_STEP = 64  # candidate-list widths are multiples of this


def _candidate_widths(k: int) -> tuple[int, ...]:
    """List widths up to the index capacity k: every multiple of ``_WIDTH_STEP``, then k (a chunk's work
    grows with the width it reads, so fine steps pay for their extra compilations).
    """
    widths = list(range(_WIDTH_STEP, k + 1, _WIDTH_STEP))
    return tuple(widths if widths and widths[-1] == k else [*widths, k])


@functools.partial(stored_jit, static_argnames=(
    "camera", "capacity", "false_capacity", "max_missing", "false_disk", "merge", "widths"))
def _scenes_chunked(seeds, noise, model, att, cell, cells, counts, star_vec, star_mag, star_row, *,
                    camera, capacity, false_capacity, max_missing, false_disk, merge=0, widths):
    """Steps 2–7 for a large batch, in chunks sorted by candidate count, each with the narrowest
    candidate list that holds it (:func:`jstarid.runtime.map_by_width`)."""
    def run(width):
        def fn(args):
            k, nz, md, a, c = args
            return _scenes_batch(
                k, nz, md, a, c, cells, star_vec, star_mag, star_row, camera=camera, capacity=capacity,
                false_capacity=false_capacity, max_missing=max_missing, false_disk=false_disk,
                merge=merge, n_candidates=width, adaptive=True)
        return fn

    return map_by_width(run, (seeds, noise, model, att, cell), counts[cell], widths, _CHUNK)


def _device_tables(catalog):
    """Simulation-star tables with one sentinel row appended (index M: never detected).

    Returns ``(vec_T (3, M+1), mag (M+1,), row (M+1,), catalog unit vectors (N, 3))``; the vectors are
    stored component-major so the hot loop gathers three contiguous 1-D tables.
    """
    def make():
        vec = np.concatenate([catalog.sim_unit_vectors, [[0.0, 0.0, 1.0]]]).astype(np.float32)
        mag = np.concatenate([catalog.sim_mag, [np.inf]]).astype(np.float32)
        row = np.concatenate([catalog.sim_row, [-1]]).astype(np.int32)
        return (jnp.asarray(vec.T.copy()), jnp.asarray(mag), jnp.asarray(row),
                jnp.asarray(catalog.unit_vectors, jnp.float32))

    return device_cache.cached(catalog, "simulator_tables", make)


def _attitude_one(key, row, cat_vec, mode_b):
    """Step 1 for one scene: the attitude (from the scene key's first sub-key)."""
    k_att = jax.random.split(key, 6)[0]
    if mode_b:
        roll = jax.random.uniform(k_att, (), minval=-jnp.pi, maxval=jnp.pi)
        return rotation_from_boresight(cat_vec[row], roll)
    return random_rotation(k_att)


@functools.partial(stored_jit, static_argnames=("grid", "mode_b"))
def _attitudes(keys, rows, cat_vec, *, grid, mode_b):
    """Step 1 for a batch from its scene keys (B,): :func:`_attitudes_of`, one stored program."""
    return _attitudes_of(keys, rows, cat_vec, grid=grid, mode_b=mode_b)


@functools.partial(jax.jit, static_argnames=("grid",))
def _given_attitudes(keys, att, *, grid):
    """Stage 1 of mode c: the scene seeds of ``keys``, the given attitudes and their sky cells."""
    return jax.vmap(streams.scene_seed)(keys), att, cell_of(att[:, 2], grid)


@functools.partial(jax.jit, static_argnums=1)
def _scene_keys(key, batch_size):
    """The B scene keys of a batch key (the sharded path splits the batch after this)."""
    return jax.random.split(key, batch_size)


def _attitudes_of(keys, rows, cat_vec, *, grid, mode_b):
    """Per-scene seeds (B, 2) uint32 (:func:`~jstarid.random_streams.scene_seed`), attitudes (B, 3, 3) and
    sky cells (B,); the seeds are materialised here so that stage 2 reads rather than re-derives them.
    """
    att = jax.vmap(lambda k, r: _attitude_one(k, r, cat_vec, mode_b))(keys, rows)
    return jax.vmap(streams.scene_seed)(keys), att, cell_of(att[:, 2], grid)



@functools.partial(stored_jit, static_argnames=(
    "camera", "capacity", "false_capacity", "max_missing", "false_disk", "merge", "n_candidates",
    "adaptive"))
def _scenes_batch(seeds, noise, model, att, cell, cells, star_vec, star_mag, star_row, *, camera,
                  capacity, false_capacity, max_missing, false_disk, n_candidates, merge=0,
                  adaptive=False):
    """Steps 2–7 for a batch, given attitudes and sky cells; ``cells[:, :n_candidates]`` is used.

    ``adaptive`` (the large-batch chunks, sorted by candidate count): step 7 selects with the smallest k
    of :func:`_keep_sizes` that holds every scene's detections (``lax.switch`` on the batch maximum;
    ``top_k``'s cost grows with k). The scenes are the same for every k (:func:`_brightest`). Small
    batches use k = capacity alone (extra branches would lengthen compilation, their main cost).
    """
    def detections(seed, noise_i, model_i, att_i, cell_i):
        return _detections(seed, noise_i, model_i, att_i, cells[cell_i, :n_candidates],
                           star_vec=star_vec, star_mag=star_mag, star_row=star_row, camera=camera,
                           false_capacity=false_capacity, max_missing=max_missing,
                           false_disk=false_disk, merge=merge)

    det = jax.vmap(detections)(seeds, noise, model, att, cell)

    def keep_brightest(k):
        def one(seed, noise_i, att_i, det_i):
            return _keep_brightest(seed, noise_i, att_i, det_i, _brightest(det_i, k),
                                   capacity=capacity, n_cand=n_candidates)
        return lambda args: jax.vmap(one)(*args)

    k_max = min(capacity, det.mag.shape[1])
    if not adaptive:
        return keep_brightest(k_max)((seeds, noise, att, det))
    sizes = _keep_sizes(k_max)
    branch = jnp.searchsorted(jnp.asarray(sizes), jnp.max(det.n_detected))
    return jax.lax.switch(jnp.minimum(branch, len(sizes) - 1), [keep_brightest(k) for k in sizes],
                          (seeds, noise, att, det))


def _keep_sizes(k_max: int) -> tuple[int, ...]:
    """The k values step 7 compiles for: powers of two from 16 below ``k_max``, then ``k_max`` (a branch
    count logarithmic in the capacity).
    """
    sizes = []
    k = 16
    while k < k_max:
        sizes.append(k)
        k *= 2
    return (*sizes, k_max)


def _simulate_one(key, noise, row, *, cells, star_vec, star_mag, star_row, cat_vec, camera, capacity,
                  grid, false_capacity, max_missing, mode_b, false_disk=True, model=None, merge=0):
    """One whole scene (steps 1–7) with the full candidate list: the per-scene reference."""
    att = _attitude_one(key, row, cat_vec, mode_b)
    return _scene_from_attitude(
        streams.scene_seed(key), noise, att, cells[cell_of(att[2], grid)], star_vec=star_vec,
        star_mag=star_mag, star_row=star_row, camera=camera, capacity=capacity, false_capacity=false_capacity,
        max_missing=max_missing, false_disk=false_disk, model=model, merge=merge)


def _drop_missing(seed, detected, n_missing, max_missing):
    """Step 5: remove ``n_missing`` of the ``detected`` stars, a uniform random subset, drawn without
    replacement (the i-th removal takes the ⌊u_i (N − i)⌋-th remaining detection): one uniform per
    removal, independent of the batch's ``max_missing``.

    Args:
        seed: the scene's Threefry key pair (:func:`~jstarid.random_streams.scene_seed`).
        detected: (K,) bool, detected true stars.
        n_missing: int32 scalar, stars to remove (≤ ``max_missing``).
        max_missing: static bound on ``n_missing`` over the batch.

    Returns:
        (K,) bool, the detections left.
    """
    u = streams.uniforms(seed, streams.MISSING, max_missing)

    def drop(i, det):
        n_left = jnp.sum(det, dtype=jnp.int32)
        j = jnp.minimum((u[i] * n_left.astype(jnp.float32)).astype(jnp.int32), n_left - 1)
        rank = jnp.cumsum(det, dtype=jnp.int32)  # 1-based rank of each detection
        return det & ~((rank == j + 1) & (i < n_missing))

    if max_missing <= 8:  # unrolled: XLA fuses the few steps; a loop for large bounds
        for i in range(max_missing):
            detected = drop(i, detected)
        return detected
    return jax.lax.fori_loop(0, max_missing, drop, detected)


def _scene_from_attitude(seed, noise, att, idx, *, star_vec, star_mag, star_row, camera, capacity,
                         false_capacity, max_missing, false_disk=True, model=None, merge=0):
    """Steps 2–7 for one scene (module docstring); ``noise`` fields are scalars here.

    Args:
        seed: (2,) uint32 Threefry key pair for steps 2–7 (:func:`~jstarid.random_streams.scene_seed`
            of the scene key, whose own draws gave the attitude).
        noise: per-scene :class:`NoiseConfig`.
        att: (3, 3) attitude.
        idx: (K,) candidate simulation-star indices (a prefix of the cell's list, padded with the
            sentinel row); the draws of candidate i do not depend on K.
        false_disk: static; False when no scene has a finite ``false_radius_px`` (disk draws skipped).
        model: the scene's :class:`~jstarid.DetectionModel` or ``None`` (the camera's cut).
        merge: static; the blends' window (:func:`~jstarid.detection_model.merge_window`), 0 when no
            scene blends.
    """
    det = _detections(seed, noise, model, att, idx, star_vec=star_vec, star_mag=star_mag,
                      star_row=star_row, camera=camera, false_capacity=false_capacity,
                      max_missing=max_missing, false_disk=false_disk, merge=merge)
    k_keep = min(capacity, det.mag.shape[0])
    return _keep_brightest(seed, noise, att, det, _brightest(det, k_keep), capacity=capacity,
                           n_cand=idx.shape[0])


class _Detections(NamedTuple):
    """One scene's detections before the brightest are kept (steps 2–6); n = K (+ false buffer).

    Attributes:
        xy: (n, 2) true centroids (px).
        mag: (n,) observed magnitudes.
        detected: (n,) bool.
        truth: (n,) catalog rows, −1 for false stars.
        n_detected: int32 scalar.
        false_overflow: bool scalar, false stars beyond the buffer (or blends beyond their window).
        sigma_px: (n,) position noise σ of each true star (px).
    """

    xy: jax.Array
    mag: jax.Array
    detected: jax.Array
    truth: jax.Array
    n_detected: jax.Array
    false_overflow: jax.Array
    sigma_px: jax.Array


def _detections(seed, noise, model, att, idx, *, star_vec, star_mag, star_row, camera, false_capacity,
                max_missing, false_disk, merge=0):
    """Steps 2–6 for one scene (arguments as :func:`_scene_from_attitude`)."""
    n_cand = idx.shape[0]

    # 2. candidates rotated (v_cam = C r, written out so it fuses) and projected
    rx, ry, rz = star_vec[0, idx], star_vec[1, idx], star_vec[2, idx]
    vx = att[0, 0] * rx + att[0, 1] * ry + att[0, 2] * rz
    vy = att[1, 0] * rx + att[1, 1] * ry + att[1, 2] * rz
    vz = att[2, 0] * rx + att[2, 1] * ry + att[2, 2] * rz
    x, y, in_field = camera.project_components(vx, vy, vz)
    xy = jnp.stack([x, y], -1)

    # 3. magnitude noise before the detection limit; the star is in the field by its true position
    if model is None:
        obs_mag = star_mag[idx] + noise.magnitude_sigma * streams.normals(seed, streams.MAG, n_cand)
        detected = in_field & (obs_mag <= camera.mag_limit) & jnp.isfinite(obs_mag)
        sigma = jnp.broadcast_to(noise.position_sigma_px, (n_cand,))
        blend_overflow = jnp.bool_(False)
    else:  # photometry, completeness and blends by magnitude (jstarid.detection_model)
        obs_mag, detected, sigma, xy, blend_overflow = observe(
            seed, model, noise, star_mag[idx], xy, in_field, camera=camera, merge=merge)

    # 5. missing stars
    if max_missing > 0:
        detected = _drop_missing(seed, detected, noise.n_missing, max_missing)
    truth = star_row[idx]

    # 6. false stars
    n_true = jnp.sum(detected, dtype=jnp.int32)
    if false_capacity > 0:
        n_false = _false_count(seed, noise, n_true, false_capacity)
        f_xy = _false_positions(seed, false_capacity, noise.false_radius_px, camera, disk=false_disk)
        f_mag = _false_magnitudes(streams.uniforms(seed, streams.FALSE_MAG, false_capacity), noise)
        f_on = jnp.arange(false_capacity) < n_false
        false_overflow = n_false > false_capacity
        xy = jnp.concatenate([xy, f_xy])
        obs_mag = jnp.concatenate([obs_mag, f_mag])
        detected = jnp.concatenate([detected, f_on])
        truth = jnp.concatenate([truth, jnp.full((false_capacity,), -1, jnp.int32)])
        sigma = jnp.concatenate([sigma, jnp.zeros((false_capacity,), sigma.dtype)])
    else:
        false_overflow = jnp.bool_(False)

    return _Detections(xy, obs_mag, detected, truth, jnp.sum(detected, dtype=jnp.int32),
                       false_overflow | blend_overflow, sigma)


def _brightest(det, k):
    """Step 7's order: indices (k,) of the k brightest detections, ascending magnitude.

    ``lax.top_k`` breaks ties by the lower index (candidate order); slots past the detections hold
    undetected candidates (masked by the caller). The first k of a larger k' are the same indices.
    """
    _, keep = jax.lax.top_k(-jnp.where(det.detected, det.mag, jnp.inf), k)
    return keep


def _keep_brightest(seed, noise, att, det, keep, *, capacity, n_cand):
    """Step 7 (and 4): the detections at ``keep`` (k,) as a capacity-N :class:`Scene`; ``keep`` may be
    shorter than the capacity (the slots after it are empty).
    """
    k = keep.shape[0]
    valid = det.detected[keep]
    # 4. position noise on the kept true stars only (false stars are placed at random anyway), so the
    #    cost does not grow with the number of candidate stars.
    #    The (k, 2) draws come straight from 2-d counters and the positions from one gather of (x, y)
    #    rows: fused with a stack of separate x and y columns, the draws were recomputed per output
    #    element and not vectorised.
    jitter = det.sigma_px[keep][:, None] * streams.normals(seed, streams.POSITION, (k, 2))
    jitter = jnp.where((keep < n_cand)[:, None], jitter, 0.0)
    out_xy = jnp.where(valid[:, None], det.xy[keep] + jitter, 0.0)
    out_mag = jnp.where(valid, det.mag[keep], jnp.inf)
    out_truth = jnp.where(valid, det.truth[keep], -1)
    if k < capacity:  # fewer candidates (or detections) than capacity: pad
        pad = capacity - k
        out_xy = jnp.pad(out_xy, ((0, pad), (0, 0)))
        out_mag = jnp.pad(out_mag, (0, pad), constant_values=jnp.inf)
        out_truth = jnp.pad(out_truth, (0, pad), constant_values=-1)
        valid = jnp.pad(valid, (0, pad))
    return Scene(xy=out_xy.astype(jnp.float32), mag=out_mag.astype(jnp.float32),
                 truth=out_truth.astype(jnp.int32), valid=valid,
                 attitude=att.astype(jnp.float32),
                 overflow=(det.n_detected > capacity) | det.false_overflow)


def _false_count(seed, noise, n_true, bound):
    """Step 6's count of false stars for one scene (int32 scalar; may exceed ``bound``, the buffer).

    The fixed count (uniform in ``[n_false, n_false_max]`` when the maximum is larger), a Poisson
    count of mean ``false_mean`` drawn by inverting its CDF over ``0 … bound`` on one uniform, and the
    two ratios to the true stars left.
    """
    u_fixed, u_poisson = streams.uniforms(seed, streams.FALSE_COUNT, 2)
    spread = jnp.maximum(noise.n_false_max - noise.n_false, 0)
    fixed = noise.n_false + jnp.minimum(jnp.floor(u_fixed * (spread + 1)).astype(jnp.int32), spread)
    k = jnp.arange(bound + 1, dtype=jnp.float32)
    lam = jnp.maximum(noise.false_mean, 1e-30)
    log_pmf = k * jnp.log(lam) - lam - jax.lax.lgamma(k + 1.0)
    cdf = jnp.cumsum(jnp.exp(log_pmf))
    # counts past the buffer keep the CDF short of u: the count then exceeds the bound (overflow)
    poisson = jnp.where(noise.false_mean > 0, jnp.sum(cdf < u_poisson, dtype=jnp.int32), 0)
    p = noise.false_ratio
    from_ratio = jnp.round(p * n_true / jnp.maximum(1.0 - p, 1e-6)).astype(jnp.int32)
    per_true = jnp.round(noise.false_per_true * n_true).astype(jnp.int32)
    return fixed + poisson + from_ratio + per_true


def _false_magnitudes(u, noise):
    """Magnitudes (n,) on ``[false_mag_min, false_mag_max]`` with density ∝ 10^(slope · m), by
    inverting the truncated exponential's CDF at uniforms ``u`` (n,); slope 0 is uniform. With a knee
    inside the range, the density is 10^(s₁ (m − k)) brighter than it and 10^(s₂ (m − k)) fainter."""
    lo, hi = noise.false_mag_min, noise.false_mag_max
    a = noise.false_mag_slope * math.log(10.0)
    span = hi - lo
    flat = jnp.abs(a * span) < 1e-6
    a_safe = jnp.where(flat, 1.0, a)
    tilted = jnp.log1p(u * jnp.expm1(a_safe * span)) / a_safe
    one_slope = lo + jnp.where(flat, u * span, tilted)
    knee = jnp.clip(noise.false_mag_knee, lo, hi)
    # masses either side of the knee, in units of the density there: ∫₀ᴸ e^(b t) dt = expm1(bL)/b
    bright = _exp_mass(-a, knee - lo)  # t = k − m, density e^(−a t)
    faint = _exp_mass(noise.false_mag_slope_faint * math.log(10.0), hi - knee)
    v = u * (bright + faint)
    from_knee_bright = _exp_mass_inverse(-a, bright - v)  # k − m where the mass brighter than m is v
    from_knee_faint = _exp_mass_inverse(noise.false_mag_slope_faint * math.log(10.0), v - bright)
    two_slopes = jnp.where(v < bright, knee - from_knee_bright, knee + from_knee_faint)
    return jnp.where(noise.false_mag_knee < hi, two_slopes, one_slope)


def _exp_mass(b, length):
    """∫₀^length e^(b t) dt (length ≥ 0), exact at b = 0."""
    flat = jnp.abs(b * length) < 1e-6
    return jnp.where(flat, length, jnp.expm1(b * length) / jnp.where(flat, 1.0, b))


def _exp_mass_inverse(b, mass):
    """The length whose :func:`_exp_mass` is ``mass`` (≥ 0)."""
    mass = jnp.maximum(mass, 0.0)
    flat = jnp.abs(b * mass) < 1e-6
    # b < 0: the mass stays below 1/|b|; rounding at u → 1 must not take the log past −1
    return jnp.where(flat, mass, jnp.log1p(jnp.maximum(b * mass, -0.999999)) / jnp.where(flat, 1.0, b))


def _false_positions(seed, n, radius_px, camera, *, disk: bool, tries: int = 8):
    """n uniform positions in the frame, or in (disk of ``radius_px`` about (cx, cy)) ∩ frame by
    rejection: ``tries`` candidates each, the first inside is used (the last, clipped in, as fallback).
    """
    w, h = camera.width - 1.0, camera.height - 1.0
    frame = streams.uniforms(seed, streams.FALSE_XY, (n, 2)) * jnp.array([[w, h]])
    if not disk:  # no finite radius in the batch: the disk draws would all be discarded
        return frame
    rad = jnp.minimum(radius_px, 2.0 * (w + h))  # inf → a disk that covers the frame
    r = rad * jnp.sqrt(streams.uniforms(seed, streams.FALSE_R, (tries, n)))
    t = 2.0 * jnp.pi * streams.uniforms(seed, streams.FALSE_T, (tries, n))
    cand = jnp.stack([camera.cx + r * jnp.cos(t), camera.cy + r * jnp.sin(t)], -1)  # (tries, n, 2)
    inside = camera.contains(cand)
    first = jnp.argmax(inside, axis=0)
    pick = jnp.take_along_axis(cand, first[None, :, None], axis=0)[0]
    pick = jnp.clip(pick, 0.0, jnp.array([[w, h]]))
    return jnp.where(jnp.isinf(radius_px), frame, pick)
