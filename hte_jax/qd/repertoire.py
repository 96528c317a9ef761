"""The pytree every container reads and writes: a fixed-size block of elites with explicit empty slots."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

EMPTY_FITNESS = -jnp.inf


@struct.dataclass
class Repertoire:
    """Elites of a container with C slots: genotypes (C, G) and descriptors (C, D) float32, zeros where empty;
    fitnesses (C,) float32, -inf where empty; filled (C,) bool; extras: pytree of (C, ...) per-elite arrays, or {}."""

    genotypes: jax.Array
    descriptors: jax.Array
    fitnesses: jax.Array
    filled: jax.Array
    extras: Any = struct.field(default_factory=dict)

    @property
    def capacity(self) -> int:
        return self.fitnesses.shape[0]

    @property
    def size(self) -> jax.Array:
        """Number of filled slots (int32 scalar)."""
        return self.filled.sum(dtype=jnp.int32)


@struct.dataclass
class Evaluation:
    """What an evaluation returns for B individuals: fitnesses (B,) float32 (higher is better), descriptors
    (B, D) float32, valid (B,) bool (invalid ones are never inserted), extras: pytree of (B, ...) arrays, or {}."""

    fitnesses: jax.Array
    descriptors: jax.Array
    valid: jax.Array
    extras: Any = struct.field(default_factory=dict)


@struct.dataclass
class Insertion:
    """Outcome of adding B individuals: accepted (B,) bool, now an elite; new_slot (B,) bool, in a slot that was
    empty; slot (B,) int32, where it went (-1: rejected)."""

    accepted: jax.Array
    new_slot: jax.Array
    slot: jax.Array


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
