import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jstarid.robust import brighter_than_named, masked_median


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


def _numpy_brighter(det, star, named, tol, sigmas, min_names):
    """Plain NumPy reference of brighter_than_named."""
    diff = det - star
    if named.sum() < min_names:
        return np.zeros_like(named)
    zero = np.median(diff[named])
    spread = 1.4826 * np.median(np.abs(diff[named] - zero))
    return named & (diff - zero < -max(tol, sigmas * spread))


def test_brighter_than_named_matches_numpy():
    rng = np.random.default_rng(1)
    fn = jax.jit(brighter_than_named, static_argnames=("tol_mag", "sigmas", "min_names"))
    for _ in range(60):
        n = 16
        star = rng.uniform(2.0, 7.0, n).astype(np.float32)
        noise = rng.choice([0.05, 0.3, 1.0])
        det = (star + 11.3 + rng.normal(0, noise, n)).astype(np.float32)  # any zero point
        det[rng.integers(n)] -= rng.uniform(1.0, 5.0)  # one detection far brighter than its star
        named = rng.random(n) < rng.uniform(0.1, 1.0)
        want = _numpy_brighter(det, star, named, 2.0, 5.0, 4)
        got = fn(jnp.asarray(det), jnp.asarray(star), jnp.asarray(named), tol_mag=2.0, sigmas=5.0,
                 min_names=4)
        np.testing.assert_array_equal(np.asarray(got), want)


def test_brighter_than_named_is_one_sided_and_needs_four_names():
    star = jnp.asarray([3.0, 4.0, 5.0, 6.0, 6.5])
    det = star + 0.1
    named = jnp.ones(5, bool)
    bright = det.at[4].add(-3.0)  # a detection 3 mag brighter than its star
    faint = det.at[0].add(+3.0)  # a saturated bright star: fainter than its V
    assert np.asarray(brighter_than_named(bright, star, named, tol_mag=2.0, sigmas=5.0)).tolist() == \
        [False] * 4 + [True]
    assert not np.any(np.asarray(brighter_than_named(faint, star, named, tol_mag=2.0, sigmas=5.0)))
    three = jnp.asarray([True, True, False, False, True])  # no zero point to trust
    assert not np.any(np.asarray(brighter_than_named(bright, star, three, tol_mag=2.0, sigmas=5.0)))
