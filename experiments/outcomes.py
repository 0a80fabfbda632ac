"""Outcomes of the seed algorithms on fixed scenes, saved for a before/after comparison of a refactor.

    python experiments/outcomes.py --out results/outcomes/after      # writes …/after/outcomes.npz
    python experiments/outcomes.py --compare results/outcomes/before/outcomes.npz \
        results/outcomes/after/outcomes.npz

Each algorithm runs with the configuration a user gets (``js.engine.default_config`` for its paper's
camera; RpNet with the quick network) on ``--scenes`` scenes per set from a fixed key, in two sets:
the camera as simulated, and the same centroids seen through a focal length ``--focal-error`` off
(so that the finishing stage's focal-length ladder and camera check both act). The file holds each
set's ``ids`` (B, N), ``ok`` (B,), ``attitude`` (B, 3, 3) and ``focal_scale`` (B,); ``--compare``
reports, per array, the scenes that differ (ids and ok exactly; attitudes and scales within 1e-5)
and exits 1 when any do.
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import numpy as np

import jstarid as js
from jstarid import camera_fit
from jstarid import experiment as ex

CAMERAS = {"sgm": ("sgm2022", 6.0, 128), "mlv": ("mlv2021", 5.5, 64), "rpnet": ("rpnet2019", 6.0, 64)}
ATOL = 1e-5  # attitudes (rotation-matrix entries) and focal scales compared within this


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/outcomes")
    p.add_argument("--algorithms", default="mlv,sgm,rpnet")
    p.add_argument("--scenes", type=int, default=200, help="scenes per set")
    p.add_argument("--position-sigma", type=float, default=1.0, help="centroid noise σ (px)")
    p.add_argument("--focal-error", type=float, default=0.015, help="relative focal-length error of set 2")
    p.add_argument("--compare", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    args = p.parse_args(argv)
    if args.set:
        p.error("--set: the outcomes are those of the default configurations")
    return args


def record(args) -> dict[str, np.ndarray]:
    """``{"<algorithm>/<set>/<field>": array}`` of every algorithm on both sets."""
    out = {}
    for name in args.algorithms.split(","):
        camera_name, depth, capacity = CAMERAS[name]
        camera = js.camera_preset(camera_name)
        catalog = js.load_catalog(depth)
        config = js.engine.default_config(name, camera=camera)
        module = js.algorithms.get(name)
        database = module.build_database(catalog, camera, config, progress=False)
        noise = js.NoiseConfig(position_sigma_px=args.position_sigma, magnitude_sigma=0.1)
        scenes = js.simulate(jax.random.key(args.seed), catalog, camera, noise, batch_size=args.scenes,
                             capacity=capacity)
        sets = {"nominal": scenes,
                "focal_off": camera_fit.rescale_scenes(scenes, camera, 1.0 + args.focal_error)}
        for label, batch in sets.items():
            result = module.identify(database, batch, config)
            out[f"{name}/{label}/ids"] = np.asarray(result.ids)
            out[f"{name}/{label}/ok"] = np.asarray(result.ok)
            out[f"{name}/{label}/attitude"] = np.asarray(result.attitude, np.float64)
            scale = np.full(batch.batch_size, np.nan) if result.focal_scale is None else result.focal_scale
            out[f"{name}/{label}/focal_scale"] = np.asarray(scale, np.float64)
            print(f"{name:6s} {label:9s} ok {int(np.sum(result.ok))}/{batch.batch_size}", flush=True)
    return out


def compare(before: Path, after: Path) -> int:
    """Print the scenes whose outcome differs; 0 when none does, else 1."""
    a, b = np.load(before), np.load(after)
    differ = 0
    for key in sorted(set(a.files) | set(b.files)):
        if key not in a.files or key not in b.files:
            print(f"{key}: only in {'after' if key in b.files else 'before'}")
            differ += 1
            continue
        x, y = a[key], b[key]
        if x.shape != y.shape:
            print(f"{key}: shape {x.shape} vs {y.shape}")
            differ += 1
            continue
        if key.endswith(("/ids", "/ok")):
            same = x == y
        else:
            same = np.isclose(x, y, atol=ATOL, rtol=0.0, equal_nan=True)
        bad = np.flatnonzero(~same.reshape(x.shape[0], -1).all(axis=1)) if x.ndim else np.array([])
        print(f"{key}: {'same' if not bad.size else f'{bad.size} scenes differ, e.g. {bad[:8].tolist()}'}")
        differ += bool(bad.size)
    return int(differ > 0)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.compare:
        return compare(*args.compare)
    out = record(args)
    args.out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out / "outcomes.npz", **out)
    print(f"wrote {args.out / 'outcomes.npz'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
