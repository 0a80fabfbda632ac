"""The greedy consistent set of names (jstarid.geometry.consistency) against a brute-force maximum clique."""

from __future__ import annotations

import itertools

import jax.numpy as jnp
import numpy as np
import pytest

from jstarid.geometry.consistency import most_consistent


def _max_clique_size(agree):
    n = agree.shape[0]
    for size in range(n, 0, -1):
        for subset in itertools.combinations(range(n), size):
            if all(agree[a, b] for a, b in itertools.combinations(subset, 2)):
                return size
    return 0


@pytest.mark.parametrize("seed", range(6))
def test_most_consistent_keeps_a_planted_clique(seed):
    """The true names agree pairwise; wrong names agree with a few at random. The greedy set is a
    clique, holds every planted member, and is the maximum clique."""
    rng = np.random.default_rng(seed)
    n, k = 10, 6
    agree = rng.random((n, n)) < 0.2
    agree = np.triu(agree, 1)
    agree = agree | agree.T
    planted = rng.choice(n, k, replace=False)
    agree[np.ix_(planted, planted)] = True
    np.fill_diagonal(agree, False)
    votes = jnp.asarray(rng.integers(1, 20, n), jnp.int32)
    members = np.asarray(most_consistent(jnp.asarray(agree), votes, jnp.ones(n, bool)))
    idx = np.flatnonzero(members)
    assert all(agree[a, b] for a, b in itertools.combinations(idx, 2))
    assert set(planted) <= set(idx)
    assert idx.size == _max_clique_size(agree)
