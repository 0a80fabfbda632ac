"""What empty padding scenes cost one SGM pass: the case for ``sgm.identify.PADDED_PASS_LIMIT``.

One pass of Algorithm 1 with names and verification (no extensions) over ``--scenes`` fresh scenes
of the ``sgm2022`` camera, padded with empty scenes to each size of ``--sizes`` (the padding SGM's
passes and retries get, ``runtime.coarse_size``). Each size runs twice and the second run is timed
(the first compiles). The identified share of the real scenes must not change with the padding.

Usage::

    python experiments/probes/sgm_padding_cost.py --scenes 100 --sizes 128 256 1024 8192
"""

from __future__ import annotations

import time

import jax
import numpy as np

import jstarid as js
from jstarid import experiment as ex
from jstarid.algorithms.sgm.identify import _algorithm1  # one pass, without the extensions
from jstarid.scene import pad_with_empty


def parse_args(argv=None):
    parser = ex.parser(__doc__.splitlines()[0], out="results/sgm_padding_cost", seed=5)
    parser.add_argument("--scenes", type=int, default=100, help="real scenes in every pass")
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 1024, 8192],
                        help="padded sizes of the pass (each ≥ --scenes)")
    parser.add_argument("--sigma", type=float, default=1.0, help="centroid noise σ (px)")
    args = parser.parse_args(argv)
    if min(args.sizes) < args.scenes:
        parser.error("every --sizes value must be at least --scenes")
    return args


def main(argv=None):
    args = parse_args(argv)
    js.use_cpu_cores()
    cam = js.load_camera("sgm2022")
    cat = js.load_catalog(cam.mag_limit)
    algo = js.algorithms.get("sgm")
    config = ex.with_overrides(js.engine.default_config("sgm", camera=cam), args.set)
    db = algo.build_database(cat, cam, config)
    noise = js.NoiseConfig(position_sigma_px=args.sigma, magnitude_sigma=0.1)
    scenes = js.simulate(jax.random.key(args.seed), cat, cam, noise, batch_size=args.scenes, capacity=64)
    rows = []
    for size in args.sizes:
        padded = pad_with_empty(scenes, size)
        for _ in range(2):  # the first run compiles the size's programs
            start = time.perf_counter()
            result, _ = _algorithm1(db, padded, config)
            jax.block_until_ready(result.ids)
            seconds = time.perf_counter() - start
        rows.append({"size": size, "seconds": seconds,
                     "identified": float(np.mean(np.asarray(result.ok)[:args.scenes]))})
        print(rows[-1], flush=True)
    base = rows[0]["seconds"]
    for row in rows:
        row["extra"] = row["seconds"] - base
    table = ex.markdown_table(rows, [
        ("size", "pass padded to", "{:,}"), ("seconds", "s (compiled)", "{:.2f}"),
        ("extra", f"s more than at {rows[0]['size']:,}", "{:+.2f}"),
        ("identified", f"identified of the {args.scenes}", "{:.1%}")],
        title=f"One SGM pass over {args.scenes} scenes padded with empty ones ({ex.machine()['devices']})")
    ex.write(args.out, config={"args": vars(args)}, results={"rows": rows}, table=table)
    print(table)


if __name__ == "__main__":
    main()
