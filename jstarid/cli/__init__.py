"""The ``jstarid`` command line: a thin shell over the public API.

Commands: ``demo`` (every algorithm on a position-noise sweep), ``sweep`` (any axis, camera or
parameter grid), ``reproduce`` (the papers' experiments), ``report`` (one markdown page of saved
results), ``identify`` (centroid files → names and attitude), ``score`` (labelled centroid files
→ names scored against the true stars), ``twin`` (labelled centroid files against their simulated
twin), ``solve`` (raw images → names and attitude), ``calibrate``
(frames → a fitted camera file), ``train`` (a
database or network built ahead of time), ``list`` and ``catalog``. Bad arguments print one line
and exit with status 2.
"""

from __future__ import annotations

import argparse
import sys

from jstarid.cli import build, calibrate, frames, info, papers, score, sweeps, twin

__all__ = ["build_parser", "main"]


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (``jstarid: error: …``) and exit status 2."""

    def error(self, message):
        raise _UsageError(f"{message} (see `{self.prog} --help`)")


class _UsageError(Exception):
    pass


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="jstarid", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    sweeps.add_commands(sub)
    papers.add_commands(sub)
    frames.add_commands(sub)
    score.add_commands(sub)
    twin.add_commands(sub)
    calibrate.add_commands(sub)
    build.add_commands(sub)
    info.add_commands(sub)
    return p


def main(argv=None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except _UsageError as err:
        print(f"jstarid: error: {err}", file=sys.stderr)
        return 2
    if argv is None:  # a command-line run (tests pass argv): keep compiled code for the next run
        from jstarid.compilation_cache import enable_compilation_cache
        from jstarid.runtime import use_cpu_cores
        enable_compilation_cache()  # every executable kept: a warm run loads them all
        use_cpu_cores()  # batches split over every core (one JAX device each)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as err:  # bad settings or files: a line, not a traceback
        print(f"jstarid: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jstarid: interrupted (databases and trainings resume where they stopped)",
              file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
