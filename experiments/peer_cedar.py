"""The peer solver: cedar-solve (the maintained fork of ESA's tetra3) on exactly the engine's scenes.

cedar-solve pins numpy < 2 and Pillow < 9, so it runs in its own virtual environment, created once
under the jstarid cache (``peer-cedar-venv``, ≈ 2 min, from the package index). This script:

1. draws the sweep's scenes with :func:`jstarid.engine.simulate_levels` (the same scenes as
   ``jstarid demo`` for the same camera, levels, scene count and seed);
2. writes jstarid's catalog in the ``hip_main.dat`` format (the only name cedar's
   ``generate_database`` reads: '|'-separated, HIP in field 1, V in 5, RA and Dec in degrees in 8
   and 9; no proper motion, so cedar takes the positions as they are) and has cedar build its
   database for the camera's horizontal field and magnitude limit (cached);
3. exports the scenes' centroids (cedar's convention: (y, x), origin at the image's corner, so
   jstarid's pixel centres + 0.5), brightest first, and runs ``solve_from_centroids`` on each in the
   peer environment, once per ``match_max_error`` (its default 0.002, and 0.005: a fair tuned value
   at 2–3 px), timing each solve;
4. brings the matches back as an :class:`~jstarid.Identification` (matched centroid → detection,
   HIP → catalog row; a scene cedar does not solve is a failure) and scores it with
   :func:`jstarid.evaluate` like every other algorithm.

If the environment cannot be built the script says so and exits with status 0 (the test suite does
not depend on it). Usage::

    python experiments/peer_cedar.py                      # sgm2022, 0–3 px, 200 scenes per level
    python experiments/peer_cedar.py --scenes 20 --levels 0,2 --max-error 0.005
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import jstarid as js
from jstarid import experiment as ex

CEDAR = "cedar-solve==0.5.1"

# Runs inside the peer environment: build (or load) the database, solve every scene, save matches.
WORKER = r'''
import json, sys, time
import numpy as np
from tetra3 import Tetra3
job = json.loads(open(sys.argv[1]).read())
db_path = job["database"]
t3 = Tetra3(load_database=None)
try:
    t3.load_database(db_path)
except Exception:
    t0 = time.perf_counter()
    t3.generate_database(max_fov=job["fov_deg"], star_catalog=job["catalog"], save_as=db_path,
                         star_max_magnitude=job["mag_limit"], epoch_proper_motion=None)
    print(f"cedar database built in {time.perf_counter() - t0:.0f} s", flush=True)
    t3.load_database(db_path)  # cedar 0.5.1 sets the pattern count only when it loads a database
data = np.load(job["scenes"])
centroids, counts = data["centroids"], data["counts"]
out = {}
for err in job["max_errors"]:
    matched, ids, seconds, solved = [], [], [], []
    for s in range(len(counts)):
        c = centroids[s, : counts[s]]
        t0 = time.perf_counter()
        r = t3.solve_from_centroids(c, (job["height"], job["width"]), fov_estimate=job["fov_deg"],
                                    return_matches=True, match_max_error=err)
        seconds.append(time.perf_counter() - t0)
        ok = r.get("RA") is not None
        solved.append(ok)
        mc = np.asarray(r["matched_centroids"], float).reshape(-1, 2) if ok else np.zeros((0, 2))
        mi = np.asarray(r["matched_catID"], np.int64).reshape(-1) if ok else np.zeros((0,), np.int64)
        matched.append(mc.tolist())
        ids.append(mi.tolist())
    out[str(err)] = {"matched": matched, "ids": ids, "seconds": seconds, "solved": solved}
json.dump(out, open(job["result"], "w"))
'''


def peer_python(cache: Path) -> Path | None:
    """The peer environment's interpreter, created on first use; ``None`` (with the reason printed)
    when it cannot be built."""
    venv = cache / "peer-cedar-venv"
    python = venv / "bin" / "python"
    if python.exists():
        return python
    print(f"building the cedar-solve environment in {venv} (once, ≈ 2 min) …", flush=True)
    try:
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        subprocess.run([str(python), "-m", "pip", "install", "-q", CEDAR], check=True)
    except (subprocess.CalledProcessError, OSError) as err:
        print(f"the cedar-solve environment could not be built ({err}); no peer rows", flush=True)
        return None
    return python


def write_hip_main(catalog, path: Path) -> None:
    """jstarid's catalog as a ``hip_main.dat`` cedar reads (fields 1, 5, 8, 9; the rest blank)."""
    ra = np.degrees(np.asarray(catalog.ra, np.float64)) % 360.0
    dec = np.degrees(np.asarray(catalog.dec, np.float64))
    lines = []
    for hip, mag, a, d in zip(np.asarray(catalog.hip), np.asarray(catalog.mag), ra, dec, strict=True):
        fields = ["H", f"{int(hip):6d}", " ", " ", " ", f"{float(mag):5.2f}", " ", " ", f"{a:12.8f}",
                  f"{d:12.8f}", " ", " ", " ", " ", " "]
        lines.append("|".join(fields))
    path.write_text("\n".join(lines) + "\n")


def export_scenes(scenes, path: Path) -> None:
    """Each scene's valid detections, brightest first, as cedar's (y, x) from the image's corner."""
    xy, valid, mag = (np.asarray(a) for a in (scenes.xy, scenes.valid, scenes.mag))
    order = np.argsort(np.where(valid, mag, np.inf), axis=1, kind="stable")
    counts = valid.sum(axis=1)
    ordered = np.take_along_axis(xy, order[:, :, None], axis=1)
    centroids = ordered[:, :, ::-1] + 0.5
    np.savez(path, centroids=centroids, counts=counts, order=order)


def identification(scenes, catalog, solved: dict) -> tuple[js.Identification, np.ndarray]:
    """cedar's matches → ids per detection (matched centroid ↔ its detection, HIP ↔ catalog row),
    and the (B,) seconds per solve."""
    b, n = np.shape(scenes.valid)
    ids = np.full((b, n), -1, np.int32)
    ok = np.asarray(solved["solved"], bool)
    xy = np.asarray(scenes.xy) + 0.5  # cedar's pixel origin
    for s in np.flatnonzero(ok):
        matched = np.asarray(solved["matched"][s], float).reshape(-1, 2)  # (y, x)
        if matched.size == 0:
            continue
        gap = np.hypot(xy[s, None, :, 0] - matched[:, None, 1], xy[s, None, :, 1] - matched[:, None, 0])
        det = np.argmin(gap, axis=1)
        ids[s, det] = catalog.row_of_hip(np.asarray(solved["ids"][s], np.int64))
    return js.Identification(ids=ids, ok=ok, attitude=None), np.asarray(solved["seconds"])


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/peer_cedar")
    p.add_argument("--camera", default="sgm2022", help="camera preset or file (default sgm2022)")
    p.add_argument("--levels", default="0,1,2,3", help="position noise σ levels, px (default 0,1,2,3)")
    p.add_argument("--scenes", type=int, default=200, help="scenes per level (default 200)")
    p.add_argument("--max-error", default="0.002,0.005",
                   help="cedar's match_max_error values (default 0.002 = its default, and 0.005)")
    args = p.parse_args(argv)
    if args.set:
        p.error("--set changes jstarid algorithms' configs; the peer takes --max-error")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    cache = js.catalog.cache_dir()
    python = peer_python(cache)
    if python is None:
        return 0
    levels = [float(v) for v in args.levels.split(",")]
    errors = [float(v) for v in args.max_error.split(",")]
    drawn = js.engine.simulate_levels(args.camera, axes={"position_sigma_px": levels}, scenes=args.scenes,
                                      seed=args.seed)
    camera, catalog, scenes = drawn.camera, drawn.catalog, drawn.scenes
    fov_deg = math.degrees(2.0 * math.atan(camera.width / 2.0 / camera.f_px))
    args.out.mkdir(parents=True, exist_ok=True)
    hip_main = cache / f"peer-cedar-{catalog.fingerprint}" / "hip_main.dat"
    hip_main.parent.mkdir(parents=True, exist_ok=True)
    if not hip_main.exists():
        write_hip_main(catalog, hip_main)
    export_scenes(scenes, args.out / "centroids.npz")
    job = {"database": str(hip_main.parent / f"db-{camera.name}-{fov_deg:.4f}-{camera.mag_limit}.npz"),
           "catalog": str(hip_main), "fov_deg": fov_deg, "mag_limit": float(camera.mag_limit),
           "scenes": str(args.out / "centroids.npz"), "height": camera.height, "width": camera.width,
           "max_errors": errors, "result": str(args.out / "cedar.json")}
    (args.out / "job.json").write_text(json.dumps(job))
    worker = args.out / "worker.py"
    worker.write_text(WORKER)
    print(f"cedar-solve on {scenes.batch_size} scenes × {len(errors)} settings …", flush=True)
    t0 = time.perf_counter()
    subprocess.run([str(python), str(worker), str(args.out / "job.json")], check=True)
    print(f"done in {time.perf_counter() - t0:.0f} s", flush=True)
    solved = json.loads((args.out / "cedar.json").read_text())
    rows = ["| match_max_error | position σ (px) | scenes | identified | misid | failed | ms per solve "
            "(median) |", "|---|---|---|---|---|---|---|"]
    for err in errors:
        result, seconds = identification(scenes, catalog, solved[str(err)])
        for k, level in enumerate(levels):
            sel = np.flatnonzero(drawn.level_of == k)
            rep = js.evaluate(scenes[sel[0]:sel[-1] + 1], result[sel[0]:sel[-1] + 1], "strict")
            rows.append(f"| {err} | {level:g} | {sel.size} | {100 * rep['identification_rate']:.2f}% | "
                        f"{100 * rep['misid_rate']:.2f}% | {100 * rep['failure_rate']:.2f}% | "
                        f"{1e3 * np.median(seconds[sel]):.1f} |")
    table = "\n".join(rows)
    print(table)
    title = f"# cedar-solve on the engine's scenes ({camera.name}, seed {args.seed})"
    (args.out / "table.md").write_text(f"{title}\n\n{table}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
