"""``jstarid train``: build an algorithm's database for a camera ahead of time (RpNet: train its
network), so the first identification does not wait for it."""

from __future__ import annotations

import time

from jstarid.cli.cameras import FRAME_CAMERA, add_camera_options, camera_from_args
from jstarid.cli.first_use import about
from jstarid.cli.frames import algorithm_settings


def add_commands(sub) -> None:
    t = sub.add_parser(
        "train", help="build an algorithm's database for a camera ahead of time (RpNet: train its "
                      "network); says first what it builds and about how long it takes",
        description="Build and cache what ALGORITHM needs for a camera: RpNet's networks (trained; "
                    "an interrupted training resumes), MLV's triangle database, SGM's neighbor "
                    "graphs. Later commands on the same camera and catalog load them.")
    t.add_argument("algorithm", help="registry name (`jstarid list`), e.g. rpnet")
    add_camera_options(t, default=FRAME_CAMERA)
    t.add_argument("--mag-limit", type=float, default=None,
                   help="catalog depth V (default: the camera's detection limit)")
    t.add_argument("--epoch", type=float, default=None,
                   help="Julian year the images will be taken at, as later given to `jstarid solve "
                        "--epoch` (a database is built for one catalog epoch; default J1991.25)")
    t.add_argument("--rpnet-network", choices=("quick", "table3"), default="quick",
                   help="RpNet: the quick network (minutes) or the paper's Table 3 schedule (hours)")
    t.add_argument("--set", nargs="*", default=[], metavar="[ALGORITHM.]FIELD=VALUE",
                   help="Config overrides, VALUE in JSON (e.g. n_boresights=50000)")
    t.set_defaults(func=run_train)


def run_train(args) -> int:
    import jstarid as js
    from jstarid.algorithms import base
    from jstarid.experiment import with_overrides

    module = js.algorithms.get(args.algorithm)
    camera = camera_from_args(args).pinhole()
    config = with_overrides(js.engine.default_config(args.algorithm, rpnet_network=args.rpnet_network,
                                                     camera=camera), algorithm_settings(args))
    catalog = js.load_catalog(camera.mag_limit if args.mag_limit is None else args.mag_limit,
                              epoch=args.epoch)
    js.engine.check_camera([js.Entry(args.algorithm, args.algorithm, config)], camera, catalog)
    planned = base.first_use(module, catalog, camera, config)
    # an algorithm that does not say what it builds (no first_use) is built: it may not be cached
    if planned is None and base.declares(module, "first_use"):
        print(f"{args.algorithm}: already built for camera {camera.name} (catalog V ≤ "
              f"{catalog.mag_limit:g}); nothing to do.", flush=True)
        return 0
    if planned is not None:
        print(f"Building {planned[0]} — {about(planned[1])} on 2 CPU cores.",
              flush=True)
    t0 = time.perf_counter()
    database = module.build_database(catalog, camera, config, progress=True)
    where = base.database_info(database).get("cache_path", "")
    print(f"{args.algorithm}: built for camera {camera.name} in {time.perf_counter() - t0:.0f} s"
          + (f" ({where})" if where else ""), flush=True)
    return 0
