"""``jstarid twin``: a labelled set of real detections against its simulated twin (:mod:`jstarid.twin`)."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from jstarid.cli.cameras import FRAME_CAMERA, add_camera_options, camera_from_args
from jstarid.cli.centroid_input import add_centroid_file_options, combine, read_labelled_files
from jstarid.cli.first_use import about
from jstarid.twin import SKIES


def add_commands(sub) -> None:
    p = sub.add_parser(
        "twin", help="labelled centroid files → a detection model fitted to them, their simulated "
                     "twin, every algorithm on both: real vs twin rates with 95 %% intervals",
        description="Fit the camera's detection model (completeness, magnitude and position scatter "
                    "by magnitude, clutter) to labelled centroid files (a true Hipparcos number per "
                    "detection, −1 for a false star, and magnitudes or fluxes; each scene's attitude "
                    "is fitted to its labelled stars), simulate the set's twin from that model, run "
                    "every algorithm on both through the sweep engine and print real and twin "
                    "identification and mis-identification rates side by side (strict criterion, "
                    "95 % Wilson intervals; a twin rate agrees when it lies inside the real "
                    "interval). Writes --out: twin.json (the fitted model, the rows) and the sweep's "
                    "files (level twin=0: the labelled set, twin=1: its twin).")
    p.add_argument("files", nargs="+", type=Path, help="labelled centroid files (.csv, .tsv, .txt, .json)")
    add_camera_options(p, default=FRAME_CAMERA)
    add_centroid_file_options(p)
    p.add_argument("--algorithms", default=None,
                   help="comma-separated registry names (default: the three papers' algorithms)")
    p.add_argument("--scenes", type=int, default=1000, help="twin scenes (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed of the twin (default 0)")
    p.add_argument("--sky", choices=SKIES, default="real",
                   help="the twin's pointings: real (boresight near a labelled scene's, roll at "
                        "random; default), exact (each labelled scene's own attitude: the twin's "
                        "rate scene by scene in twin.json) or random (anywhere: what a sweep draws)")
    p.add_argument("--capacity", type=int, default=64,
                   help="brightest detections the algorithms use per scene, real and twin (default 64)")
    p.add_argument("--mag-limit", type=float, default=None,
                   help="identification catalog depth V (default: the camera's detection limit)")
    p.add_argument("--epoch", type=float, default=None,
                   help="Julian year of the observations, for proper motion (default J1991.25)")
    p.add_argument("--rpnet-network", choices=("quick", "table3"), default="quick",
                   help="RpNet's network, trained for the camera on first use (default quick)")
    p.add_argument("--train-on-fit", action="store_true",
                   help="RpNet trains its network on the detection model fitted to the labelled set "
                        "(a network of its own for this set; default: its network for the camera)")
    p.add_argument("--set", nargs="*", default=[], metavar="[ALGORITHM.]FIELD=VALUE",
                   help="algorithm Config overrides, VALUE in JSON (as in `jstarid sweep`)")
    p.add_argument("--out", type=Path, default=Path("results/twin"),
                   help="results directory (default results/twin)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run_twin)


def run_twin(args) -> int:
    import dataclasses

    import jstarid as js
    from jstarid.cli.sweeps import _settings, _with_overrides
    from jstarid.serialization import to_json
    from jstarid.twin import twin_check

    camera = camera_from_args(args)  # a bad camera fails before any file is read
    if args.scenes < 1 or args.capacity < 1:
        raise ValueError("--scenes and --capacity must be ≥ 1")
    sets = read_labelled_files(args)
    found = combine(sets)
    names = args.algorithms or ",".join(js.algorithms.seed_names())
    entries = _with_overrides(js.engine.entries(names, rpnet_network=args.rpnet_network, camera=camera),
                              _settings(args.set, "--set"))
    catalog = js.load_catalog(camera.mag_limit if args.mag_limit is None else args.mag_limit,
                              epoch=args.epoch)
    js.engine.check_camera(entries, camera, catalog)
    steps = js.engine.plan(entries, catalog, camera, rpnet_network=args.rpnet_network)
    print(f"jstarid twin: {len(found)} labelled scenes, {args.scenes} twin scenes, "
          f"{', '.join(e.label for e in entries)} on camera {camera.name}.", flush=True)
    if steps:
        print(f"First use builds: {'; '.join(t for t, _ in steps)} — "
              f"{about(sum(s for _, s in steps) + 60)} in all on 2 CPU cores, once.", flush=True)
    t0 = time.perf_counter()
    check = twin_check(found, camera, entries, scenes=args.scenes, seed=args.seed,
                       capacity=args.capacity, epoch=args.epoch, catalog=catalog, sky=args.sky,
                       rpnet_network=args.rpnet_network, train_on_fit=args.train_on_fit,
                       progress=not args.quiet)
    out = check.result.save(args.out, title="jstarid twin (level twin=0: the labelled set, "
                                             "twin=1: its twin)", figure=False)
    fit = check.labelled.fit
    (out / "twin.json").write_text(json.dumps(to_json({
        "files": [str(p) for p in args.files], "camera": js.camera_files.camera_to_dict(camera),
        "model": dataclasses.asdict(fit.model), "noise": dataclasses.asdict(fit.noise()),
        "magnitude_offset": fit.magnitude_offset, "stars": fit.stars, "detected": fit.detected,
        "depth_mag": check.labelled.depth_mag, "scenes_fitted": int(check.labelled.solved.sum()),
        "detections_per_scene": check.detections, "sky": args.sky, "rows": check.rows(),
        "scenes": check.scene_rows()}), indent=1))
    (out / "table.md").write_text(check.table())
    print(check.table(), flush=True)
    print(f"wrote {out}/ (twin.json, table.md, results.json, config.json, scenes.npz) in "
          f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return 0
