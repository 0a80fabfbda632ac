import jax
import jax.numpy as jnp
import numpy as np

from jstarid.geometry import angle_between, pairwise_angles


def _np_angles(u, v):
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.sum(u * v, -1))


def test_angle_between_matches_float64_reference_including_tiny_angles():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(500, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    tiny = np.radians(rng.uniform(1e-4, 0.05, 500))  # 0.36″ … 0.05°
    axis = np.cross(u, rng.normal(size=(500, 3)))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    v = np.cos(tiny)[:, None] * u + np.sin(tiny)[:, None] * axis  # rotated by exactly `tiny`
    got = np.asarray(jax.jit(angle_between)(jnp.asarray(u, jnp.float32), jnp.asarray(v, jnp.float32)))
    np.testing.assert_allclose(got, tiny, rtol=2e-3, atol=2e-7)
    w = rng.normal(size=(500, 3))
    got = np.asarray(angle_between(jnp.asarray(u, jnp.float32), jnp.asarray(w, jnp.float32)))
    np.testing.assert_allclose(got, _np_angles(u, w), atol=1e-6)


def test_pairwise_angles_inside_jit_and_vmap():
    rng = np.random.default_rng(1)
    vecs = rng.normal(size=(6, 40, 3))
    vecs /= np.linalg.norm(vecs, axis=-1, keepdims=True)
    got = np.asarray(jax.jit(jax.vmap(pairwise_angles))(jnp.asarray(vecs, jnp.float32)))
    ref = _np_angles(vecs[:, :, None, :], vecs[:, None, :, :])
    np.testing.assert_allclose(got, ref, atol=1e-6)
    assert np.all(np.diagonal(got, axis1=1, axis2=2) < 1e-6)
