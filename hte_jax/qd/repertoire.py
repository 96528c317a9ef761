"""The pytree every container (`Grid`, `Archive`: static, with pure `add`) reads and writes: a fixed-size
block of elites with explicit empty slots, an elite's fields always written together in one masked scatter."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

EMPTY_FITNESS = -jnp.inf


@struct.dataclass
class Repertoire:
    """Elites of a container with C slots."""

    genotypes: jax.Array  # (C, G) float32, zeros where empty
    descriptors: jax.Array  # (C, D) float32, zeros where empty
    fitnesses: jax.Array  # (C,) float32, -inf where empty
    filled: jax.Array  # (C,) bool
    extras: Any = struct.field(default_factory=dict)  # pytree of (C, ...) per-elite arrays, or {}

    @property
    def capacity(self) -> int:
        return self.fitnesses.shape[0]

    @property
    def size(self) -> jax.Array:
        """Number of filled slots (int32 scalar)."""
        return self.filled.sum(dtype=jnp.int32)


@struct.dataclass
class Evaluation:
    """What an evaluation returns for B individuals."""

    fitnesses: jax.Array  # (B,) float32, higher is better
    descriptors: jax.Array  # (B, D) float32
    valid: jax.Array  # (B,) bool; invalid individuals are never inserted
    extras: Any = struct.field(default_factory=dict)  # pytree of (B, ...) arrays stored with the elites, or {}


@struct.dataclass
class Insertion:
    """Outcome of adding B individuals."""

    accepted: jax.Array  # (B,) bool, now an elite
    new_slot: jax.Array  # (B,) bool, in a slot that was empty
    slot: jax.Array  # (B,) int32, where it went, -1 if rejected


def empty_repertoire(capacity: int, genotype_dim: int, descriptor_dim: int, extras: Any = None) -> Repertoire:
    """An empty repertoire; `extras` is a pytree of per-elite example arrays (shapes without C)."""
    extras = {} if extras is None else extras
    return Repertoire(genotypes=jnp.zeros((capacity, genotype_dim), jnp.float32),
                      descriptors=jnp.zeros((capacity, descriptor_dim), jnp.float32),
                      fitnesses=jnp.full((capacity,), EMPTY_FITNESS, jnp.float32), filled=jnp.zeros((capacity,), bool),
                      extras=jax.tree.map(lambda x: jnp.zeros((capacity, *jnp.shape(x)), jnp.asarray(x).dtype), extras))


def write(repertoire: Repertoire, slot: jax.Array, genotypes, evaluation: Evaluation) -> Repertoire:
    """Write a batch's rows into `slot` (B,) int32 (-1: skipped; unique, so the scatter is deterministic)."""
    target = jnp.where(slot >= 0, slot, repertoire.capacity)  # out of range -> dropped

    def put(store, rows):
        return store.at[target].set(rows.astype(store.dtype), mode="drop")

    return repertoire.replace(
        genotypes=put(repertoire.genotypes, genotypes), descriptors=put(repertoire.descriptors, evaluation.descriptors),
        fitnesses=put(repertoire.fitnesses, evaluation.fitnesses),
        filled=put(repertoire.filled, jnp.ones_like(slot, bool)),
        extras=jax.tree.map(put, repertoire.extras, evaluation.extras))


def best_per_target(fitness: jax.Array, target: jax.Array, candidate: jax.Array, num_targets: int) -> jax.Array:
    """(B,) bool: the candidate with the highest fitness (B,) for its target (B,) int in [0, num_targets), ties
    to the first in the batch; candidate (B,) bool marks who competes."""
    batch = fitness.shape[0]
    order = jnp.arange(batch, dtype=jnp.int32)
    segment = jnp.where(candidate, target, num_targets)  # non-candidates share a dummy segment
    best = jax.ops.segment_max(jnp.where(candidate, fitness, -jnp.inf), segment, num_segments=num_targets + 1)
    contender = candidate & (fitness == best[segment])
    first = jax.ops.segment_min(jnp.where(contender, order, batch), segment, num_segments=num_targets + 1)
    return candidate & (first[segment] == order)


def insertable(evaluation: Evaluation) -> jax.Array:
    """(B,) bool: valid, finite fitness and finite descriptors."""
    return evaluation.valid & jnp.isfinite(evaluation.fitnesses) & jnp.isfinite(evaluation.descriptors).all(axis=-1)
