"""Where the suite's time goes, per stored program: a pytest plugin and its report.

The suite builds its programs at a low XLA optimisation level (``tests/conftest.py``): fast to
compile, slow to run. Which kernels should be built at a higher level (``LOOP_BOUND_KERNELS``) is
decided by this profile: for every :func:`jstarid.runtime.program_store.stored_jit` program, the time
spent building it (tracing, lowering, compiling or loading) and the time its calls ran, summed over a
whole run — once as the suite builds them, once with every program at another level::

    PYTHONPATH=tests JSTARID_SUITE_PROFILE=/tmp/prof/base pytest -n 2 -q -p suite_profile
    PYTHONPATH=tests JSTARID_SUITE_PROFILE=/tmp/prof/level2 JSTARID_SUITE_PROFILE_LEVEL=2 \\
        pytest -n 2 -q -p suite_profile
    python tests/suite_profile.py /tmp/prof/base /tmp/prof/level2

The report also counts the programs each kernel compiled (rather than loaded from the store) over
the run, and compares the counts of two runs (two revisions, with this plugin in both).

Each call is waited for (``jax.block_until_ready``), so a profiled run takes longer than a plain
one; calls that bypass the store (inside a trace) count under their caller's program.
"""

from __future__ import annotations

import atexit
import collections
import json
import os
import sys
import time
from pathlib import Path

_build: collections.Counter = collections.Counter()
_run: collections.Counter = collections.Counter()
_calls: collections.Counter = collections.Counter()
_compiled: collections.Counter = collections.Counter()  # by kernel (the name before its statics)


def pytest_sessionstart(session):
    """Time every stored program (after the suite's conftest has set its compiler options)."""
    out = os.environ.get("JSTARID_SUITE_PROFILE")
    if not out:
        return
    import jax

    from jstarid.runtime import program_store as ps

    level = os.environ.get("JSTARID_SUITE_PROFILE_LEVEL")
    if level is not None:
        ps.set_compiler_options(lambda name: {"xla_backend_optimization_level": int(level)})
    build, call = ps.StoredFunction._load_or_compile, ps.StoredFunction.__call__

    def timed_build(self, key, args, kwargs):
        start, compiled = time.perf_counter(), ps.program_store_stats()["compiled"]
        try:
            return build(self, key, args, kwargs)
        finally:
            _build[self._name] += time.perf_counter() - start
            # a program compiled here, not loaded from the store (a kernel's programs differ by
            # their statics, devices and argument shapes)
            _compiled[self._name.split(" on devices ")[0]] += ps.program_store_stats()["compiled"] - compiled

    def timed_call(self, *args, **kwargs):
        start, built = time.perf_counter(), _build[self._name]
        result = jax.block_until_ready(call(self, *args, **kwargs))
        _run[self._name] += time.perf_counter() - start - (_build[self._name] - built)
        _calls[self._name] += 1
        return result

    ps.StoredFunction._load_or_compile, ps.StoredFunction.__call__ = timed_build, timed_call
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    atexit.register(lambda: (folder / f"{os.getpid()}.json").write_text(
        json.dumps({"build_s": _build, "run_s": _run, "calls": _calls, "compiled": _compiled})))


def _load(folder: Path) -> dict[str, collections.Counter]:
    total = {field: collections.Counter() for field in ("build_s", "run_s", "calls", "compiled")}
    for path in folder.glob("*.json"):
        for field, values in json.loads(path.read_text()).items():
            total[field].update(values)
    return total


def main(argv: list[str]) -> None:
    """Print each program's build and run seconds (and, given a second profile, the difference)."""
    base = _load(Path(argv[0]))
    other = _load(Path(argv[1])) if len(argv) > 1 else None
    for label, prof in (("profile", base), ("other", other)):
        if prof is not None:
            print(f"{label}, all programs: build {sum(prof['build_s'].values()):.1f} s, "
                  f"run {sum(prof['run_s'].values()):.1f} s")

    def saved(name):
        if other is None:
            return base["run_s"][name]
        return (base["run_s"][name] - other["run_s"][name]) - (other["build_s"][name] - base["build_s"][name])

    print("saved s  build s        run s          calls  program")
    for name in sorted(base["run_s"], key=saved, reverse=True)[:30]:
        b, r = base["build_s"][name], base["run_s"][name]
        if other is not None:
            b, r = f"{b:5.1f} → {other['build_s'][name]:5.1f}", f"{r:5.1f} → {other['run_s'][name]:5.1f}"
        else:
            b, r = f"{b:13.1f}", f"{r:13.1f}"
        print(f"{saved(name):7.1f}  {b}  {r}  {base['calls'][name]:5d}  {name[:100]}")

    counts = (base["compiled"], other["compiled"] if other is not None else None)
    print(f"\nprograms compiled (not loaded from the store): {sum(counts[0].values())}"
          + (f" → {sum(counts[1].values())}" if counts[1] is not None else "") + "; per kernel:")
    for kernel in sorted(counts[0], key=lambda k: -(counts[0][k] + (counts[1] or {}).get(k, 0)))[:20]:
        other_count = "" if counts[1] is None else f" → {counts[1][kernel]:4d}"
        print(f"{counts[0][kernel]:6d}{other_count}  {kernel}")


if __name__ == "__main__":
    main(sys.argv[1:])
