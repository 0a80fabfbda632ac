"""Shared fixtures. Several host devices are forced so sharding code paths are exercised on CPU."""

import os
import shutil
import subprocess
import sys
import uuid

# The suite is compile-bound (most tests compile their kernels for a few tiny batches), so XLA's
# backend spends less time optimising the code it generates: slower to run, much faster to build
# (the RpNet and SGM tests: 275 s → 205 s on 2 cores). Float semantics are LLVM's at any level.
SUITE_XLA_FLAGS = "--xla_backend_optimization_level=0"
# XLA's classic fusion emitter builds faster still (the whole suite on 2 cores: experiments/RESULTS.md,
# "The default test suite"), but the code it emits may round a reduction differently at another batch
# shape. The tests that hold a result equal to the last bits across batch shapes, chunks or devices
# (which the default emitter, the one users' programs are built with, gives) are marked
# ``production_numerics`` and run in a child process under the default emitter
# (:func:`pytest_pyfunc_call`). A jaxlib that no longer knows the flag aborts at start-up on it, so
# it is tried in a throwaway process first and left out where refused.
CLASSIC_EMITTER = "--xla_cpu_use_fusion_emitters=false"


def _xla_accepts(flag: str) -> bool:
    probe = subprocess.run([sys.executable, "-c", "import jax; jax.devices('cpu')"],
                           env=dict(os.environ, XLA_FLAGS=flag), capture_output=True)
    return probe.returncode == 0


# The controller sets the flags once; the xdist workers and the processes tests start inherit them
# (a user's own XLA_FLAGS are kept as they are).
if "XLA_FLAGS" not in os.environ:
    os.environ["XLA_FLAGS"] = " ".join(
        ["--xla_force_host_platform_device_count=4", SUITE_XLA_FLAGS]
        + [CLASSIC_EMITTER] * _xla_accepts(CLASSIC_EMITTER))
SUITE_USES_CLASSIC_EMITTER = CLASSIC_EMITTER in os.environ["XLA_FLAGS"].split()
# set in a child process that runs one production_numerics test (it keeps the run's program store)
CHILD_RUN = "JSTARID_SUITE_CHILD"

import jax  # noqa: E402
import pytest  # noqa: E402

import jstarid as js  # noqa: E402

# Broadcasting between arrays of different rank must be written out (``a[:, None]``), as in diffrax's
# and optax's suites: an implicit rank promotion is usually a shape bug.
jax.config.update("jax_numpy_rank_promotion", "raise")

# No persistent XLA cache in the suite (nor in the CLI calls and scripts it starts): JAX's cache
# code segfaulted in the workers, reading and writing entries, three times in three runs, with one
# shared directory and with one per worker. Each process keeps its compiled kernels in memory.
os.environ["JSTARID_COMPILATION_CACHE"] = "off"

# jstarid's own program store (serialized executables, written atomically) is shared by the xdist
# workers of one run: a kernel one worker compiled, the other loads instead of compiling it again
# (the suite is compile-bound, and both workers meet most kernels). One directory per run (xdist's
# run id), under the jstarid cache; a run without xdist keeps its programs in memory only.
# The controller names the run before it starts the workers, which inherit its environment.
SUITE_PROGRAMS = js.catalog.cache_dir() / "suite-programs" / os.environ.setdefault(
    "JSTARID_SUITE_RUN", uuid.uuid4().hex)
js.runtime.program_store.enable_program_store(SUITE_PROGRAMS)

# The kernels whose run time, not their compilation, dominates the tests that call them (loops over
# triangles and candidate stars) run several times slower at SUITE_XLA_FLAGS' optimisation level:
# the store builds them at level 2. Chosen by tests/suite_profile.py (build and run time of every
# stored program, summed over a run at each level; experiments/RESULTS.md, "The default test suite").
# The simulator stays at the suite's level: scenes drawn inside a caller's jit must equal those its
# own program draws.
LOOP_BOUND_KERNELS = ("jstarid.hypotheses._search_chunk", "jstarid.completion._extend",
                      "jstarid.algorithms.pyramid.identify._identify_chunk",
                      "jstarid.algorithms.voting.identify._identify_chunk",
                      "jstarid.algorithms.mlv.database._brightest_in_field")


SUITE_LOWERS_OPTIMISATION = SUITE_XLA_FLAGS in os.environ["XLA_FLAGS"].split()


def _suite_compiler_options(name: str) -> dict | None:
    if SUITE_LOWERS_OPTIMISATION and name.startswith(LOOP_BOUND_KERNELS):
        return {"xla_backend_optimization_level": 2}
    return None


js.runtime.program_store.set_compiler_options(_suite_compiler_options)


@pytest.fixture(autouse=True)
def _suite_program_store():
    """Each test starts with the suite's program store on (a test of the store may switch it)."""
    if js.runtime.program_store.program_store_dir() != SUITE_PROGRAMS:
        js.runtime.program_store.enable_program_store(SUITE_PROGRAMS)
    yield


def pytest_sessionfinish(session):
    """The controller (or a run without workers) removes the run's programs when the run ends."""
    if not hasattr(session.config, "workerinput") and CHILD_RUN not in os.environ:
        shutil.rmtree(SUITE_PROGRAMS, ignore_errors=True)

@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem):
    """Under the classic emitter, a ``production_numerics`` test runs in a child pytest process
    whose XLA builds with the default emitter; its failure output is this test's failure."""
    if not SUITE_USES_CLASSIC_EMITTER or pyfuncitem.get_closest_marker("production_numerics") is None:
        return None
    flags = [f for f in os.environ["XLA_FLAGS"].split() if f != CLASSIC_EMITTER]
    child = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "production_numerics",
         pyfuncitem.nodeid],
        cwd=pyfuncitem.config.rootpath, capture_output=True, text=True,
        env=dict(os.environ, XLA_FLAGS=" ".join(flags), **{CHILD_RUN: "1"}))
    if child.returncode != 0:
        pytest.fail(f"under XLA's default emitter, in a child process (exit {child.returncode}):\n"
                    f"{child.stdout[-8000:]}{child.stderr[-2000:]}", pytrace=False)
    return True


# Memory maps: each compiled XLA CPU executable holds ≈ 6 memory mappings, and a worker that runs
# a third of the suite keeps thousands of executables in JAX's caches. At Linux's default
# vm.max_map_count (65,530) XLA's next compile fails to map its code, and the C++ exception it throws
# segfaulted in libgcc's unwinder (cores of three worker crashes: 65,507–65,522 mappings, the crash
# in XLA's compile_and_load). Past MAX_MAPS mappings the caches are dropped between tests.
MAX_MAPS = 45_000


@pytest.fixture(autouse=True)
def _bounded_memory_maps():
    yield
    js.runtime.relieve(MAX_MAPS)


# Files whose tests build the same programs go to one xdist worker, one after the other, so the
# second loads what the first compiled (run at once on two workers, both compile them):
# test_contract.py's RpNet world is test_rpnet.py's network at the same scene width.
SHARED_PROGRAMS = {"tests/algorithms/test_contract.py": "rpnet-world",
                   "tests/algorithms/test_rpnet.py": "rpnet-world"}


def unit_of_work(nodeid: str) -> str:
    """The unit of work a test belongs to: its file, or its file's :data:`SHARED_PROGRAMS` group."""
    path = nodeid.split("::", 1)[0]
    return SHARED_PROGRAMS.get(path, path)


def pytest_xdist_make_scheduler(config, log):
    """xdist: under ``--dist loadfile`` (the suite's) the units of work are :func:`unit_of_work`'s;
    any other ``--dist`` is xdist's own."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class SharedProgramsScheduling(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return unit_of_work(nodeid)

    return SharedProgramsScheduling(config, log)


# A test whose xdist worker still dies in native code runs once more in a fresh worker; a second
# crash fails it. Ordinary failures are never retried, and the retry shows as ``R`` / "rerun".
_crash_retries: dict[str, int] = {}
MAX_CRASH_RETRIES = 1


@pytest.hookimpl(optionalhook=True)
def pytest_handlecrashitem(crashitem, report, sched):
    """xdist: put a crashed test back in the queue (once) instead of failing it."""
    if _crash_retries.get(crashitem, 0) >= MAX_CRASH_RETRIES:
        return
    _crash_retries[crashitem] = _crash_retries.get(crashitem, 0) + 1
    sched.mark_test_pending(crashitem)
    report.outcome = "rerun"


def pytest_report_teststatus(report):
    if report.outcome == "rerun":
        return "rerun", "R", ("RERUN", {"yellow": True})
    return None


@pytest.fixture(scope="session")
def catalog6():
    """Hipparcos V ≤ 6.0 with the default close-pair handling."""
    return js.load_catalog(6.0)


@pytest.fixture(scope="session")
def sgm_camera():
    return js.camera_preset("sgm2022")


@pytest.fixture(scope="module")
def setup5():
    """SGM on a V ≤ 5 catalog: small graphs (≈ 6 vertices), so Algorithm 1 can be replayed quickly.

    Here rather than in ``tests/algorithms/conftest.py``: a second ``conftest`` module would shadow
    this one for ``from conftest import ...`` in whichever xdist worker imported it first.
    """
    from jstarid.algorithms import sgm

    cat = js.load_catalog(5.0)
    cam = js.camera_preset("sgm2022", mag_limit=5.0)
    return cat, cam, sgm.build_database(cat, cam, sgm.Config(), progress=False)


@pytest.fixture
def key():
    return jax.random.key(0)


@pytest.fixture
def several_devices():
    """Skip where the default backend has one device: the forced host devices above are CPU devices,
    and on a GPU host JAX computes on its one GPU (sharding then has nothing to split over)."""
    if jax.device_count() < 2:
        pytest.skip(f"one {jax.default_backend()} device: nothing to shard over")
