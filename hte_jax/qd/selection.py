"""Parent selection: which elites get offspring. Functions, the objects emitters hold, the
registry of the selections `SelectionConfig.selection` can name, and their settings (`SelectionConfig`).

A selection object has `select(key, repertoire, num) -> (num,) int32 slots` of filled slots
(drawn with replacement) and a `from_config(config, container)` class method (config: a `SelectionConfig`).
"""

from __future__ import annotations

import dataclasses
import importlib

import jax
import jax.numpy as jnp

from hte_jax.errors import ConfigError, require_choice, require_int, require_number
from hte_jax.qd.repertoire import Repertoire

MAX_DENSITY_CELLS = 1 << 22

# name -> ("module:Class" of the selection object, the SelectionConfig fields it reads). The
# fields are recorded in checkpoints: uniform records none (not even `selection`), as before
# selection was a setting, so old checkpoints resume; a new entry should list "selection".
# A class is imported when first used: "frontier" is the hexapod's and lives in `hte_jax.hbr`.
SELECTIONS: dict[str, tuple[str, tuple[str, ...]]] = {
    "uniform": ("hte_jax.qd.selection:UniformSelection", ()),
    "density": ("hte_jax.qd.selection:DensitySelection", ("selection", "density_bins", "density_dims")),
    "frontier": (
        "hte_jax.hbr.selection:FrontierSelection",
        ("selection", "frontier_fraction", "frontier_angle_bins", "frontier_level_bins"),
    ),
}


@dataclasses.dataclass(frozen=True)
class SelectionConfig:
    """How parents are selected: the settings of the selections in `SELECTIONS` (inlined in
    `MapElitesConfig` and `hbr.training.LayerSchedule`: stored and overridden by these names).

    selection: "uniform" (every elite equally likely, the original's) or "density" (every occupied
      cell of a coarse `density_bins`^`density_dims` grid over the first `density_dims`
      descriptor dimensions, all of them if the container has fewer, equally likely;
      `density_selection`) or "frontier" (a share `frontier_fraction` of every batch drawn among
      the elites farthest from the centre of the plane of the first two descriptors, one per cell
      of `frontier_angle_bins` sectors x `frontier_level_bins` levels of the third descriptor, the
      rest uniformly; `hte_jax.hbr.selection`).
    """

    selection: str = "uniform"
    density_bins: int = 16
    density_dims: int = 3
    frontier_fraction: float = 0.5
    frontier_angle_bins: int = 16
    frontier_level_bins: int = 16

    def __post_init__(self):
        require_choice("selection", self.selection, SELECTIONS)
        require_int("density_bins", self.density_bins)
        require_int("density_dims", self.density_dims)
        if self.density_bins**self.density_dims > MAX_DENSITY_CELLS:
            raise ConfigError(
                f"density_bins^density_dims = {self.density_bins}^{self.density_dims} exceeds {MAX_DENSITY_CELLS} cells"
            )
        require_number("frontier_fraction", self.frontier_fraction, 0.0, 1.0)
        require_int("frontier_angle_bins", self.frontier_angle_bins)
        require_int("frontier_level_bins", self.frontier_level_bins)


def selection_from_config(config: SelectionConfig, container):
    """The selection object `config.selection` names, set up from `config` for `container`."""
    module, name = SELECTIONS[config.selection][0].split(":")
    return getattr(importlib.import_module(module), name).from_config(config, container)


def uniform_selection(key: jax.Array, repertoire: Repertoire, num: int) -> jax.Array:
    """(num,) slots drawn uniformly, with replacement, among the filled ones.

    Draws a rank r in [0, filled count) and returns the slot of the r-th filled slot
    (O(capacity + num log capacity), whatever the capacity). An empty repertoire has nothing
    to select: the caller must fill it first (MAP-Elites' initial random batch does).
    """
    return uniform_among(key, repertoire.filled, num)


def uniform_among(key: jax.Array, mask: jax.Array, num: int) -> jax.Array:
    """(num,) slots drawn uniformly, with replacement, among those where `mask` (C,) is True."""
    cumulative = jnp.cumsum(mask, dtype=jnp.int32)
    rank = jax.random.randint(key, (num,), 0, jnp.maximum(cumulative[-1], 1))
    return jnp.searchsorted(cumulative, rank + 1, side="left").astype(jnp.int32)


def density_selection(
    key: jax.Array, repertoire: Repertoire, num: int, low: jax.Array, high: jax.Array, bins: int, dims: int
) -> jax.Array:
    """(num,) filled slots drawn with replacement, each with probability proportional to 1 / (the
    number of elites in its coarse cell): every occupied cell of a `bins`^`dims` grid over the
    first `dims` descriptor dimensions (bounds low, high) is equally likely, then an elite within it.

    Elites in sparsely filled regions, such as the frontier of what the layer can do, are picked
    more often than under uniform selection, where densely filled regions (many elites with the
    same primary descriptor and other secondary ones) take most offspring.
    """
    low, high = jnp.asarray(low, jnp.float32)[:dims], jnp.asarray(high, jnp.float32)[:dims]
    scaled = (repertoire.descriptors[:, :dims] - low) / (high - low)
    index = jnp.clip(jnp.floor(scaled * bins), 0, bins - 1).astype(jnp.int32)
    cell = jnp.ravel_multi_index(tuple(index.T), (bins,) * dims, mode="clip")
    counts = jax.ops.segment_sum(repertoire.filled.astype(jnp.float32), cell, num_segments=bins**dims)
    weight = jnp.where(repertoire.filled, 1.0 / jnp.maximum(counts[cell], 1.0), 0.0)
    cumulative = jnp.cumsum(weight)
    draw = jax.random.uniform(key, (num,)) * cumulative[-1]
    slot = jnp.searchsorted(cumulative, draw, side="right")  # the first slot whose weight covers the draw
    last = repertoire.filled.shape[0] - 1 - jnp.argmax(repertoire.filled[::-1])  # float round-up guard
    return jnp.minimum(slot, last).astype(jnp.int32)


@dataclasses.dataclass(frozen=True)
class UniformSelection:
    """Every elite equally likely (the original's); `uniform_selection`."""

    @classmethod
    def from_config(cls, config, container) -> UniformSelection:
        return cls()

    def select(self, key: jax.Array, repertoire: Repertoire, num: int) -> jax.Array:
        return uniform_selection(key, repertoire, num)


@dataclasses.dataclass(frozen=True)
class DensitySelection:
    """Every occupied cell of a coarse `bins`^`dims` grid over the first `dims` descriptor
    dimensions (bounds low, high) equally likely; `density_selection`."""

    low: tuple[float, ...]
    high: tuple[float, ...]
    bins: int
    dims: int

    @classmethod
    def from_config(cls, config, container) -> DensitySelection:
        dims = min(config.density_dims, container.descriptor_dim)
        return cls(container.low, container.high, config.density_bins, dims)

    def select(self, key: jax.Array, repertoire: Repertoire, num: int) -> jax.Array:
        return density_selection(key, repertoire, num, self.low, self.high, self.bins, self.dims)
