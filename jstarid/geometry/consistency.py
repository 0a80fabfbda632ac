"""The largest set of mutually consistent names, found greedily (shared by the pair-angle baselines).

Two named detections agree when their catalog stars' angle matches the measured one; a set of names
is consistent when every pair in it agrees. Finding the largest such set is a maximum-clique problem;
the greedy rule here drops, while some pair disagrees, the name with the fewest agreements (ties:
the fewest first-round votes or score) — exact whenever the wrong names agree with few others, as
chance agreements do.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["most_consistent"]


def most_consistent(agree, votes, members):
    """Drop the least-agreeing member until every remaining pair agrees (module docstring).

    Args:
        agree: (n, n) bool symmetric, False on the diagonal.
        votes: (n,) int32 first-round votes or scores (the tie-break: fewer go first).
        members: (n,) bool starting set.

    Returns:
        (n,) bool the consistent set.
    """
    n = agree.shape[0]
    big = jnp.iinfo(jnp.int32).max

    def step(_, members):
        support = jnp.sum(agree & members[None, :], axis=1)
        size = jnp.sum(members)
        consistent = jnp.all(~members | (support == size - 1))
        least = jnp.min(jnp.where(members, support, big))
        worst = jnp.argmin(jnp.where(members & (support == least), votes, big))
        return jnp.where(consistent, members, members & (jnp.arange(n) != worst))

    return jax.lax.fori_loop(0, n, step, members)
