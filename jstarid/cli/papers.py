"""``jstarid reproduce`` (the papers' experiments through the engine) and ``jstarid report``."""

from __future__ import annotations

import argparse
from pathlib import Path

REPORT_START = "<!-- jstarid report: start -->"
REPORT_END = "<!-- jstarid report: end -->"


def add_commands(sub) -> None:
    r = sub.add_parser(
        "reproduce", help="the papers' experiments through the sweep engine (--quick: minutes)",
        description="Run a paper's experiments (SGM Table 2; MLV Figs. 6–8; RpNet Figs. 8–11) on "
                    "the paper's camera, scenes and criterion, and save each under "
                    "<out>/<paper>/<experiment>/. Full size: 10,000 scenes per level (SGM: 5,070), "
                    "hours on 2 cores; --quick: 200 per level (SGM: 60), minutes.")
    r.add_argument("paper", choices=("sgm", "mlv", "rpnet", "all"), help="which paper")
    r.add_argument("--quick", action="store_true", help="a small run (200 scenes per level; SGM 60)")
    r.add_argument("--scenes", type=int, default=None, help="scenes per level (overrides --quick)")
    r.add_argument("--experiments", default=None,
                   help="comma-separated experiment names (e.g. fig6,fig8; default: all of them)")
    r.add_argument("--seed", type=int, default=0, help="PRNG seed (default 0)")
    r.add_argument("--baselines", action="store_true",
                   help="also run the classic baselines (pyramid, voting, grid) on the same scenes")
    r.add_argument("--rpnet-network", choices=("quick", "table3"), default="quick",
                   help="RpNet's network (default quick)")
    r.add_argument("--paper-algorithm", action="store_true",
                   help="the paper's algorithm alone (the settings Config.paper() changes: our "
                        "extensions off) instead of jstarid's default")
    r.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="settings of the paper's algorithm, VALUE in JSON (e.g. th1=2 eps_deg=0.3; "
                        "finishing.fit_focal=false)")
    r.add_argument("--out", type=Path, default=Path("results/reproduce"),
                   help="results directory (default results/reproduce)")
    r.add_argument("--quiet", action="store_true", help="no progress lines")
    r.set_defaults(func=run_reproduce)
    p = sub.add_parser(
        "report", help="one markdown page from saved results: each paper beside ours, and the "
                       "cross-algorithm sweeps",
        description="Collect the saved runs of `jstarid reproduce` and the sweeps of `jstarid "
                    "demo`/`sweep` into one markdown page (each with its command, commit and "
                    "machine). --update FILE rewrites the part of FILE between the report markers "
                    "(experiments/RESULTS.md is kept this way).")
    p.add_argument("--reproduce", type=Path, default=Path("results/reproduce"),
                   help="where `jstarid reproduce` saved (default results/reproduce)")
    p.add_argument("--sweeps", type=Path, nargs="*", default=[Path("results/demo")],
                   help="saved sweep directories (default results/demo)")
    p.add_argument("--benchmark", type=Path, default=Path("results/benchmark"),
                   help="where experiments/benchmark.py saved (default results/benchmark; "
                        "skipped when absent)")
    p.add_argument("--out", type=Path, default=Path("results/report.md"),
                   help="the page (default results/report.md)")
    p.add_argument("--update", type=Path, default=None,
                   help=f"also replace the text between {REPORT_START} and {REPORT_END} in this file")
    p.set_defaults(func=run_report)


def run_reproduce(args: argparse.Namespace) -> int:
    from jstarid.papers import reproduction as rp

    papers = rp.PAPERS if args.paper == "all" else (args.paper,)
    chosen = None if args.experiments is None else set(args.experiments.split(","))
    if args.scenes is not None and args.scenes < 1:
        raise ValueError("--scenes must be ≥ 1")
    todo = [e for p in papers for e in rp.experiments(p) if chosen is None or e.name in chosen]
    if not todo:
        raise ValueError(f"no experiment named {args.experiments!r} in {', '.join(papers)}")
    configs = [_config(exp, args) for exp in todo]  # a bad setting fails before anything runs
    for exp, config in zip(todo, configs, strict=True):
        print(f"{exp.paper} {exp.name}: {exp.label}, {len(exp.levels)} levels", flush=True)
        result = rp.run(exp, args.out, quick=args.quick, scenes=args.scenes, seed=args.seed,
                        progress=not args.quiet, rpnet_network=args.rpnet_network,
                        baselines=args.baselines, config=config)
        print(rp.comparison(exp, result.rows()), flush=True)
    print(f"saved under {args.out}/; `jstarid report` collects them into one page")
    return 0


def _config(experiment, args):
    """The paper's algorithm's config for ``experiment``: ``None`` (the engine's default for the
    paper's camera) unless ``--paper-algorithm`` or ``--set`` change it."""
    if not (args.paper_algorithm or args.set):
        return None
    import jstarid as js
    from jstarid.algorithms.base import paper_algorithm
    from jstarid.experiment import with_overrides

    config = js.engine.default_config(experiment.paper, rpnet_network=args.rpnet_network,
                                      camera=js.camera_preset(experiment.camera))
    if args.paper_algorithm:
        config = paper_algorithm(config)
    return with_overrides(config, args.set)


def report_text(reproduce: Path, sweeps: list[Path], *, benchmark: Path | None = None,
                title: bool = True) -> str:
    """The report page: the saved sweeps (every algorithm on identical scenes), each reproduced
    experiment beside its paper, then the saved benchmark (``experiments/benchmark.py``'s tables).
    ``title=False``: no ``#`` heading (a block of a page)."""
    import jstarid as js
    from jstarid.papers import reproduction as rp

    head = ["# jstarid report", ""] if title else []
    parts = head + ["Made by `jstarid report` from saved results; every table names the command, "
                    "commit and machine that produced it. Rates are % of scenes with 95 % Wilson "
                    "intervals.", ""]
    n_head = len(parts)
    for where in sweeps:
        if not (where / "scenes.npz").exists():
            continue
        result = js.load_sweep(where)
        parts += ["## Every algorithm on identical scenes", "", f"Saved in `{where}`.", "",
                  result.table().strip(), "", _provenance(where), ""]
        if title:  # the page sits beside results/; a block of a committed file links no figure
            parts += [f"![rates]({(where / 'rates.png').as_posix()})", ""]
    found = False
    for paper in rp.PAPERS:
        for exp in rp.experiments(paper):
            where = reproduce / paper / exp.name
            if not (where / "scenes.npz").exists():
                continue
            if not found:
                parts += ["## The papers' experiments", ""]
                found = True
            result = js.load_sweep(where)
            parts += [rp.comparison(exp, result.rows()), _provenance(where), ""]
    if benchmark is not None and (benchmark / "table.md").exists():
        parts += ["## Throughput", "", f"Saved in `{benchmark}`.", "",
                  (benchmark / "table.md").read_text().strip(), "", _provenance(benchmark), ""]
    if len(parts) == n_head:
        raise FileNotFoundError(f"no saved results under {reproduce}, {', '.join(map(str, sweeps))} or "
                                f"{benchmark}; run `jstarid demo`, `jstarid reproduce … --quick` or "
                                "`python experiments/benchmark.py` first")
    return "\n".join(parts).rstrip() + "\n"


def _provenance(where: Path) -> str:
    from jstarid import experiment

    config, _ = experiment.load(where)
    p = config.get("provenance", {})
    m = p.get("machine", {})
    return (f"`{p.get('command', '?')}` — commit {p.get('commit', '?')}, {p.get('date', '?')}; "
            f"{m.get('cpu_count', '?')} CPU cores, {m.get('devices', '?')} ({m.get('backend', '?')}).")


def run_report(args: argparse.Namespace) -> int:
    text = report_text(args.reproduce, args.sweeps, benchmark=args.benchmark)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out}")
    if args.update is not None:
        old = args.update.read_text() if args.update.exists() else ""
        text = report_text(args.reproduce, args.sweeps, benchmark=args.benchmark, title=False)
        block = f"{REPORT_START}\n{text}{REPORT_END}"
        if REPORT_START in old and REPORT_END in old:
            head, rest = old.split(REPORT_START, 1)
            new = head + block + rest.split(REPORT_END, 1)[1]
        else:
            new = old.rstrip() + ("\n\n" if old else "") + block + "\n"
        args.update.write_text(new)
        print(f"updated {args.update}")
    return 0
