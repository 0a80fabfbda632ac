"""cedar-solve (the maintained fork of ESA's tetra3) as a peer behind the algorithm contract.

cedar-solve pins numpy < 2 and Pillow < 9, so it lives in its own virtual environment, created on
first use under the jstarid cache (``peer-cedar-venv``: ``pip install cedar-solve==0.5.1``, ≈ 2 min
from the package index). :func:`build_database` writes jstarid's catalog in the ``hip_main.dat``
format (the only name cedar's ``generate_database`` reads: '|'-separated, HIP in field 1, V in 5,
RA and Dec in degrees in 8 and 9; no proper motion, so cedar takes the positions as given) and has
cedar build its database for the camera's horizontal field and magnitude limit (cached).
:func:`identify` exports the scenes' valid detections, brightest first, in cedar's convention
((y, x) from the image's corner: jstarid's pixel centres + 0.5), runs ``solve_from_centroids`` on
each in the peer environment (:mod:`jstarid.peers.cedar_worker`) and brings the matches back: a
matched centroid names its detection with the catalog row of the matched HIP; a scene cedar does
not solve is a failure. Host-side by nature (another process, another interpreter).
"""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from jstarid.algorithms.base import cache_key, check_scenes
from jstarid.catalog import cache_dir
from jstarid.scene import Identification, Scene

__all__ = ["CEDAR", "REPORTED", "Config", "Database", "Diagnostics", "Tuning", "build_database",
           "environment", "export_scenes", "first_use", "identify", "matches_to_ids", "solve",
           "write_hip_main"]

CEDAR = "cedar-solve==0.5.1"

#: The settings cedar is reported at, as a grid of :class:`Config` fields (``jstarid demo --peer
#: cedar`` runs every one of them as a row): its default ``match_max_error`` 0.002, which fails at
#: 2–3 px of centroid noise, and 0.005, a fair tuned value; reporting only the default would be unfair.
REPORTED = {"match_max_error": (0.002, 0.005)}
_WORKER = Path(__file__).with_name("cedar_worker.py")


class Tuning(NamedTuple):
    """Nothing to sweep inside one compiled call (cedar's settings are ``Config`` fields)."""


@dataclasses.dataclass(frozen=True)
class Config:
    """cedar-solve's settings.

    Attributes:
        match_max_error: cedar's ``match_max_error`` (its default 0.002 fails at 2–3 px of noise;
            0.005 is a fair tuned value).
        timeout_ms: cedar's ``solve_timeout`` per scene (ms).
    """

    match_max_error: float = 0.002
    timeout_ms: int = 5000

    def __post_init__(self):
        if not (0 < self.match_max_error < 0.1) or self.timeout_ms < 1:
            raise ValueError("match_max_error must be in (0, 0.1) and timeout_ms ≥ 1")

    @classmethod
    def paper(cls, **overrides) -> Config:
        """cedar-solve's defaults."""
        return cls(**overrides)

    def tuning(self) -> Tuning:
        return Tuning()

    def database_fields(self) -> dict:
        return {}


@dataclasses.dataclass(frozen=True, eq=False)
class Database:
    """Where cedar's environment and database are, and what they were built for.

    Attributes:
        python: the peer environment's interpreter. database: cedar's ``.npz`` database.
        catalog: the :class:`~jstarid.catalog.Catalog` (HIP → row). camera: the camera.
        key: cache key.
    """

    python: Path
    database: Path
    catalog: object
    camera: object
    key: str = ""

    def cache_key(self) -> str:
        return self.key

    @property
    def fov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(self.camera.width / 2.0 / self.camera.f_px))


class Diagnostics(NamedTuple):
    """Per scene: ``n_candidates`` (B,) int32 stars cedar matched; ``overflow`` (B,) bool the scene's
    own flag; ``seconds`` (B,) float64 cedar's time for the solve."""

    n_candidates: jax.Array
    overflow: jax.Array
    seconds: np.ndarray


def environment(*, build: bool = True, quiet: bool = False) -> Path | None:
    """The peer environment's interpreter, created on first use (``build``); ``None``, with the
    reason printed, when it is not there and cannot be built."""
    venv = cache_dir() / "peer-cedar-venv"
    python = venv / "bin" / "python"
    if python.exists() or not build:
        return python if python.exists() else None
    if not quiet:
        print(f"building cedar-solve's environment in {venv} (once, ≈ 2 min) …", flush=True)
    try:
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        subprocess.run([str(python), "-m", "pip", "install", "-q", CEDAR], check=True)
    except (subprocess.CalledProcessError, OSError) as err:
        print(f"cedar-solve's environment could not be built ({err})", flush=True)
        return None
    return python


def write_hip_main(catalog, path: Path) -> None:
    """``catalog`` as a ``hip_main.dat`` cedar reads (fields 1, 5, 8, 9; the rest blank)."""
    ra = np.degrees(np.asarray(catalog.ra, np.float64)) % 360.0
    dec = np.degrees(np.asarray(catalog.dec, np.float64))
    lines = ["|".join(["H", f"{int(h):6d}", " ", " ", " ", f"{float(m):5.2f}", " ", " ", f"{a:12.8f}",
                       f"{d:12.8f}", " ", " ", " ", " ", " "])
             for h, m, a, d in zip(np.asarray(catalog.hip), np.asarray(catalog.mag), ra, dec, strict=True)]
    path.write_text("\n".join(lines) + "\n")


def export_scenes(scenes: Scene, path: Path) -> None:
    """Each scene's valid detections, brightest first, as cedar's (y, x) from the image's corner
    (``centroids`` (B, N, 2), ``counts`` (B,), ``order`` (B, N) the detection of each entry)."""
    xy, valid, mag = (np.asarray(a) for a in (scenes.xy, scenes.valid, scenes.mag))
    order = np.argsort(np.where(valid, mag, np.inf), axis=1, kind="stable")
    centroids = np.take_along_axis(xy, order[:, :, None], axis=1)[:, :, ::-1] + 0.5
    np.savez(path, centroids=centroids, counts=valid.sum(axis=1), order=order)


def matches_to_ids(scenes: Scene, catalog, solved: dict) -> tuple[np.ndarray, np.ndarray]:
    """cedar's matches → ((B, N) int32 catalog rows per detection, −1 unnamed; (B,) bool solved): a
    matched centroid names its nearest detection."""
    b, n = np.shape(scenes.valid)
    ids = np.full((b, n), -1, np.int32)
    ok = np.asarray(solved["solved"], bool)
    xy = np.asarray(scenes.xy) + 0.5  # cedar's pixel origin
    for s in np.flatnonzero(ok):
        matched = np.asarray(solved["matched"][s], float).reshape(-1, 2)  # (y, x)
        if matched.size:
            gap = np.hypot(xy[s, None, :, 0] - matched[:, None, 1], xy[s, None, :, 1] - matched[:, None, 0])
            ids[s, np.argmin(gap, axis=1)] = catalog.row_of_hip(np.asarray(solved["ids"][s], np.int64))
    return ids, ok


def _folder(catalog) -> Path:
    folder = cache_dir() / f"peer-cedar-{catalog.fingerprint}"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _run(python: Path, job: dict) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "job.json"
        path.write_text(json.dumps(job))
        subprocess.run([str(python), str(_WORKER), str(path)], check=True)


def build_database(catalog, camera, config: Config | None = None, *, use_cache: bool = True,
                   progress: bool = True) -> Database:
    """cedar's database for ``camera`` from ``catalog`` (built once, cached).

    Args:
        catalog, camera, config: as for every algorithm (:mod:`jstarid.algorithms.base`).
        use_cache: unused: cedar reads its database from a file, so the file under the jstarid
            cache is always kept and reused.
        progress: say what the environment's installation does.

    Raises:
        RuntimeError: cedar-solve's environment cannot be built.
    """
    config = Config() if config is None else config
    python = environment(quiet=not progress)
    if python is None:
        raise RuntimeError("cedar-solve's environment could not be built (see above)")
    folder = _folder(catalog)
    hip_main = folder / "hip_main.dat"
    if not hip_main.exists():
        write_hip_main(catalog, hip_main)
    key = cache_key("cedar", 1, catalog, camera, config.database_fields())
    db = Database(python=python, database=folder / f"db-{key}.npz", catalog=catalog, camera=camera, key=key)
    if not db.database.exists():
        _run(python, {"database": str(db.database), "catalog": str(hip_main), "fov_deg": db.fov_deg,
                      "mag_limit": float(camera.mag_limit)})
    return db


def first_use(catalog, camera, config: Config | None = None) -> tuple[str, float] | None:
    """What :func:`build_database` builds first and about how long it takes (s); ``None`` when ready."""
    config = Config() if config is None else config
    key = cache_key("cedar", 1, catalog, camera, config.database_fields())
    if environment(build=False) is not None and (_folder(catalog) / f"db-{key}.npz").exists():
        return None
    return f"cedar-solve's environment and database for {camera.name}", 150.0


def solve(database: Database, scenes: Scene, max_errors, *, timeout_ms: int = 5000) -> dict:
    """cedar's raw answers for every scene, once per ``match_max_error``: ``{str(error): {"solved",
    "matched", "ids", "seconds"}}`` (lists over the scenes; :func:`matches_to_ids` reads one)."""
    b = scenes.batch_size
    if b == 0:
        return {str(e): {"solved": [], "matched": [], "ids": [], "seconds": []} for e in max_errors}
    cam = database.camera
    with tempfile.TemporaryDirectory() as tmp:
        export_scenes(scenes, Path(tmp) / "scenes.npz")
        _run(database.python, {"database": str(database.database), "scenes": str(Path(tmp) / "scenes.npz"),
                               "fov_deg": database.fov_deg, "height": cam.height, "width": cam.width,
                               "max_errors": [float(e) for e in max_errors], "timeout_ms": int(timeout_ms),
                               "result": str(Path(tmp) / "result.json")})
        return json.loads((Path(tmp) / "result.json").read_text())


def identify(database: Database, scenes: Scene, config: Config | None = None, *,
             tuning: Tuning | None = None, diagnostics: bool = False):
    """Solve every scene with cedar-solve (module docstring); ``attitude`` is not returned
    (``tuning``: cedar has none, accepted for the contract)."""
    config = Config() if config is None else config
    check_scenes(scenes)
    answer = solve(database, scenes, [config.match_max_error], timeout_ms=config.timeout_ms)
    solved = answer[str(float(config.match_max_error))]
    ids, ok = matches_to_ids(scenes, database.catalog, solved)
    result = Identification(ids=ids, ok=ok, attitude=None)
    if diagnostics:
        return result, Diagnostics(n_candidates=np.sum(ids >= 0, axis=1).astype(np.int32),
                                   overflow=np.asarray(scenes.overflow),
                                   seconds=np.asarray(solved["seconds"], np.float64))
    return result
