"""``jstarid demo`` and ``jstarid sweep``: the sweep engine from the command line."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from jstarid.algorithms import BASELINES
from jstarid.cli.cameras import add_camera_options, camera_from_args
from jstarid.cli.first_use import about
from jstarid.peers import PEERS

DEMO_LEVELS = "0,1,2,3"


def add_commands(sub) -> None:
    d = sub.add_parser(
        "demo", help="every algorithm on a position-noise sweep of the same scenes: table, figure",
        description="Run every registered algorithm (the oracle and the baselines aside) on the same "
                    "simulated scenes "
                    "at 0–3 px of centroid noise; print the table and write results/demo/ "
                    "(config.json, results.json, table.md, rates.png, scenes.npz). The first run "
                    "builds databases, trains RpNet's quick network and compiles (5–13 min on 2 "
                    "cores, by host); later runs load them and take about half a minute.")
    _scene_options(d, out="results/demo", scenes=200, levels=DEMO_LEVELS)
    d.set_defaults(func=run_demo)
    s = sub.add_parser(
        "sweep", help="algorithms × one or two noise axes (× a parameter grid) on any camera",
        description="Like demo, for any noise axis, camera and algorithm settings. Example: "
                    "jstarid sweep --algorithms mlv --camera mlv2021 --axis magnitude --levels "
                    "0,0.35,0.7 --fixed position_sigma_px=1 --grid th1=0,2 eps_deg=0.1,0.2")
    _scene_options(s, out="results/sweep", scenes=200, levels=DEMO_LEVELS)
    s.add_argument("--grid", nargs="*", default=[], metavar="FIELD=V1,V2",
                   help="a parameter grid of the one algorithm in --algorithms: every combination "
                        "of these Config values is a row (run as one batch where the algorithm "
                        "allows), e.g. th1=0,1,2 eps_deg=0.1,0.2")
    s.set_defaults(func=run_sweep)


def _scene_options(p, *, out: str, scenes: int, levels: str) -> None:
    p.add_argument("--algorithms", default=None,
                   help="comma-separated registry names (default: every registered algorithm "
                        "but the oracle and the baselines; `jstarid list` shows them)")
    p.add_argument("--baselines", action="store_true",
                   help="also run the classic baselines (" + ", ".join(BASELINES) + ") on the same scenes")
    p.add_argument("--peer", choices=sorted(PEERS), action="append", default=[],
                   help="also run a peer solver on the same scenes, in its own environment built on "
                        "first use (cedar: cedar-solve/tetra3, ≈ 2 min once; a row at its default and "
                        "one at a tuned match_max_error); if it cannot be built "
                        "the run says so and goes on without it")
    add_camera_options(p, default="sgm2022")
    p.add_argument("--mag-limit", type=float, default=None,
                   help="catalog depth V (default: the camera's detection limit)")
    p.add_argument("--axis", default="position",
                   help="noise axis: position (px), magnitude (mag), missing, false (stars per "
                        "scene), false-ratio, false-per-true (false stars per true star) or "
                        "false-mean (Poisson mean); clutter as bright as stars: --fixed "
                        "false_mag_slope=0.47; with --pixels or --detection sensor also a sensor "
                        "axis: exposure (s), "
                        "read-noise (e⁻), defocus (px), smear (px), psf_sigma_px, sky_e_per_s, "
                        "dark_e_per_s, hot_pixels")
    p.add_argument("--levels", default=levels, help=f"comma-separated levels of --axis (default {levels})")
    p.add_argument("--axis2", default=None, help="a second noise axis (every combination is a level)")
    p.add_argument("--levels2", default=None, help="levels of --axis2")
    p.add_argument("--fixed", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="other NoiseConfig settings for every scene, e.g. magnitude_sigma=0.3")
    g = p.add_argument_group("from pixels (render → extract centroids → identify)")
    g.add_argument("--pixels", action="store_true",
                   help="render every scene into a frame (js.render, the camera's default sensor) and "
                        "identify the centroids extracted from it, instead of simulated centroids")
    g.add_argument("--detection", choices=("sensor",), default=None,
                   help="draw centroids from the sensor's detection model (js.DetectionModel.from_sensor: "
                        "noise, completeness and bias by magnitude, blends) instead of the papers' cut "
                        "at the camera's limit; sensor axes then run without rendering")
    g.add_argument("--sensor", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="SensorConfig settings with --pixels or --detection sensor, e.g. read_noise_e=20 "
                        "exposure_s=0.05")
    g.add_argument("--centroid", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="CentroidConfig settings with --pixels or --detection sensor, e.g. "
                        "threshold_sigma=4 window_px=2")
    p.add_argument("--scenes", type=int, default=scenes, help=f"scenes per level (default {scenes})")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed of the scenes (default 0)")
    p.add_argument("--capacity", type=int, default=96,
                   help="detections kept per scene, brightest first (default 96)")
    p.add_argument("--boresight", choices=("random", "stars"), default="random",
                   help="random attitudes, or the boresight on a random catalog star (default random)")
    p.add_argument("--criterion", choices=("strict", "mlv", "sgm", "rpnet"), default="strict",
                   help="what counts as identified (docs/conventions.md §5; default strict: ≥ 3 "
                        "correct, none wrong)")
    p.add_argument("--stars", default=None, metavar="LO-HI",
                   help="also tabulate only the scenes with LO to HI true stars among their "
                        "detections (e.g. 5-6: sparse frames; a single number: exactly that many); "
                        "printed after the full table and written to table_stars.md")
    p.add_argument("--chunk-size", type=int, default=256,
                   help="most scenes per identify call (bounds memory; default 256)")
    p.add_argument("--rpnet-network", choices=("quick", "table3"), default="quick",
                   help="RpNet's network, trained for the camera on first use: quick (≈ 5 min on "
                        "2 cores) or table3 (the paper's schedule, ≈ 2 h)")
    p.add_argument("--set", nargs="*", default=[], metavar="[ALGORITHM.]FIELD=VALUE",
                   help="algorithm Config overrides, VALUE in JSON (e.g. mlv.n_stars=12 "
                        "sgm.max_error_deg=0.2); without ALGORITHM. it applies to every algorithm "
                        "that has the field")
    p.add_argument("--out", type=Path, default=Path(out), help=f"results directory (default {out})")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    g = p.add_argument_group("several processes (jax.distributed; docs/scale_out.md)")
    g.add_argument("--distributed", action="store_true",
                   help="join a multi-process run; on SLURM / Open MPI / Cloud TPU nothing else is "
                        "needed, elsewhere add the three options below")
    g.add_argument("--coordinator", default=None, help="HOST:PORT of process 0")
    g.add_argument("--num-processes", type=int, default=None, help="how many processes take part")
    g.add_argument("--process-id", type=int, default=None, help="this process's index (0 …)")


def _floats(text: str, what: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"{what} must be comma-separated numbers, got {text!r}") from None
    if not values:
        raise ValueError(f"{what} has no values")
    return values


def _settings(items, what: str) -> dict:
    out = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"{what} {item!r} is not FIELD=VALUE")
        name, value = item.split("=", 1)
        out[name.strip()] = value
    return out


def _run(args, *, title: str, grid: dict | None = None) -> int:
    import jax

    import jstarid as js

    if args.distributed or args.coordinator is not None:
        js.engine.initialize(args.coordinator, args.num_processes, args.process_id)
    if jax.process_index() != 0:  # every process computes its share; process 0 reports and writes
        args.quiet = True

    camera = camera_from_args(args)
    names = args.algorithms or ",".join(js.algorithms.seed_names())
    algorithms = [n.strip() for n in names.split(",") if n.strip()]
    if args.baselines:
        algorithms += [n for n in js.algorithms.BASELINES if n not in algorithms]
    # a peer named among the algorithms (`--algorithms mlv,cedar`) is run as --peer runs it
    named_peers = [n for n in algorithms if n in PEERS]
    algorithms = [n for n in algorithms if n not in PEERS]
    peers = [p for p in _available_peers([*args.peer, *named_peers]) if p not in algorithms]
    for name in algorithms:
        js.algorithms.get(name)  # unknown names fail before anything is built
    axes = _axes_of(args)
    fixed = {k: float(v) for k, v in _settings(args.fixed, "--fixed").items()}
    overrides = _settings(args.set, "--set")
    chosen = _with_overrides(js.engine.entries(algorithms + peers, rpnet_network=args.rpnet_network,
                                               camera=camera), overrides)
    algorithms, peers = chosen[:len(algorithms)], chosen[len(algorithms):]
    if grid:
        if len(algorithms) != 1:
            raise ValueError("--grid needs exactly one algorithm in --algorithms")
        algorithms = js.grid(algorithms[0].algorithm, algorithms[0].config, **grid)
    algorithms += [e for peer in peers for e in _reported(peer, overrides)]
    js.engine.level_noise(js.engine.level_grid(axes), 1, fixed)  # bad levels fail here, not later
    sensor, centroid = _pixel_options(args, camera)
    if args.scenes < 1 or args.chunk_size < 1 or args.capacity < 1:
        raise ValueError("--scenes, --chunk-size and --capacity must be ≥ 1")
    stars = None if args.stars is None else star_range(args.stars)
    catalog = js.load_catalog(camera.mag_limit if args.mag_limit is None else args.mag_limit)
    js.engine.check_camera(algorithms, camera, catalog)  # before anything is built
    store = js.runtime.program_store
    if store.program_store_dir() is not None:  # programs of this jstarid, JAX and device setup
        compiled_before = store.programs_stored() > 0
    else:
        cache = Path(jax.config.jax_compilation_cache_dir or js.catalog.cache_dir() / "xla")
        compiled_before = cache.exists() and any(cache.iterdir())
    steps = js.engine.plan(algorithms, catalog, camera, rpnet_network=args.rpnet_network,
                           compiled_before=compiled_before)
    n_levels = len(js.engine.level_grid(axes))
    label = ", ".join(sorted({e.algorithm for e in js.engine.entries(
        algorithms, rpnet_network=args.rpnet_network)}))
    if jax.process_index() == 0:
        print(f"jstarid {title}: {label} on {n_levels} levels × {args.scenes} scenes "
              f"({', '.join(axes)}; camera {camera.name}).", flush=True)
        if steps:
            total = sum(s for _, s in steps) + 30  # + simulating, identifying, writing
            print(f"First use builds: {'; '.join(t for t, _ in steps)} — {about(total)} in "
                  "all on 2 CPU cores, once; later runs reuse them.", flush=True)
        else:
            print("Everything it needs is built and cached.", flush=True)
    t0 = time.perf_counter()
    result = js.sweep(algorithms, camera, axes=axes, fixed=fixed, scenes=args.scenes, seed=args.seed,
                      catalog=catalog, capacity=args.capacity, boresight=args.boresight,
                      criterion=args.criterion, chunk_size=args.chunk_size,
                      rpnet_network=args.rpnet_network, progress=not args.quiet,
                      pixels=args.pixels, sensor=sensor, centroid=centroid, detection=args.detection)
    if jax.process_index() != 0:
        return 0
    out = result.save(args.out, title=f"jstarid {title}")
    print(result.table(), flush=True)
    written = "table.md, rates.png, results.json, config.json, scenes.npz"
    if stars is not None:
        sparse = result.table(f"jstarid {title}: scenes with {stars[0]}–{stars[1]} true stars", stars=stars)
        (out / "table_stars.md").write_text(sparse)
        print(sparse, flush=True)
        written += ", table_stars.md"
    print(f"wrote {out}/ ({written}) in {time.perf_counter() - t0:.0f} s", flush=True)
    return 0


def star_range(text: str) -> tuple[int, int]:
    """``"5-6"`` → (5, 6), ``"5"`` → (5, 5): the --stars option's range of true stars per scene.

    Raises:
        ValueError: not one or two integers with 0 ≤ LO ≤ HI.
    """
    parts = text.split("-")
    try:
        lo, hi = (int(parts[0]), int(parts[-1])) if len(parts) <= 2 else (None, None)
    except ValueError:
        lo = hi = None
    if lo is None or not 0 <= lo <= hi:
        raise ValueError(f"--stars takes LO-HI with 0 ≤ LO ≤ HI (or one number), got {text!r}")
    return lo, hi


def _pixel_options(args, camera):
    """``(sensor, centroid)`` of ``--pixels`` or ``--detection sensor`` from ``--sensor`` /
    ``--centroid`` (``None``, ``None`` without either); bad fields or values fail here, before anything
    is built."""
    import jstarid as js
    from jstarid.experiment import with_overrides

    if args.pixels and args.detection:
        raise ValueError("--pixels detects in the pixels: drop --detection")
    if not (args.pixels or args.detection):
        if args.sensor or args.centroid:
            raise ValueError("--sensor and --centroid need --pixels or --detection sensor")
        return None, None
    return (with_overrides(js.sensor_for_camera(camera), args.sensor),
            with_overrides(js.CentroidConfig(), args.centroid))


def _axes_of(args) -> dict:
    import jstarid as js

    axes = {js.engine.axis_field(args.axis): _floats(args.levels, "--levels")}
    if args.axis2:
        axes[js.engine.axis_field(args.axis2)] = _floats(args.levels2 or "", "--levels2")
    return axes


def _available_peers(peers) -> list[str]:
    """The peers of ``--peer`` registered, less those whose environment cannot be built (the run
    says so and goes on without them)."""
    import jstarid as js

    out = []
    for peer in dict.fromkeys(peers):
        js.algorithms.register(peer, PEERS[peer])
        if js.algorithms.get(peer).environment() is None:
            print(f"{peer}: its environment is not available; going on without it", flush=True)
        else:
            out.append(peer)
    return out


def _reported(entry, overrides: dict) -> list:
    """A peer's entry as one row per setting it is reported at: the grid of its module's
    ``REPORTED`` fields (cedar: its default and a tuned ``match_max_error``) that ``--set`` leaves
    alone."""
    import jstarid as js
    from jstarid.algorithms import base

    set_fields = {path.partition(".")[0] for target, path in map(_set_target, overrides)
                  if target in ("", entry.algorithm)}
    reported = {k: v for k, v in base.reported(js.algorithms.get(entry.algorithm)).items()
                if k not in set_fields}
    return js.grid(entry.algorithm, entry.config, label=entry.label, **reported) if reported else [entry]


def _with_overrides(entries, overrides: dict):
    """Entries with ``--set`` applied (``algorithm.field`` or ``field`` for every entry having it)."""
    import dataclasses

    from jstarid.experiment import with_overrides

    out = list(entries)
    for key, text in overrides.items():
        target, path = _set_target(key)
        field = path.partition(".")[0]
        hit = False
        for k, e in enumerate(out):
            names = {f.name for f in dataclasses.fields(e.config)}
            if (target and target != e.algorithm) or field not in names:
                continue
            out[k] = e._replace(config=with_overrides(e.config, [f"{path}={text}"]))
            hit = True
        if not hit:
            raise ValueError(f"--set {key}: no algorithm in the run has a field {field!r}")
    return out


def _set_target(key: str) -> tuple[str, str]:
    """``(algorithm, field path)`` of a ``--set`` key: ``mlv.finishing.fit_focal`` →
    ``("mlv", "finishing.fit_focal")``; a key whose first part names no algorithm applies to every
    entry having that field (``finishing.fit_focal`` → ``("", "finishing.fit_focal")``)."""
    import jstarid as js

    head, _, rest = key.partition(".")
    return (head, rest) if rest and head in js.algorithms.names() else ("", key)


def run_demo(args: argparse.Namespace) -> int:
    return _run(args, title="demo")


def run_sweep(args: argparse.Namespace) -> int:
    grid = {}
    for name, text in _settings(args.grid, "--grid").items():
        values = []
        for v in text.split(","):
            try:
                values.append(json.loads(v))
            except json.JSONDecodeError:
                raise ValueError(f"--grid {name}: {v!r} is not a JSON value") from None
        grid[name] = values
    return _run(args, title="sweep", grid=grid or None)
