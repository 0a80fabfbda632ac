"""What each algorithm costs to set up on cameras across the range a user may bring.

For the corners of the range 2°–40° field × 0.5k–4k px (and any ``--camera`` files), every
algorithm's database is built with its defaults for the camera, exactly as a user would:
``jstarid train ALGORITHM --camera FILE`` in a fresh process, on a cache that holds only the
catalogs (built first, not counted). Per build: the line the command prints first (what it builds,
how long it expects), wall time, the process's peak resident memory (``os.wait4``), the size of
what it wrote to the cache, or the one-line refusal of an algorithm that cannot work there.

Usage::

    python experiments/camera_range.py                       # every algorithm, the four corners
    python experiments/camera_range.py --algorithms mlv,sgm  # without RpNet's training (≈ 4 min each)

Writes results/camera_range/{config.json, results.json, table.md, cameras/*.toml}.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import jstarid as js
from jstarid import experiment as ex

# The corners of the range (issue: 2°–40° field, 0.5k–4k px). The detection limit follows the
# field so that a frame holds stars to identify: V 10 at 2° (≈ 10 catalog stars in a 2° × 1.5°
# frame; Hipparcos thins out past V 9), V 6 at 40° (≈ 150 in the frame).
CORNERS = (
    ("2deg_512", 512, 384, 2.0, 10.0),
    ("2deg_4096", 4096, 3072, 2.0, 10.0),
    ("40deg_512", 512, 512, 40.0, 6.0),
    ("40deg_4096", 4096, 4096, 40.0, 6.0),
)


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/camera_range")
    p.add_argument("--algorithms", default="mlv,sgm,rpnet", help="comma-separated registry names")
    p.add_argument("--camera", action="append", default=[], metavar="FILE",
                   help="a camera file to add to the corners (repeatable)")
    p.add_argument("--only", default=None, help="comma-separated corner names to keep (e.g. 2deg_512)")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds before a build is stopped")
    p.add_argument("--keep-cache", action="store_true",
                   help="keep what the builds wrote (OUT/cache), e.g. to identify with the networks")
    return p.parse_args(argv)


def cameras(args) -> list[tuple[str, js.Camera]]:
    """(label, camera) pairs: the corners (or those named by ``--only``) and the ``--camera`` files."""
    keep = None if args.only is None else {s.strip() for s in args.only.split(",")}
    out = [(name, js.Camera.from_fov(w, h, fov, mag_limit=mag, name=name))
           for name, w, h, fov, mag in CORNERS if keep is None or name in keep]
    out += [(Path(f).stem, js.load_camera(f)) for f in args.camera]
    return out


def cache_bytes(cache: Path) -> int:
    """Bytes of everything in the cache but the catalogs."""
    return sum(p.stat().st_size for p in cache.rglob("*")
               if p.is_file() and not p.name.startswith("catalog-"))


# Runs one command and prints its peak resident memory: the helper has that one child, so the
# children's maximum is the command's own peak.
_MEASURE = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
            "print('PEAK_KB', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, flush=True); "
            "sys.exit(r.returncode)")


def build(algorithm: str, camera_file: Path, cache: Path, timeout: float,
          overrides=()) -> dict:
    """``jstarid train ALGORITHM --camera FILE`` in a fresh process: outcome, time, memory, bytes."""
    before = cache_bytes(cache)
    env = {**os.environ, "JSTARID_CACHE": str(cache)}
    cmd = [sys.executable, "-c", _MEASURE, sys.executable, "-m", "jstarid.cli", "train", algorithm,
           "--camera", str(camera_file), *(["--set", *overrides] if overrides else [])]
    t0 = time.perf_counter()
    try:
        run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
        out, code = run.stdout + run.stderr, run.returncode
    except subprocess.TimeoutExpired as err:
        partial = err.stdout or b""
        partial = partial.decode(errors="replace") if isinstance(partial, bytes) else partial
        out, code = f"{partial}\nstopped after {timeout:.0f} s", None
    seconds = time.perf_counter() - t0
    peak = [ln.split()[1] for ln in out.splitlines() if ln.startswith("PEAK_KB")]
    lines = [ln.strip() for ln in out.replace("\r", "\n").splitlines()
             if ln.strip() and not ln.startswith("PEAK_KB") and "it/s]" not in ln and "s/it]" not in ln
             and "%|" not in ln]
    return {"returncode": code, "seconds": round(seconds, 1),
            "peak_mb": round(int(peak[0]) / 1024) if peak else None,
            "cache_mb": round((cache_bytes(cache) - before) / 2**20, 1),
            "first_line": lines[0] if lines else "", "last_line": lines[-1] if lines else ""}


def outcome(record: dict) -> str:
    """A table cell: built, or the refusal / error line."""
    if record["returncode"] == 0:
        return "built"
    return "refused: " + record["last_line"].replace("|", "/") if record["returncode"] == 2 else (
        "failed: " + record["last_line"].replace("|", "/"))


def main(argv=None):
    args = parse_args(argv)
    out = Path(args.out)
    (out / "cameras").mkdir(parents=True, exist_ok=True)
    cache = out / "cache"
    shutil.rmtree(cache, ignore_errors=True)
    cache.mkdir()
    for built in js.catalog.cache_dir().glob("catalog-*.npz"):  # catalogs the user has: not rebuilt
        shutil.copy2(built, cache / built.name)
    os.environ["JSTARID_CACHE"] = str(cache)
    names = [n.strip() for n in args.algorithms.split(",") if n.strip()]
    records = []
    for label, camera in cameras(args):
        js.load_catalog(camera.mag_limit)  # the catalog, built once and not counted
        path = js.save_camera(camera, out / "cameras" / f"{label}.toml")
        for name in names:
            print(f"{label} ({camera.width}×{camera.height} px, {camera.fov_x_deg:.1f}° × "
                  f"{camera.fov_y_deg:.1f}°, {camera.pixel_scale_arcsec:.1f}″/px, V ≤ "
                  f"{camera.mag_limit:g}): {name} …", flush=True)
            rec = {"camera": label, "algorithm": name, "width": camera.width, "height": camera.height,
                   "fov_x_deg": round(camera.fov_x_deg, 2), "mag_limit": camera.mag_limit,
                   **build(name, path, cache, args.timeout, args.set)}
            print(f"  {outcome(rec)}; {rec['seconds']} s, peak {rec['peak_mb']} MB, cache "
                  f"{rec['cache_mb']} MB", flush=True)
            records.append(rec)
    if not args.keep_cache:
        shutil.rmtree(cache, ignore_errors=True)
    rows = ["| camera | field | px | V ≤ | algorithm | outcome | what it said first | s | peak MB "
            "| cache MB |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        first = r["first_line"].replace("|", "/") if r["returncode"] == 0 else ""
        rows.append(f"| {r['camera']} | {r['fov_x_deg']}° | {r['width']}×{r['height']} | {r['mag_limit']:g} "
                    f"| {r['algorithm']} | {outcome(r)} | {first} | {r['seconds']} | {r['peak_mb']} "
                    f"| {r['cache_mb']} |")
    ex.write(out, config={"algorithms": names, "cameras": [c for _, c in cameras(args)],
                          "overrides": args.set},
             results={"records": records}, table="\n".join(rows))
    print("\n".join(rows))


if __name__ == "__main__":
    main()
