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
        start = time.perf_counter()
        try:
            return build(self, key, args, kwargs)
        finally:
            _build[self._name] += time.perf_counter() - start

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
        json.dumps({"build_s": _build, "run_s": _run, "calls": _calls})))


def _load(folder: Path) -> dict[str, collections.Counter]:
    total = {"build_s": collections.Counter(), "run_s": collections.Counter(), "calls": collections.Counter()}
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


if __name__ == "__main__":
    main(sys.argv[1:])
