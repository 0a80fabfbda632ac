"""The program store (jstarid.runtime.program_store): compiled programs kept on disk, loaded by a
later call or process without tracing, and never returned for a different program."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js
from jstarid.runtime import program_store as ps


@pytest.fixture
def store(tmp_path):
    ps.enable_program_store(tmp_path / "programs")
    yield tmp_path / "programs"
    ps.disable_program_store()


@pytest.fixture
def store_off():
    """The store off for one test (the suite runs with its own store on, tests/conftest.py)."""
    ps.disable_program_store()
    yield


def _programs(root):
    return sorted(root.rglob("*.jaxprog"))


def _counting_kernel(traces):
    def kernel(x, y, *, power):
        traces.append((x.shape, power))
        return jnp.sum(x**power, axis=-1) + y

    return ps.StoredFunction(jax.jit(kernel, static_argnames=("power",)), "tests.kernel", ("power",))


def test_off_it_is_the_jitted_function(store_off):
    traces = []
    kernel = _counting_kernel(traces)
    out = kernel(jnp.ones((3, 4)), 1.0, power=2)
    np.testing.assert_array_equal(out, np.full(3, 5.0))
    assert ps.program_store_dir() is None and kernel._cache_size() == 1 and traces == [((3, 4), 2)]


def test_a_program_is_written_once_and_read_back_without_tracing(store):
    traces = []
    kernel = _counting_kernel(traces)
    x = np.arange(12, dtype=np.float32).reshape(3, 4)
    before = ps.program_store_stats()
    first = np.asarray(kernel(x, 0.5, power=3))
    assert len(_programs(store)) == 1 and len(traces) == 1
    assert ps.program_store_stats()["written"] == before["written"] + 1
    kernel(x + 1, 0.25, power=3)  # same shapes: the program in memory
    assert len(traces) == 1
    ps.forget_programs()  # as a new process would: only the file is left
    again = np.asarray(kernel(x, 0.5, power=3))
    np.testing.assert_array_equal(again, first)
    assert len(traces) == 1 and ps.program_store_stats()["loaded"] == before["loaded"] + 1
    np.testing.assert_allclose(first, np.sum(x**3, axis=-1) + 0.5, rtol=1e-6)


def test_disable_jit_runs_op_by_op_with_the_store_on(store):
    """Under ``jax.disable_jit()`` a stored function runs its Python op by op (no program is
    compiled or loaded), as ``jax.jit`` does: the way to debug a kernel with the store on."""
    traces = []
    kernel = _counting_kernel(traces)
    x = np.arange(6, dtype=np.float32).reshape(2, 3)
    with jax.disable_jit():
        eager = np.asarray(kernel(x, 1.0, power=2))
        eager_again = np.asarray(kernel(x, 1.0, power=2))
    assert len(traces) == 2 and not _programs(store)  # the body ran twice, nothing was stored
    np.testing.assert_allclose(eager, np.sum(x**2, axis=-1) + 1.0)
    np.testing.assert_array_equal(np.asarray(kernel(x, 1.0, power=2)), eager_again)
    assert len(_programs(store)) == 1


def test_another_static_shape_dtype_or_sharding_is_another_program(store, several_devices):
    traces = []
    kernel = _counting_kernel(traces)
    x = np.ones((4, 2), np.float32)
    kernel(x, 0.0, power=2)
    kernel(x, 0.0, power=3)  # static
    kernel(np.ones((8, 2), np.float32), 0.0, power=2)  # shape
    kernel(np.ones((4, 2), np.int32), 0, power=2)  # dtypes (the scalar's too)
    kernel(js.runtime.shard_batch(jnp.ones((4, 2))), 0.0, power=2)  # committed, sharded
    assert len(traces) == 5 and len(_programs(store)) == 5


def test_compiler_options_reach_the_programs_they_name_and_key_them(store, tmp_path):
    """The options chosen for a name are given to XLA when that program is built (here: a dump
    directory it writes into) and not to others; a program built with options is another file."""
    traces = []
    kernel = _counting_kernel(traces)
    dumps = tmp_path / "dumps"
    asked = []

    def options(name):
        asked.append(name)
        return {"xla_dump_to": str(dumps)} if name == "tests.kernel" else None

    x = np.ones((2, 5), np.float32)
    plain = np.asarray(kernel(x, 1.0, power=2))
    assert not dumps.exists()
    suites = ps.set_compiler_options(options)
    try:
        ps.forget_programs()
        with_options = np.asarray(kernel(x, 1.0, power=2))
        assert "tests.kernel" in asked and any(dumps.iterdir())  # XLA wrote its dump
        assert len(_programs(store)) == 2  # not the file built without them
        np.testing.assert_array_equal(with_options, plain)
        dumped = sorted(dumps.iterdir())
        other = ps.StoredFunction(jax.jit(lambda v: v * 3.0), "tests.other")
        np.testing.assert_array_equal(np.asarray(other(x)), x * 3.0)
        assert "tests.other" in asked and sorted(dumps.iterdir()) == dumped  # built without them
    finally:
        ps.set_compiler_options(suites)


def test_a_damaged_file_is_compiled_again_and_rewritten(store, caplog):
    traces = []
    kernel = _counting_kernel(traces)
    x = np.ones((2, 3), np.float32)
    kernel(x, 1.0, power=1)
    (path,) = _programs(store)
    path.write_bytes(b"not a program")
    ps.forget_programs()
    before = ps.program_store_stats()
    np.testing.assert_array_equal(kernel(x, 1.0, power=1), np.full(2, 4.0))
    after = ps.program_store_stats()
    assert after["compiled"] == before["compiled"] + 1 and after["loaded"] == before["loaded"]
    assert "unreadable" in caplog.text and path.stat().st_size > 100


def test_inside_a_trace_and_for_foreign_code_it_is_plain_jit(store, several_devices):
    traces = []
    kernel = _counting_kernel(traces)
    outer = jax.jit(lambda x: kernel(x, 1.0, power=2) * 2)
    np.testing.assert_array_equal(outer(jnp.ones((2, 2))), np.full(2, 6.0))
    # a user's kernel through map_batch (its source is not in the key), a lambda, a partial
    out = js.runtime.map_batch(lambda x: x + 1, (jnp.arange(8.0),))
    np.testing.assert_array_equal(out, np.arange(8.0) + 1)
    assert ps.storable_name(lambda x: x) is None and ps.storable_name(np.sum) is None
    assert ps.storable_name(js.attitude.estimate_attitude) == "jstarid.attitude.estimate_attitude"
    assert _programs(store) == []


def test_old_versions_are_pruned(store, tmp_path):
    for k in range(5):  # salt directories of earlier sources, oldest first
        old = store / f"old{k}"
        old.mkdir(parents=True)
        os.utime(old, (1_000_000 + k, 1_000_000 + k))
    _counting_kernel([])(np.ones(3, np.float32), 0.0, power=1)
    kept = sorted(p.name for p in store.iterdir())
    assert len(kept) == ps.KEEP_VERSIONS and "old4" in kept and "old3" in kept


_SCRIPT = textwrap.dedent("""
    import json, sys
    import numpy as np
    import jax
    import jstarid as js
    from jstarid.runtime import program_store as ps
    if len(sys.argv) > 2:  # JAX's persistent cache on as well (as in the CLI)
        js.enable_compilation_cache(sys.argv[2], min_compile_time_s=0.0, programs=False)
    ps.enable_program_store(sys.argv[1])
    cam = js.camera_preset("mlv2021")
    catalog = js.load_catalog(cam.mag_limit)
    scenes = js.simulate(jax.random.key(3), catalog, cam, batch_size=6, capacity=48)
    truth = js.Identification(ids=scenes.truth, ok=np.ones(6, bool))
    # a one-device program with LAPACK (Wahba's SVD; statics passed by position) and a sharded one
    att, res, have = js.estimate_attitude(catalog, cam, scenes, truth)
    rows = js.runtime.map_batch(js.metrics.nearest_to_principal_point, (scenes.xy, scenes.valid),
                                static=dict(camera=cam))
    print(json.dumps(dict(stats=ps.program_store_stats(), att=np.asarray(att).tolist(),
                          rows=np.asarray(rows).tolist())))
""")


def _run_script(tmp_path, *args):
    import json

    # two devices, and the suite's other XLA flags (its optimisation level: compiled faster)
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    env = {**os.environ, "XLA_FLAGS": " ".join(["--xla_force_host_platform_device_count=2", *flags])}
    env.pop("JSTARID_COMPILATION_CACHE", None)
    script = tmp_path / "run.py"
    script.write_text(_SCRIPT)
    done = subprocess.run([sys.executable, str(script), *map(str, args)], env=env, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_a_new_process_loads_the_programs_and_computes_the_same(tmp_path):
    """LAPACK and the devices of a one-device program must be readied by the loading process."""
    first, second = (_run_script(tmp_path, tmp_path / "programs") for _ in range(2))
    assert first["stats"]["written"] >= 3 and first["stats"]["loaded"] == 0
    assert second["stats"]["compiled"] == 0 and second["stats"]["loaded"] == first["stats"]["written"]
    assert second["att"] == first["att"] and second["rows"] == first["rows"]
    assert np.isfinite(np.asarray(second["att"])).all()


def test_programs_are_not_taken_from_jaxs_cache(tmp_path):
    """An executable JAX read back from its persistent cache serializes incomplete (XLA:CPU): a
    store filled while that cache holds every program must still load in a new process."""
    xla = tmp_path / "xla"
    _run_script(tmp_path, tmp_path / "first", xla)  # fills JAX's cache
    filled = _run_script(tmp_path, tmp_path / "second", xla)
    loaded = _run_script(tmp_path, tmp_path / "second", xla)
    assert loaded["stats"]["loaded"] == filled["stats"]["written"] > 0
    assert loaded["att"] == filled["att"] and loaded["rows"] == filled["rows"]
