"""``jstarid list`` and ``jstarid catalog``."""

from __future__ import annotations

import numpy as np


def add_commands(sub) -> None:
    ls = sub.add_parser("list", help="registered algorithms and camera presets")
    ls.set_defaults(func=run_list)
    c = sub.add_parser("catalog", help="catalog statistics")
    c.add_argument("--mag-limit", type=float, default=6.0, help="catalog depth V (default 6.0)")
    c.add_argument("--double-sep", type=float, default=0.05,
                   help="close-pair separation (deg; default 0.05)")
    c.add_argument("--double-mode", choices=("drop", "merge", "keep"), default="drop",
                   help="what to do with close pairs (default drop: keep the brighter)")
    c.set_defaults(func=run_catalog)


def run_list(args) -> int:
    import jstarid as js

    print("algorithms:", ", ".join(js.algorithms.seed_names()))
    print("baselines: ", ", ".join(js.algorithms.BASELINES), "(demo and sweep: --baselines)")
    listed = js.algorithms.seed_names() + js.algorithms.BASELINES
    others = [n for n in js.algorithms.names() if n not in listed]
    print("others:    ", ", ".join(others), "(the oracle returns the truth: a test reference)")
    print("cameras:   ", ", ".join(js.preset_names()))
    return 0


def run_catalog(args) -> int:
    import jstarid as js

    cat = js.load_catalog(args.mag_limit, double_sep_deg=args.double_sep,
                          double_mode=args.double_mode)
    print(cat)
    # bins of 1 mag centred on integers, the last one reaching past the limit (every star counted)
    edges = np.arange(-1.5, args.mag_limit + 1.0, 1.0)
    hist, edges = np.histogram(cat.mag, bins=edges)
    for h, e in zip(hist, edges, strict=False):
        print(f"  V {e:5.1f} – {e + 1:4.1f}: {h}")
    return 0
