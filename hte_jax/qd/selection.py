"""Parent selection: objects with `select(key, repertoire, num) -> (num,) int32` filled slots, with replacement."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from hte_jax.qd.repertoire import Repertoire


def uniform_among(key: jax.Array, mask: jax.Array, num: int) -> jax.Array:
    """(num,) slots drawn uniformly, with replacement, among those where `mask` (C,) is True (by rank)."""
    cumulative = jnp.cumsum(mask, dtype=jnp.int32)
    rank = jax.random.randint(key, (num,), 0, jnp.maximum(cumulative[-1], 1))
    return jnp.searchsorted(cumulative, rank + 1, side="left").astype(jnp.int32)


@dataclasses.dataclass(frozen=True)
class UniformSelection:
    """Every elite equally likely (the original's; there must be some)."""

    def select(self, key: jax.Array, repertoire: Repertoire, num: int) -> jax.Array:
        return uniform_among(key, repertoire.filled, num)
