"""The batching runtime (jstarid.runtime): host device count, replication, the device cache,
sharded pair kernels."""

import gc

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js
from jstarid.runtime import call_width, columns_in_use, skip_padding
from jstarid.runtime.pairs import _spread


def test_use_cpu_cores_reads_an_explicit_count_and_refuses_a_late_change(monkeypatch, several_devices):
    assert js.use_cpu_cores() == jax.device_count()  # conftest set the count in XLA_FLAGS
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=7 --foo")
    assert js.use_cpu_cores() == 7
    monkeypatch.setenv("XLA_FLAGS", "")
    jax.devices()  # the backend is running
    assert js.use_cpu_cores(jax.device_count()) == jax.device_count()
    with pytest.raises(RuntimeError, match="before the first JAX computation"):
        js.use_cpu_cores(jax.device_count() + 1)


def test_replicate_puts_a_copy_on_every_device():
    x = js.runtime.replicate(jnp.arange(5))
    assert len(x.sharding.device_set) == jax.device_count()
    np.testing.assert_array_equal(np.asarray(x), np.arange(5))


def test_device_cache_places_an_owners_tables_once_per_name_and_mesh(several_devices):
    class Owner:  # any object that takes weak references (catalogs, indexes, databases)
        pass

    cache = js.runtime.DeviceCache()
    owner, calls = Owner(), []

    def make(value):
        def fn():
            calls.append(value)
            return {"a": jnp.full((3,), value)}
        return fn

    first = cache.replicated(owner, "t", make(1.0))
    assert cache.replicated(owner, "t", make(2.0)) is first  # placed once: make not called
    other = cache.replicated(owner, "u", make(3.0))
    one = cache.replicated(owner, "t", make(4.0), mesh=js.runtime.batch_mesh(jax.devices()[:1]))
    assert calls == [1.0, 3.0, 4.0]
    assert len(first["a"].sharding.device_set) == jax.device_count()
    assert len(one["a"].sharding.device_set) == 1
    np.testing.assert_array_equal(np.asarray(other["a"]), 3.0)
    assert not hasattr(owner, "_replicated_tables") and vars(owner) == {}  # the owner is untouched
    assert len(cache) == 3
    del owner
    gc.collect()
    assert len(cache) == 0  # entries live as long as their owner


@pytest.mark.parametrize("n, padded, n_dev", [(5, 16, 4), (16, 16, 4), (1, 16, 2), (9, 32, 1), (3, 16, 3)])
def test_spread_deals_pairs_evenly_into_distinct_slots(n, padded, n_dev):
    slot = _spread(n, padded, n_dev)
    assert slot.size == n and np.unique(slot).size == n and slot.max() < padded
    if n_dev > 1 and padded % n_dev == 0:
        per_device = np.bincount(slot // (padded // n_dev), minlength=n_dev)
        assert per_device.max() - per_device.min() <= 1


def test_skip_padding_runs_live_entries_only():
    calls = jnp.arange(6.0)
    live = jnp.array([True, False, True, True, False, False])
    out = skip_padding(lambda x: (x * 2.0, x + 1.0), live, (calls,), (jnp.float32(-1), jnp.float32(-2)))
    np.testing.assert_array_equal(np.asarray(out[0]), [0, -1, 4, 6, -1, -1])
    np.testing.assert_array_equal(np.asarray(out[1]), [1, -2, 3, 4, -2, -2])


def _square_rows(x, valid, scale):  # module level: map_batch caches the compiled call on the function
    return jnp.where(valid, x * x * scale, -1.0), jnp.sum(valid, axis=-1)


def test_run_calls_computes_every_row_once_whatever_the_plan():
    """Sorted, padded, ragged-width calls give each row what one whole-batch call gives."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(23, 8)).astype(np.float32)
    n = rng.integers(1, 9, 23)
    valid = np.arange(8)[None, :] < n[:, None]
    want = _square_rows(x, valid, 2.0)
    order = np.argsort(n, kind="stable")
    calls = js.runtime.chunk_calls(order, 5)
    assert [c.rows.size for c in calls] == [5, 5, 5, 5, 3] and all(c.size == 5 for c in calls)

    def args(call):  # each call cut to the widest of its rows
        width = int(n[call.rows].max())
        return js.runtime.take_rows((x[:, :width], valid[:, :width]), call)

    got = js.runtime.run_calls(_square_rows, calls, args, (np.float32(2.0),), n_rows=23,
                               tails=[(8,), ()], fills=[-1.0, 0])
    np.testing.assert_array_equal(got[0], np.asarray(want[0]))
    np.testing.assert_array_equal(got[1], np.asarray(want[1]))
    # a plan of a subset leaves the other rows as they were in ``out``
    part = js.runtime.run_calls(_square_rows, js.runtime.chunk_calls(np.array([3, 7]), 4), args,
                                (np.float32(3.0),), n_rows=23, tails=[(8,), ()], fills=[-1.0, 0],
                                out=[g.copy() for g in got])
    changed = np.flatnonzero(np.any(part[0] != got[0], axis=1))
    assert set(changed) <= {3, 7} and changed.size


def test_grow_until_retries_only_flagged_rows():
    need = np.array([3, 40, 9, 100, 1])
    seen = []

    def run(capacity, rows):
        seen.append((capacity, rows.tolist()))
        return need[rows] > capacity

    assert js.runtime.grow_until(run, np.arange(5), 8, 64) == 64
    assert seen == [(8, [0, 1, 2, 3, 4]), (16, [1, 2, 3]), (32, [1, 3]), (64, [1, 3])]


def test_map_by_width_equals_the_full_width_map():
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.normal(size=(37, 16)).astype(np.float32))
    need = jnp.asarray(rng.integers(1, 17, 37))

    def make(width):  # a row's sum over its first `need` entries, read from `width` columns
        def fn(args):
            xs, ns = args
            cols = jnp.arange(width)[None, :]
            return jnp.sum(jnp.where(cols < ns[:, None], xs[:, :width], 0.0), axis=1)
        return fn

    got = jax.jit(lambda a, nd: js.runtime.map_by_width(make, (a, nd), nd, (4, 8, 16), 8))(x, need)
    np.testing.assert_allclose(np.asarray(got), np.asarray(make(16)((x, need))), rtol=1e-6)


def test_relieve_drops_compiled_kernels_only_past_the_limit(monkeypatch):
    from jstarid.runtime import memory_maps

    double = jax.jit(lambda x: 2 * x)
    double(jnp.ones(3))
    assert double._cache_size() == 1
    monkeypatch.setattr(memory_maps, "map_count", lambda: 1_000)
    assert not js.runtime.relieve(1_000) and double._cache_size() == 1
    assert js.runtime.relieve(999) and double._cache_size() == 0
    assert memory_maps.map_limit() > 0 and memory_maps.map_count() > 0  # Linux: /proc is there


def test_release_staging_keeps_the_executables_and_drops_the_traced_programs(several_devices):
    """After a release, a kernel called again on the shapes it met runs its executable (not traced
    again, same answer); a new shape is traced as a first call is. Nothing is released before
    ``min_new`` programs were staged since the last release."""
    from jstarid.runtime import staging_memory

    traces = []

    def body(x):
        traces.append(x.shape)  # runs once per trace, never when the executable is reused
        return jnp.cumsum(x * x)

    kernel = jax.jit(body)
    x5, x6, x8 = jnp.arange(5.0), jnp.arange(6.0), jnp.arange(8.0)
    js.runtime.release_staging(min_new=0)  # start from a release: count from here
    before = staging_memory.programs_staged()
    first = np.asarray(kernel(x5))
    assert staging_memory.programs_staged() == before + 1
    assert not js.runtime.release_staging(min_new=2)  # one program since the last release
    np.asarray(js.runtime.map_batch(_double_rows, (x8,)))  # a second program
    assert staging_memory.programs_staged() >= before + 2
    from jax._src import dispatch, pjit  # the caches the release empties and keeps

    primitives = dispatch.xla_primitive_callable.cache_info().currsize
    assert pjit._infer_params_cached.cache_info().currsize > 0
    assert js.runtime.release_staging(min_new=2)
    assert pjit._infer_params_cached.cache_info().currsize == 0  # the traced programs are gone
    assert dispatch.xla_primitive_callable.cache_info().currsize == primitives  # eager ops kept
    np.testing.assert_array_equal(np.asarray(kernel(x5)), first)
    assert traces == [(5,)] and kernel._cache_size() == 1
    kernel(x6)
    assert traces == [(5,), (6,)]
    assert isinstance(staging_memory.trim_heap(), bool)


def _double_rows(x):
    return 2 * x


def test_prefetch_yields_the_sequential_items_in_order():
    from jstarid.runtime.prefetch import prefetch

    key = jax.random.key(3)

    def make(i):
        return jax.random.normal(jax.random.fold_in(key, i), (4,))

    got = list(prefetch(make, range(2, 9), depth=2))
    want = [make(i) for i in range(2, 9)]
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    assert list(prefetch(make, range(0))) == []


def test_prefetch_raises_the_makers_error_at_its_item_and_stops_when_closed():
    import threading

    from jstarid.runtime.prefetch import prefetch

    def make(i):
        if i == 3:
            raise KeyError("item 3")
        return i

    items = prefetch(make, range(10))
    assert [next(items) for _ in range(3)] == [0, 1, 2]
    with pytest.raises(KeyError, match="item 3"):
        next(items)

    made = []
    items = prefetch(lambda i: made.append(i) or i, range(10**6), depth=1)
    assert next(items) == 0
    items.close()  # the consumer stops early: the thread ends, a few items made at most
    assert not any(t.name == "jstarid-prefetch" for t in threading.enumerate())
    assert len(made) <= 3
    with pytest.raises(ValueError, match="depth"):
        next(prefetch(make, range(3), depth=0))


@pytest.mark.parametrize("n", [0, 1, 63, 64, 65, 100, 686, 4096, 4097, 5000, 12_345])
def test_power_of_two_chunks_cover_the_rows_with_little_padding(n):
    from jstarid.runtime.padding import power_of_two_chunks
    chunks = power_of_two_chunks(n, 64)
    if n == 0:
        assert chunks == []
        return
    assert [lo for lo, _, _ in chunks] == [0] + [hi for _, hi, _ in chunks[:-1]] and chunks[-1][1] == n
    for lo, hi, padded in chunks:
        assert padded >= max(hi - lo, 64) and padded & (padded - 1) == 0
    # every call but the last is full; the last pads by at most a quarter of its rows (or to 64)
    assert all(hi - lo == padded for lo, hi, padded in chunks[:-1])
    lo, hi, padded = chunks[-1]
    assert padded == 64 or padded - (hi - lo) <= 0.25 * (hi - lo)


@pytest.mark.parametrize("floor", [1, 8, 16])
def test_next_power_of_two_is_the_smallest_above_n_and_floor(floor):
    from jstarid.runtime import next_power_of_two
    for n in [0, 0.5, 1, 2, 3, 4.5, 7, 8, 9, 63, 64, 65, 1000, 4096, 4097]:
        want = max(floor, 2 ** max(0, int(np.ceil(np.log2(max(n, 1))))))  # the float reference
        assert next_power_of_two(n, floor) == want, n


@pytest.mark.parametrize("n, chunk, size", [(0, 100, 16), (1, 1024, 16), (12, 100, 16), (16, 100, 16),
                                             (17, 100, 32), (100, 100, 100), (5000, 1024, 1024),
                                             (5, 8, 8), (3, 1, 1)])
def test_call_size_is_a_power_of_two_from_sixteen_up_to_the_chunk(n, chunk, size):
    """Batches of 1 to 16 scenes share one call size (one compilation); the chunk caps it."""
    from jstarid.runtime import call_size

    assert call_size(n, chunk) == size


@pytest.mark.parametrize("floor, limit", [(16, 1024), (64, 4096), (64, 256), (1, 1)])
def test_coarse_size_steps_by_four_up_to_the_limit_and_by_two_above(floor, limit):
    """The padded sizes of calls whose padding is skipped: floor · 4^k while ≤ limit, then powers of
    two; each the smallest of that ladder holding n."""
    from jstarid.runtime import coarse_size, next_power_of_two

    ladder = [floor * 4**k for k in range(12) if floor * 4**k <= limit]
    ladder += [2**k for k in range(40) if 2**k > ladder[-1]]
    for n in [0, 1, 15, 16, 17, 100, 128, 129, 1000, 1024, 1025, 3000, 5000, 70_000]:
        assert coarse_size(n, floor, limit) == min(s for s in ladder if s >= n), (n, floor, limit)
    # up to the limit four sizes serve every n, where powers of two take seven
    sizes = {coarse_size(n, 16, 1024) for n in range(1, 1025)}
    assert sizes == {16, 64, 256, 1024} and len({next_power_of_two(n, 16) for n in range(1, 1025)}) == 7


def test_padded_indices_repeat_the_first_row_up_to_a_power_of_two():
    from jstarid.runtime import padded_indices
    np.testing.assert_array_equal(padded_indices(np.array([5, 2, 9])), [5, 2, 9, 5])
    np.testing.assert_array_equal(padded_indices(np.array([4, 1])), [4, 1])
    assert padded_indices(np.arange(3), floor=8).tolist() == [0, 1, 2, 0, 0, 0, 0, 0]


def test_static_config_resets_what_the_kernels_do_not_compile():
    """Configs that differ only in traced or host-loop fields share one static config (one program);
    a field the kernels read keeps its value, and an unknown name is refused."""
    from jstarid.algorithms import mlv
    from jstarid.runtime import static_config
    traced = ("th1", "eps_deg", "batch_chunk", "finishing")
    a = static_config(mlv.Config(th1=2, eps_deg=0.3, batch_chunk=64, finishing={"fit_focal": False}), traced)
    assert a == mlv.Config() and hash(a) == hash(mlv.Config())
    assert static_config(mlv.Config(n_stars=8), traced).n_stars == 8
    with pytest.raises(ValueError, match="no field"):
        static_config(mlv.Config(), ("not_a_field",))


def test_count_compilations_counts_each_new_program_once():
    """``CountCompilations``: a new jit program counts once, the same shapes again not at all, a new
    shape again once; nothing is counted after the block. (Programs this small stay out of XLA's
    persistent cache, whose hits would not count.)"""
    from jstarid.runtime import CountCompilations

    f = jax.jit(lambda x: jnp.sin(x) * 3.0 + 1.0)
    x4, y4, x5 = jnp.arange(4.0), jnp.arange(4.0) + 1.0, jnp.arange(5.0)
    with CountCompilations() as first:
        f(x4).block_until_ready()
    with CountCompilations() as again:
        f(y4).block_until_ready()
    with CountCompilations() as other:
        f(x5).block_until_ready()
        assert other.programs == 1  # live inside the block
    f(jnp.arange(6.0)).block_until_ready()
    assert (first.programs, again.programs, other.programs) == (1, 0, 1)
    assert first.seconds > 0 and again.seconds == 0


def test_columns_in_use_is_one_past_the_last_valid_entry():
    valid = np.array([[1, 0, 1, 0, 0], [0, 0, 0, 0, 0], [1, 1, 1, 1, 1], [0, 0, 0, 0, 1]], bool)
    np.testing.assert_array_equal(columns_in_use(valid), [3, 0, 5, 5])


def test_call_width_is_a_power_of_two_covering_the_rows_and_at_most_the_columns():
    filled = np.array([3, 0, 40, 70, 5])
    assert call_width(filled, np.array([0, 1, 4]), 128, 32) == 32  # the floor
    assert call_width(filled, np.array([0, 2]), 128, 32) == 64
    assert call_width(filled, np.array([3]), 128, 32) == 128
    assert call_width(filled, np.array([3]), 96, 32) == 96  # never past the columns there are


def test_call_padded_computes_each_row_as_the_plain_call_and_shares_one_program():
    """Batches of 0, 3 and 9 rows run at 16 (one program); each output row is the plain call's,
    cut back to the batch; a batch at a power of two ≥ the floor runs as it is."""
    from jstarid.runtime.padding import call_padded

    @jax.jit
    def kernel(x, flags, scale):
        return {"sum": jnp.sum(x, axis=1) * scale, "any": jnp.any(flags, axis=1)}

    rng = np.random.default_rng(0)
    for n in (0, 3, 9, 32):
        x = jnp.asarray(rng.normal(size=(n, 5)), jnp.float32)
        flags = jnp.asarray(rng.random((n, 5)) < 0.3)
        got = call_padded(kernel, (x, flags), jnp.float32(2.0))
        want = kernel(x, flags, jnp.float32(2.0))
        for name in ("sum", "any"):
            assert got[name].shape == (n,)
            np.testing.assert_array_equal(np.asarray(got[name]), np.asarray(want[name]))
    assert kernel._cache_size() == 1 + 4  # one at 16 for 0, 3 and 9 rows (32 as it is); the plain calls
