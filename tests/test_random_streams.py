"""The simulator's written-out Threefry streams against JAX's own implementation (bit for bit)."""

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.random import threefry_2x32

from jstarid import random_streams as streams


def test_threefry_is_bit_identical_to_jax():
    rng = np.random.default_rng(0)
    key = rng.integers(0, 2**32, 2, dtype=np.uint32)
    count = rng.integers(0, 2**32, (2, 1000), dtype=np.uint32)
    want = np.asarray(threefry_2x32(jnp.asarray(key), jnp.asarray(count)))
    got = jax.jit(streams.threefry2x32)(key[0], key[1], count[0], count[1])
    np.testing.assert_array_equal(np.stack([np.asarray(g) for g in got]), want)


def test_uniform_and_normal_transforms_match_jax_random():
    key = jax.random.key(7)
    bits = jax.random.bits(key, (4096,), jnp.uint32)
    np.testing.assert_array_equal(np.asarray(jax.jit(streams.unit_uniform)(bits)),
                                  np.asarray(jax.random.uniform(key, (4096,))))
    np.testing.assert_array_equal(np.asarray(jax.jit(streams.unit_normal)(bits)),
                                  np.asarray(jax.random.normal(key, (4096,))))


def test_streams_are_prefix_stable_and_distinct():
    seed = streams.scene_seed(jax.random.key(3))
    short = np.asarray(streams.normals(seed, streams.POSITION, 5))
    long = np.asarray(streams.normals(seed, streams.POSITION, 50))
    np.testing.assert_array_equal(short, long[:5])
    other = np.asarray(streams.normals(seed, streams.MAG, 5))
    assert not np.array_equal(short, other)
    u = np.asarray(streams.uniforms(seed, streams.FALSE_XY, (4, 2)))
    assert u.shape == (4, 2) and np.all((u >= 0) & (u < 1))
