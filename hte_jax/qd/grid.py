"""MAP-Elites grid: dimension i spans [low_i, high_i] in bins_i bins (x = high: the last), cells row-major, outside
rejected. Per cell, a batch's best valid candidate (ties: first) replaces the elite if strictly fitter (empty: -inf)."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.errors import ConfigError, require_bounds, require_int
from hte_jax.numerics import quotient
from hte_jax.qd.repertoire import (Evaluation, Insertion, Repertoire, best_per_target, empty_repertoire, insertable,
                                   write)


@dataclasses.dataclass(frozen=True)
class Grid:
    """A grid container (static, hashable): `bins` cells per dimension over descriptor bounds `low`, `high`."""

    bins: tuple[int, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]

    def __post_init__(self):
        if not self.bins:
            raise ConfigError("grid bins must not be empty")
        for i, bins in enumerate(self.bins):
            require_int(f"grid bins[{i}]", bins)
        require_bounds("grid", self.low, self.high, len(self.bins))

    @property
    def capacity(self) -> int:
        return math.prod(self.bins)

    @property
    def descriptor_dim(self) -> int:
        return len(self.bins)

    def empty(self, genotype_dim: int, extras=None) -> Repertoire:
        return empty_repertoire(self.capacity, genotype_dim, self.descriptor_dim, extras)

    def cell_index(self, descriptors: jax.Array, xp=jnp) -> jax.Array:
        """(B, D) float32 descriptors -> (B,) int32 cell index, -1 if outside the bounds or not finite (jax or
        NumPy: the same cells)."""
        low = xp.asarray(self.low, xp.float32)
        high = xp.asarray(self.high, xp.float32)
        bins = xp.asarray(self.bins, xp.int32)
        inside = xp.all((descriptors >= low) & (descriptors <= high), axis=-1)
        scaled = quotient(descriptors - low, high - low, xp) * bins.astype(xp.float32)
        coords = xp.clip(xp.floor(scaled).astype(xp.int32), 0, bins - 1)
        strides = np.cumprod((1,) + self.bins[:0:-1])[::-1].astype(np.int32)  # row-major
        index = (coords * strides).sum(axis=-1, dtype=xp.int32)
        return xp.where(inside, index, -1)

    def cell_matches(self, descriptors: jax.Array, cells: jax.Array, tolerance: float = 1e-6) -> np.ndarray:
        """(B,) bool: `cells` is the cell of `descriptors`, up to `tolerance` either side of a bin edge (rounding);
        on the host (NumPy)."""
        descriptors = np.asarray(descriptors, np.float32)
        cells = np.asarray(cells)
        ok = np.zeros(cells.shape, bool)
        for shift in (0.0, -tolerance, tolerance):
            ok |= self.cell_index(descriptors + shift, xp=np) == cells
        return ok

    def add(self, repertoire: Repertoire, genotypes: jax.Array, evaluation: Evaluation):
        """Insert a batch; returns (new repertoire, Insertion)."""
        # The cell is computed from the stored float32 descriptors, not from a fused recomputation.
        cell = self.cell_index(jax.lax.optimization_barrier(evaluation.descriptors))
        ok = insertable(evaluation) & (cell >= 0)
        cell = jnp.where(ok, cell, self.capacity)  # rejected rows point past the last cell
        fitness = jnp.where(ok, evaluation.fitnesses, -jnp.inf)
        winner = best_per_target(fitness, cell, ok, self.capacity)
        incumbent = jnp.concatenate([repertoire.fitnesses, jnp.full((1,), jnp.inf)])[cell]
        accepted = winner & (fitness > incumbent)
        slot = jnp.where(accepted, cell, -1).astype(jnp.int32)
        was_filled = jnp.concatenate([repertoire.filled, jnp.ones((1,), bool)])[cell]
        new = write(repertoire, slot, genotypes, evaluation)
        return new, Insertion(accepted=accepted, new_slot=accepted & ~was_filled, slot=slot)
