"""A narrow, deep camera: every algorithm with its defaults on a simulated twin of a real one.

The ``narrow_twin`` preset copies a real star tracker a user brought (1392×1040 px, 6.1° × 4.6°,
15.8″/px, 40–130 detections per frame down to V ≈ 10); ``jstarid.papers.narrow_field.NOISE`` copies
its frames (0.8 px centroid noise, 0.2 mag of brightness scatter, two false stars of V 6–10). The
catalog is Hipparcos to V 10 (complete to V ≈ 8: fainter real stars are missing from it, as they
would be from the database of any user of this catalog). Each algorithm runs through the sweep engine on
the same scenes, with its defaults for this camera (``Config.for_camera`` where it has one) and,
for comparison, the published defaults (``… (paper tolerances)`` rows).

Usage::

    python experiments/narrow_twin.py --quick                 # 200 scenes, MLV
    python experiments/narrow_twin.py --scenes 1000 --algorithms mlv,rpnet

Writes results/narrow_twin/{config.json, results.json, table.md, rates.png, scenes.npz}.
"""

from __future__ import annotations

import argparse

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms import base
from jstarid.papers import narrow_field as twin


def parse_args(argv=None):
    p = ex.parser(__doc__.splitlines()[0], out="results/narrow_twin", seed=35,
                  quick="200 scenes")
    p.add_argument("--scenes", type=int, default=1000, help="scenes (default 1000)")
    p.add_argument("--algorithms", default="mlv", help="comma-separated registry names")
    p.add_argument("--paper-rows", action=argparse.BooleanOptionalAction, default=True,
                   help="also run each algorithm with its published defaults")
    p.add_argument("--capacity", type=int, default=twin.CAPACITY, help="detections kept per scene")
    return p.parse_args(argv)


def entries(names, camera, paper_rows: bool) -> list[js.Entry]:
    """Each algorithm with its defaults for ``camera`` (and with the published ones)."""
    out = []
    for name in names:
        out.append(js.Entry(name, name, js.engine.default_config(name, camera=camera)))
        if paper_rows and base.declares(js.algorithms.get(name), "for_camera"):
            out.append(js.Entry(f"{name} (paper tolerances)", name, js.engine.default_config(name)))
    return out


def main(argv=None):
    args = parse_args(argv)
    js.use_cpu_cores()
    camera = js.camera_preset(twin.CAMERA)
    names = [n.strip() for n in args.algorithms.split(",") if n.strip()]
    fixed = {k: v for k, v in twin.NOISE.items() if k != "position_sigma_px"}
    result = js.sweep(entries(names, camera, args.paper_rows), camera,
                      axes={"position_sigma_px": [twin.NOISE["position_sigma_px"]]}, fixed=fixed,
                      catalog=js.load_catalog(twin.MAG_LIMIT),
                      scenes=200 if args.quick else args.scenes, seed=args.seed,
                      capacity=args.capacity, criterion="strict", progress=True)
    out = result.save(args.out, title="Narrow twin (1392×1040 px, 6.1° × 4.6°, V ≤ 10)")
    print(result.table())
    print(f"wrote {out}")
    return result


if __name__ == "__main__":
    main()
