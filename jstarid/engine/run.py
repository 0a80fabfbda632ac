"""The sweep engine: simulate every level in one call, run every algorithm on the same scenes.

:func:`sweep` = :func:`~jstarid.engine.levels.level_noise` → one ``js.simulate`` call →
:func:`compare` → :class:`~jstarid.engine.result.SweepResult`. :func:`compare` runs each entry's
``identify`` on the scenes in chunks that never cross a level and hold at most ``chunk_size``
scenes (memory stays bounded whatever the sweep's size), scores every scene by one rule
(:func:`jstarid.metrics.scene_outcomes`) and measures every algorithm's attitude the same way (a
Wahba fit of the stars it named, :func:`jstarid.estimate_attitude`), so the algorithms differ only
in their names. Timing: every chunk is timed once (wall time, compilation of the shapes a level
meets first included; the entry's first call is recorded apart); scenes/s are per process.
``experiments/benchmark.py`` measures steady throughput.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms import base
from jstarid.algorithms import get as get_algorithm
from jstarid.attitude import attitude_errors_arcsec, estimate_attitude
from jstarid.camera import Camera
from jstarid.camera_files import load_camera
from jstarid.catalog import FULL_DEPTH, load_catalog
from jstarid.centroid import CentroidConfig
from jstarid.detection_model import DetectionModel
from jstarid.engine import processes
from jstarid.engine.entries import Entry, check_camera
from jstarid.engine.entries import entries as make_entries
from jstarid.engine.levels import level_grid, level_noise
from jstarid.engine.pixels import RENDER_DEPTH_MAG, SENSOR_AXES, detect_scenes, sensor_levels
from jstarid.engine.result import SweepResult
from jstarid.experiment import peak_rss_mb
from jstarid.false_match import of_solutions
from jstarid.metrics import CRITERIA, scene_outcomes
from jstarid.render import SensorConfig, sensor_for_camera
from jstarid.runtime.compilations import CountCompilations
from jstarid.runtime.memory_maps import relieve
from jstarid.runtime.staging_memory import release_staging
from jstarid.scene import Identification, Scene
from jstarid.simulator import simulate

__all__ = ["Levels", "compare", "plan", "simulate_levels", "sweep", "BORESIGHTS", "CHUNK_SIZE",
           "SCORES"]

BORESIGHTS = ("random", "stars")
# Scenes per identify call. Kept at 256: SGM on two CPU devices has stopped for good inside an eager
# op after its sharded pair kernels at 1,000-scene calls (seen five times, JAX 0.10.2; cause open,
# issue 37) and never at 200-scene calls in about ten runs.
CHUNK_SIZE = 256
SKY_CAPACITY = 512  # stars rendered per frame in a sweep from pixels (more: the sky's overflow count)
# what is kept per scene and entry (the table is computed from these alone)
SCORES = {"outcome": np.int8, "n_correct": np.int16, "n_wrong": np.int16, "n_identified": np.int16,
          "boresight_err_arcsec": np.float32, "roll_err_arcsec": np.float32, "false_match": np.float32}


def sweep(algorithms: Sequence | str = "sgm,mlv,rpnet", camera: str | Camera = "sgm2022", *,
          axes: Mapping[str, Sequence[float]] | None = None, fixed: Mapping | None = None,
          scenes: int = 200, seed: int = 0, catalog=None, capacity: int = 64,
          boresight: str = "random", criterion: str = "strict", chunk_size: int = CHUNK_SIZE,
          rpnet_network: str | None = None, progress: bool = True, pixels: bool = False,
          sensor: SensorConfig | None = None, centroid: CentroidConfig | None = None,
          detection: DetectionModel | str | None = None) -> SweepResult:
    """Every algorithm × every noise level on one shared, seeded set of simulated scenes.

    Args:
        algorithms: registry names (``"sgm,mlv"`` or a list), :class:`~jstarid.engine.Entry`
            items, or :func:`~jstarid.engine.grid` lists.
        camera: a preset name (:func:`jstarid.preset_names`), a camera file or a
            :class:`~jstarid.Camera`; algorithms given by name get their defaults for it
            (:func:`~jstarid.engine.entries.default_config`).
        axes: one or two noise axes ``{axis: levels}`` (default ``{"position_sigma_px": [0, 1, 2,
            3]}``); axis names as in :func:`~jstarid.engine.levels.axis_field`.
        fixed: other :class:`~jstarid.NoiseConfig` settings for every scene.
        scenes: scenes per level.
        seed: PRNG seed of the scenes (same seed, same scenes, for every algorithm).
        catalog: a :class:`~jstarid.Catalog` (default: Hipparcos down to the camera's limit).
        capacity: detections kept per scene.
        boresight: ``"random"`` (uniform attitudes), ``"stars"`` (boresight on a catalog star
            drawn at random, roll uniform: the SGM and RpNet papers' scenes) or a 1-D array of
            the catalog rows to draw that star from (e.g. RpNet's guide stars).
        criterion: outcome rule (:data:`jstarid.metrics.CRITERIA`).
        chunk_size: most scenes per ``identify`` call (bounds memory).
        rpnet_network: RpNet's network when RpNet is named (``"quick"`` or ``"table3"``; ``None``:
            ``"quick"``), the preset of every algorithm with presets
            (:func:`~jstarid.engine.entries.default_config`).
        progress: print what is built and each algorithm's progress (stderr).
        pixels: run from rendered frames (:mod:`~jstarid.engine.pixels`: render → extract → label →
            identify) instead of the simulator's centroids; the axes may then vary
            :class:`~jstarid.SensorConfig` fields (``"exposure_s"``, ``"defocus_px"``, …).
        sensor: the sensor of a sweep from pixels (default: :func:`jstarid.sensor_for_camera`).
        centroid: the extractor's settings of a sweep from pixels (default: ``CentroidConfig()``).
        detection: draw the centroids from a :class:`~jstarid.DetectionModel` (every scene), or
            ``"sensor"``: from each level's sensor (``DetectionModel.from_sensor`` of ``sensor`` and
            ``centroid``), so sensor axes run without rendering; the sky then reaches the model's
            depth and stars past the catalog's limit are labelled −1.

    Returns:
        A :class:`~jstarid.engine.result.SweepResult` (rows, per-scene outcomes, settings).

    Raises:
        ValueError: an unknown algorithm, camera, axis or criterion, scenes or chunk size < 1,
            out-of-range noise, or an algorithm that cannot work on the camera
            (:func:`~jstarid.engine.entries.check_camera`), all before anything is simulated.
    """
    _check_positive(chunk_size=chunk_size)
    if criterion not in CRITERIA:
        raise ValueError(f"unknown criterion {criterion!r}; choose one of {CRITERIA}")
    camera = load_camera(camera)
    entries = make_entries(algorithms, rpnet_network=rpnet_network, camera=camera)
    check_camera(entries, camera, catalog)
    drawn = simulate_levels(camera, axes=axes, fixed=fixed, scenes=scenes, seed=seed,
                            catalog=catalog, capacity=capacity, boresight=boresight,
                            progress=progress, pixels=pixels, sensor=sensor, centroid=centroid,
                            detection=detection)
    settings = {**drawn.settings, "criterion": criterion, "chunk_size": chunk_size}
    return compare(drawn.scenes, entries, drawn.catalog, drawn.camera, level_of=drawn.level_of,
                   levels=drawn.levels, criterion=criterion, chunk_size=chunk_size,
                   progress=progress, settings=settings)


class Levels(NamedTuple):
    """A sweep's scenes (:func:`simulate_levels`): every level's, level-major.

    Attributes:
        scenes: (L · n, N) :class:`~jstarid.Scene`. level_of: (L · n,) level index of each scene.
        levels: per level, ``{noise field: value}``. catalog, camera: what they were drawn from.
        settings: the drawing settings (recorded with a sweep's result).
    """

    scenes: Scene
    level_of: np.ndarray
    levels: list
    catalog: object
    camera: Camera
    settings: dict


def simulate_levels(camera: str | Camera = "sgm2022", *,
                    axes: Mapping[str, Sequence[float]] | None = None,
                    fixed: Mapping | None = None, scenes: int = 200, seed: int = 0, catalog=None,
                    capacity: int = 64, boresight: str = "random", progress: bool = False,
                    pixels: bool = False, sensor: SensorConfig | None = None,
                    centroid: CentroidConfig | None = None,
                    detection: DetectionModel | str | None = None, attitudes=None) -> Levels:
    """The scenes :func:`sweep` runs on, in one ``simulate`` call (arguments as in :func:`sweep`);
    from pixels, the sky's scenes in that call and each level's frames rendered and extracted in
    batched calls (:func:`~jstarid.engine.pixels.detect_scenes`).

    ``attitudes``: (L · scenes, 3, 3) rotations ICRS → camera of every scene, level-major, instead of
    drawn ones (``boresight="random"`` only; :func:`jstarid.simulate`'s mode c).

    A script that measures more than the engine does (a network's top-1 accuracy, a naming
    ceiling) draws the scenes here and passes them to :func:`compare` and to its own code.
    """
    axes = {"position_sigma_px": [0.0, 1.0, 2.0, 3.0]} if axes is None else axes
    camera = load_camera(camera)
    _check_positive(scenes=scenes, capacity=capacity)
    candidates = None
    if not isinstance(boresight, str):  # the catalog rows a boresight star is drawn from
        candidates = np.asarray(boresight)
        if candidates.ndim != 1 or candidates.size == 0 or not np.issubdtype(candidates.dtype,
                                                                             np.integer):
            raise ValueError("boresight rows must be a non-empty 1-D integer array")
        boresight = "stars"
    if boresight not in BORESIGHTS:
        raise ValueError(f"boresight must be one of {BORESIGHTS} or catalog rows, got {boresight!r}")
    levels = level_grid(axes)
    if attitudes is not None and (boresight != "random" or np.shape(attitudes)[0] != len(levels) * scenes):
        raise ValueError(f"attitudes must hold one rotation per scene ({len(levels) * scenes}) and "
                         f"come with boresight='random'")
    noise = level_noise(levels, scenes, fixed)
    if pixels and detection is not None:
        raise ValueError("a sweep from pixels detects in the pixels: drop detection")
    if isinstance(detection, str) and detection != "sensor":
        raise ValueError(f"detection must be a DetectionModel or 'sensor', got {detection!r}")
    sensors = _pixel_settings(levels, camera, pixels or detection == "sensor", sensor, centroid)
    catalog = load_catalog(camera.mag_limit) if catalog is None else catalog
    candidates = np.arange(len(catalog)) if candidates is None else candidates
    total = len(levels) * scenes
    key_scenes, key_rows = jax.random.split(jax.random.key(seed))
    pointing = (candidates[np.asarray(jax.random.randint(key_rows, (total,), 0, candidates.size))]
            if boresight == "stars" else None)
    t0 = time.perf_counter()
    if attitudes is not None:
        pointing = np.asarray(attitudes, np.float64)
    if pixels:
        batch, pixel_settings = _from_pixels(key_scenes, catalog, camera, noise, pointing, levels, sensors,
                                             centroid or CentroidConfig(), scenes, capacity, progress)
    elif detection is not None:
        batch, pixel_settings = _from_model(key_scenes, catalog, camera, noise, pointing, detection, sensors,
                                            centroid or CentroidConfig(), scenes, total, capacity)
    else:
        batch = simulate(key_scenes, catalog, camera, noise, capacity=capacity, shard=True,
                         **_pointing_arguments(pointing, total))
        pixel_settings = {}
    jax.block_until_ready(batch)
    _say(progress, f"simulated {total:,} scenes ({len(levels)} levels × {scenes}) in "
                   f"{time.perf_counter() - t0:.1f} s")
    settings = {"camera": camera, "catalog": {"mag_limit": catalog.mag_limit,
                                              "fingerprint": catalog.fingerprint,
                                              "stars": len(catalog)},
                "axes": {k: sorted({lv[k] for lv in levels}, key=[lv[k] for lv in levels].index)
                         for k in levels[0]}, "levels": levels,
                "fixed": dict(fixed or {}), "scenes_per_level": scenes, "seed": seed,
                "capacity": capacity,
                "boresight": boresight if attitudes is None else "given attitudes",
                "simulate_seconds": time.perf_counter() - t0, "pixels": bool(pixels), **pixel_settings}
    return Levels(batch, np.repeat(np.arange(len(levels)), scenes).astype(np.int32), levels,
                  catalog, camera, settings)


def _pixel_settings(levels, camera, pixels, sensor, centroid):
    """Each level's sensor for a sweep from pixels (checked before anything is simulated)."""
    sensor_fields = sorted({k for lv in levels for k in lv if k in SENSOR_AXES})
    if not pixels:
        if sensor_fields:
            raise ValueError(f"{', '.join(sensor_fields)}: a sensor axis needs a sweep from pixels "
                             f"(pixels=True; the command line's --pixels) or from the sensor's "
                             f"detection model (detection='sensor')")
        if sensor is not None or centroid is not None:
            raise ValueError("sensor and centroid settings are for sweeps from pixels (pixels=True) "
                             "or from the sensor's detection model (detection='sensor')")
        return None
    return sensor_levels(levels, sensor_for_camera(camera) if sensor is None else sensor)


def _deep_sky(key, catalog, camera, noise, pointing, total, depth, capacity, detection=None):
    """One ``simulate`` call from a catalog to V ``depth`` (the identification catalog's other
    settings), its truth relabelled in the identification catalog's rows (−1: a star it lacks)."""
    kept = ("double_sep_deg", "double_mode", "sim_margin", "epoch")
    sky_catalog = load_catalog(depth, **{k: v for k, v in catalog.settings.items() if k in kept})
    sky_camera = dataclasses.replace(camera, mag_limit=depth) if detection is None else camera
    if pointing is not None and pointing.ndim == 1:  # the boresight stars, as rows of the deeper catalog
        pointing = _rows_in(sky_catalog, catalog, pointing)
    sky = simulate(key, sky_catalog, sky_camera, noise, capacity=capacity, shard=True,
                   detection=detection, **_pointing_arguments(pointing, total))
    sky = jax.device_get(sky)
    deep = np.asarray(sky.truth)
    truth = np.where(deep >= 0, catalog.row_of_hip(sky_catalog.hip[np.maximum(deep, 0)]), -1)
    return dataclasses.replace(sky, truth=truth.astype(np.int32))


def _from_model(key, catalog, camera, noise, pointing, detection, sensors, centroid, per_level, total,
                capacity):
    """The sweep's scenes drawn from a detection model (one for every scene, or each level's
    sensor's), in one ``simulate`` call from a sky as deep as the model detects."""
    if isinstance(detection, str):  # "sensor": each level's model, repeated over its scenes
        models = [DetectionModel.from_sensor(camera, s, centroid) for s in sensors]
        fields = [f.name for f in dataclasses.fields(DetectionModel)]
        detection = DetectionModel(**{f: np.repeat([getattr(m, f) for m in models], per_level)
                                      for f in fields})
        recorded = {"detection": "sensor", "sensors": [dataclasses.asdict(s) for s in sensors],
                    "centroid": dataclasses.asdict(centroid),
                    "models": [dataclasses.asdict(m) for m in models]}
    elif isinstance(detection, DetectionModel):
        recorded = {"detection": {f.name: np.asarray(getattr(detection, f.name)).tolist()
                                  for f in dataclasses.fields(detection)}}
    else:
        raise ValueError(f"detection must be a DetectionModel or 'sensor', got {type(detection).__name__}")
    detection.validate()
    sim_margin = catalog.settings.get("sim_margin", 1.0)
    seen = detection.simulation_depth(float(np.max(np.asarray(noise.magnitude_sigma))))
    depth = camera.mag_limit  # an ideal model cuts at the camera's limit: no deeper sky
    if math.isfinite(seen):
        depth = min(FULL_DEPTH - sim_margin, max(depth, seen - sim_margin))
    sky = _deep_sky(key, catalog, camera, noise, pointing, total, depth, capacity, detection)
    return sky, {**recorded, "detection_depth_mag": depth}


def _from_pixels(key, catalog, camera, noise, pointing, levels, sensors, centroid, per_level, capacity,
                 progress):
    """The sweep's scenes from rendered frames: the sky to the camera's limit + RENDER_DEPTH_MAG
    in one ``simulate`` call, then each level rendered, extracted and labelled (engine.pixels)."""
    total = len(levels) * per_level
    key_sky, key_frames = jax.random.split(key)
    sky = _deep_sky(key_sky, catalog, camera, noise, pointing, total, camera.mag_limit + RENDER_DEPTH_MAG,
                    SKY_CAPACITY)
    keys = jax.random.split(key_frames, total)
    parts, seconds = [], 0.0
    for level, sensor in enumerate(sensors):
        at = slice(level * per_level, (level + 1) * per_level)
        part, dt = detect_scenes(keys[at], jax.tree.map(lambda a, at=at: a[at], sky), camera, sensor,
                                 centroid, capacity=capacity)
        parts.append(part)
        seconds += dt
        _say(progress, f"rendered and extracted level {level + 1}/{len(levels)} "
                       f"({per_level} frames, {dt:.1f} s)")
    scenes = jax.tree.map(lambda *a: jnp.concatenate(a), *parts)
    return scenes, {"sensors": [dataclasses.asdict(s) for s in sensors],
                    "centroid": dataclasses.asdict(centroid), "render_depth_mag": RENDER_DEPTH_MAG,
                    "sky_capacity": SKY_CAPACITY, "render_extract_seconds": seconds,
                    "sky_overflow": int(np.asarray(sky.overflow).sum())}


def _pointing_arguments(pointing, total) -> dict:
    """``simulate``'s pointing arguments: ``total`` random attitudes (``pointing`` None), boresight
    stars (``pointing`` (S,) catalog rows) or the given attitudes (``pointing`` (S, 3, 3))."""
    if pointing is None:
        return {"batch_size": total}
    return {"attitudes": pointing} if np.ndim(pointing) == 3 else {"boresight_ids": pointing}


def _rows_in(other, catalog, rows) -> np.ndarray:
    """The rows of ``other`` holding the stars ``catalog`` has at ``rows``: by HIP number, or, for a
    star ``other`` dropped as the fainter of a close pair, the nearest star it kept."""
    out = other.row_of_hip(catalog.hip[rows])
    lost = np.nonzero(out < 0)[0]
    if lost.size:
        out[lost] = np.argmax(np.matmul(catalog.unit_vectors[rows[lost]], other.unit_vectors.T), axis=1)
    return out


def compare(scenes: Scene, algorithms: Sequence | str, catalog, camera: Camera, *,
            level_of: np.ndarray | None = None, levels: Sequence[Mapping] | None = None,
            criterion: str = "strict", chunk_size: int = CHUNK_SIZE, progress: bool = True,
            settings: Mapping | None = None, rpnet_network: str | None = None) -> SweepResult:
    """Every entry on the given scenes, scored per scene and tabulated per level.

    Args:
        scenes: (S, N) scenes (with truth) from ``camera``.
        algorithms: as in :func:`sweep`.
        catalog, camera: what the scenes were drawn from.
        level_of: (S,) level index of each scene (default: one level), ascending.
        levels: the levels' settings, ``{field: value}`` each (default: ``[{}]``).
        criterion, chunk_size, progress, rpnet_network: as in :func:`sweep`.
        settings: recorded with the result.

    Returns:
        A :class:`~jstarid.engine.result.SweepResult`.
    """
    entries = make_entries(algorithms, rpnet_network=rpnet_network, camera=camera)
    check_camera(entries, camera, catalog)
    _check_positive(chunk_size=chunk_size)
    n_total = scenes.batch_size
    level_of = np.zeros(n_total, np.int32) if level_of is None else np.asarray(level_of, np.int32)
    levels = [{}] if levels is None else list(levels)
    if level_of.shape != (n_total,) or np.any(np.diff(level_of) < 0) or level_of.max() >= len(levels):
        raise ValueError("level_of must be an ascending (S,) index into levels")
    # a host copy: chunks are cut on the host and each algorithm places (and shards) its inputs
    # itself, rather than every chunk starting as a slice of a sharded device array
    mine = processes.share(n_total)
    local = jax.device_get(scenes)[mine]
    chunks = _chunks(level_of[mine], chunk_size)
    scored: list[dict | None] = [None] * len(entries)
    timing: list[dict | None] = [None] * len(entries)
    seconds = np.zeros((len(entries), len(levels)))
    compile_seconds = np.zeros((len(entries), len(levels)))
    for members in _groups(entries):
        first = entries[members[0]]
        module = get_algorithm(first.algorithm)
        configs = [entries[i].config for i in members]
        names = first.group or first.label
        _say(progress, f"{names}: database …")
        t0 = time.perf_counter()
        # one database per config (cached on disk: a grid over traced tolerances loads one file)
        dbs = [module.build_database(catalog, camera, c, progress=progress and k == 0)
               for k, c in enumerate(configs)]
        t_db = time.perf_counter() - t0
        run = _runner(module, dbs, configs)
        outs = [[] for _ in members]
        first_call = None
        for c, (part, level) in enumerate(chunks):
            results, shares, compile_shares = run(local[part])
            first_call = sum(shares) if first_call is None else first_call
            for k, i in enumerate(members):
                seconds[i, level] += shares[k]
                compile_seconds[i, level] += compile_shares[k]
                outs[k].append(_score(local[part], results[k], catalog, camera, criterion,
                                      base.scoring_radius_deg(entries[i].config)))
            release_staging()  # outside the timed call (runtime.staging_memory)
            if progress and (c + 1 == len(chunks) or c % 4 == 3):
                _say(True, f"{names}: {part.stop:,} / {local.batch_size:,} scenes")
        for k, i in enumerate(members):
            scored[i] = {name: np.concatenate([o[name] for o in outs[k]]) if outs[k]
                         else np.zeros((0,), dtype) for name, dtype in SCORES.items()}
            timing[i] = {"label": entries[i].label, "database_seconds": t_db,
                         "first_call_seconds": first_call, "peak_rss_mb": peak_rss_mb()}
        relieve()  # between algorithms, never inside a timed chunk (runtime.memory_maps)
    local_arrays = {name: np.stack([s[name] for s in scored], axis=1) for name in SCORES}  # (S_i, E)
    merged = processes.gather(local_arrays, n_total)
    # (P, E, L) → (E, L): every process's seconds at each level, added
    spent = processes.gather({"s": seconds[None], "c": compile_seconds[None]}, processes.process_count())
    merged["seconds"], merged["compile_seconds"] = spent["s"].sum(0), spent["c"].sum(0)
    valid, truth = (np.asarray(a) for a in jax.device_get((scenes.valid, scenes.truth)))
    return SweepResult.from_arrays(entries=entries, levels=levels, level_of=level_of, arrays=merged,
                                   timing=timing, settings=dict(settings or {}),
                                   processes=processes.process_count(),
                                   stars=np.sum(valid & (truth >= 0), axis=1))


def plan(algorithms: Sequence | str, catalog, camera: Camera, *, rpnet_network: str | None = None,
         compiled_before: bool = True) -> list[tuple[str, float]]:
    """What a run of these entries builds first, and about how long each takes on 2 CPU cores (s).

    Uses each algorithm's optional ``first_use(catalog, camera, config)``
    (:func:`jstarid.algorithms.base.first_use`); empty when everything is cached.

    Args:
        compiled_before: ``False`` adds the one-off compilation of a first run on this machine
            (no on-disk compilation cache yet): the longest of the algorithms'
            (:func:`jstarid.algorithms.base.first_compile_seconds`).
    """
    items = []
    modules = {}
    for entry in make_entries(algorithms, rpnet_network=rpnet_network, camera=camera):
        module = modules.setdefault(entry.algorithm, get_algorithm(entry.algorithm))
        item = base.first_use(module, catalog, camera, entry.config)
        if item and item not in items:
            items.append(item)
    if not compiled_before:
        seconds = max(base.first_compile_seconds(m) for m in modules.values())
        items.append(("compiled kernels, kept on disk for later runs", seconds))
    return items


def _runner(module, dbs, configs):
    """``run(scenes) -> ([Identification per config], [seconds per config], [XLA compile seconds per
    config])``: the algorithm's ``identify_grid`` (one batch, its times shared equally) where it can
    take the grid, else one timed ``identify`` call per config with its own database."""
    # only an algorithm's own identify_grid batches the grid: the contract's default is the
    # per-config calls below, which time each config on its own
    state = {"batched": (len(configs) > 1 and base.declares(module, "identify_grid")
                         and len({d.cache_key() for d in dbs}) == 1)}

    def timed(call):  # call() -> [Identification]; returns it, its wall time and XLA's compile time (s)
        with CountCompilations() as compiled:
            t0 = time.perf_counter()
            out = call()
            jax.block_until_ready([r.ids for r in out])
            dt = time.perf_counter() - t0
        return out, dt, compiled.seconds

    def run(scenes):
        if state["batched"]:
            try:
                results, dt, ct = timed(lambda: base.identify_grid(module, dbs[0], scenes, configs))
                return results, [dt / len(configs)] * len(configs), [ct / len(configs)] * len(configs)
            except ValueError:  # the grid varies settings it cannot batch (e.g. MLV's Δv)
                state["batched"] = False
        each = [timed(lambda db=db, c=c: [module.identify(db, scenes, c)])
                for db, c in zip(dbs, configs, strict=True)]
        return [out[0] for out, _, _ in each], [dt for _, dt, _ in each], [ct for _, _, ct in each]

    return run


def _groups(entries: Sequence[Entry]) -> list[list[int]]:
    """Entry indices grouped by grid (an entry without a group is alone)."""
    groups: dict[str, list[int]] = {}
    out = []
    for i, e in enumerate(entries):
        if e.group:
            if e.group not in groups:
                groups[e.group] = []
                out.append(groups[e.group])
            groups[e.group].append(i)
        else:
            out.append([i])
    return out


def _chunks(level_of: np.ndarray, chunk_size: int) -> list[tuple[slice, int]]:
    """``(rows, level)`` blocks of at most ``chunk_size`` rows that never cross a level."""
    out = []
    starts = np.flatnonzero(np.r_[True, np.diff(level_of) != 0]) if level_of.size else []
    ends = list(starts[1:]) + [level_of.size]
    for lo, hi in zip(starts, ends, strict=True):
        for a in range(int(lo), int(hi), chunk_size):
            out.append((slice(a, min(a + chunk_size, int(hi))), int(level_of[lo])))
    return out


def _score(scenes: Scene, result: Identification, catalog, camera, criterion,
           radius_deg: float = 6.0) -> dict:
    """Per-scene outcome, counts, attitude errors (a Wahba fit of the named stars) and the claim's
    false-match probability (:func:`jstarid.false_match.of_solutions`; 1 where not claimed).

    ``radius_deg``: the neighbor circle of the ``"sgm"`` criterion, the entry's own where its
    config has one (an SGM run with another r is scored on its own circle).
    """
    out = scene_outcomes(scenes, result, criterion, camera=camera, radius_deg=float(radius_deg))
    att, _, have = estimate_attitude(catalog, camera, scenes, result)
    bore, roll = attitude_errors_arcsec(att, scenes.attitude)
    have = np.asarray(have) & np.asarray(result.ok)
    # the names' Wahba attitude where the algorithm gives none: the false-match probability reads it
    located = result if result.attitude is not None else dataclasses.replace(
        result, attitude=np.where(have[:, None, None], np.asarray(att, np.float32), np.nan))
    return {"outcome": np.asarray(out["outcome"], np.int8),
            "n_correct": np.asarray(out["n_correct"], np.int16),
            "n_wrong": np.asarray(out["n_wrong"], np.int16),
            "n_identified": np.asarray(out["n_identified"], np.int16),
            "boresight_err_arcsec": np.where(have, np.asarray(bore), np.nan).astype(np.float32),
            "roll_err_arcsec": np.where(have, np.asarray(roll), np.nan).astype(np.float32),
            "false_match": of_solutions(scenes, located, catalog, camera).astype(np.float32)}


def _check_positive(**values) -> None:
    for name, value in values.items():
        if not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")


def _say(on: bool, text: str) -> None:
    if on and jax.process_index() == 0:
        print(text, file=sys.stderr, flush=True)
