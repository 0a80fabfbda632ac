import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jstarid.robust import masked_median


@pytest.mark.parametrize("lower", [False, True])
def test_masked_median_matches_numpy(lower):
    rng = np.random.default_rng(0)
    fn = jax.jit(masked_median, static_argnames="lower")
    for n_kept in range(1, 12):  # odd and even counts, padding after and between the kept entries
        x = rng.normal(size=12).astype(np.float32)
        mask = np.zeros(12, bool)
        mask[rng.choice(12, n_kept, replace=False)] = True
        kept = np.sort(x[mask])
        want = kept[(n_kept - 1) // 2] if lower else np.median(kept)
        np.testing.assert_allclose(float(fn(jnp.asarray(x), jnp.asarray(mask), lower=lower)), want,
                                   rtol=1e-6)


def test_masked_median_of_nothing_is_inf():
    assert np.isinf(float(masked_median(jnp.ones(4), jnp.zeros(4, bool))))
    assert np.isinf(float(masked_median(jnp.ones(4), jnp.zeros(4, bool), lower=True)))
