"""jstarid: lost-in-space star identification in JAX (public API, docs/conventions.md §9)."""

from jstarid import algorithms, engine, experiment, plotting, runtime, sky_depth, twin, wcs
from jstarid.attitude import (
    attitude_errors_arcsec,
    estimate_attitude,
    quaternion_from_rotation,
    random_rotation,
    rotation_from_boresight,
    rotation_from_quaternion,
    rotation_from_radec_roll,
    rotation_to_radec_roll,
    solve_wahba,
)
from jstarid.camera import Camera, camera_preset, preset_names
from jstarid.camera_files import load_camera, save_camera
from jstarid.catalog import Catalog, load_catalog, v_from_hp
from jstarid.centroid import CentroidConfig, extract_centroids
from jstarid.compilation_cache import enable_compilation_cache
from jstarid.completion import name_from_attitude
from jstarid.detection_model import DetectionModel
from jstarid.engine import Entry, SweepResult, compare, grid, sweep
from jstarid.engine import load as load_sweep
from jstarid.finishing import Finishing
from jstarid.image_files import ImageFile, read_image, read_image_file
from jstarid.metrics import evaluate, scene_outcomes
from jstarid.render import SensorConfig, mean_electrons, render, sensor_for_camera
from jstarid.runtime import use_cpu_cores
from jstarid.scene import Identification, Scene, pad_with_empty, scenes_from_centroids, undistort_scenes
from jstarid.simulator import (
    CATALOG_MAG_SLOPE,
    NoiseConfig,
    SceneSampler,
    noise_grid,
    scene_sampler,
    simulate,
)
from jstarid.solution import Solution, solve

__version__ = "0.1.0"

__all__ = [
    "CATALOG_MAG_SLOPE", "Camera", "Catalog", "CentroidConfig", "DetectionModel", "Entry", "Finishing",
    "Identification",
    "NoiseConfig", "Scene",
    "SensorConfig", "mean_electrons", "render", "sensor_for_camera",
    "SweepResult", "algorithms", "compare", "engine", "experiment", "grid", "load_sweep", "sweep",
    "plotting", "runtime", "sky_depth", "twin", "wcs", "attitude_errors_arcsec", "camera_preset",
    "enable_compilation_cache",
    "estimate_attitude", "evaluate", "extract_centroids", "load_camera", "load_catalog", "name_from_attitude",
    "noise_grid", "pad_with_empty", "preset_names", "quaternion_from_rotation", "random_rotation",
    "ImageFile", "read_image", "read_image_file",
    "rotation_from_boresight", "rotation_from_quaternion", "rotation_from_radec_roll",
    "rotation_to_radec_roll", "save_camera", "scene_outcomes", "scene_sampler", "scenes_from_centroids",
    "SceneSampler", "simulate",
    "Solution", "solve", "solve_wahba", "undistort_scenes",
    "use_cpu_cores", "v_from_hp",
]
