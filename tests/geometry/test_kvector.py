"""k-vector range search against np.searchsorted."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jstarid.geometry import build_kvector, range_search


@pytest.mark.parametrize("dist", ["uniform", "clustered", "duplicates", "single"])
def test_range_search_matches_searchsorted(dist):
    rng = np.random.default_rng(0)
    if dist == "uniform":
        v = rng.uniform(-5, 40, 3000)
    elif dist == "clustered":
        v = np.concatenate([rng.normal(10, 0.01, 2000), rng.exponential(5, 500)])
    elif dist == "duplicates":
        v = rng.integers(0, 20, 1000).astype(float) * 0.5
    else:
        v = np.array([3.25])
    kv, order = build_kvector(v)
    s = np.asarray(kv.values)
    np.testing.assert_array_equal(s, np.sort(v).astype(np.float32))
    np.testing.assert_array_equal(s, v[order].astype(np.float32))
    # queries: random, exactly on stored values, outside the range, empty intervals
    a = np.concatenate([rng.uniform(-10, 50, 400), s[rng.integers(0, s.size, 200)],
                        [-1e3, 1e3, s[0], s[-1]]]).astype(np.float32)
    width = np.concatenate([rng.uniform(0, 3, a.size - 10), np.zeros(5), [-1.0] * 5]).astype(
        np.float32)
    b = (a + width).astype(np.float32)
    start, stop = jax.jit(jax.vmap(range_search, in_axes=(None, 0, 0)))(kv, jnp.asarray(a),
                                                                         jnp.asarray(b))
    ref_start = np.searchsorted(s, a, side="left")
    ref_stop = np.maximum(np.searchsorted(s, b, side="right"), ref_start)
    np.testing.assert_array_equal(np.asarray(start), ref_start)
    np.testing.assert_array_equal(np.asarray(stop), ref_stop)


def test_build_rejects_bad_input():
    with pytest.raises(ValueError):
        build_kvector([])
    with pytest.raises(ValueError):
        build_kvector([1.0, np.nan])
