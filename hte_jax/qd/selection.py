"""Parent selection: objects with `select(key, repertoire, num) -> (num,) int32` filled slots, with replacement."""

from __future__ import annotations

import dataclasses
import importlib

import jax
import jax.numpy as jnp

from hte_jax.errors import ConfigError, check_fields, choice, integer, number
from hte_jax.qd.repertoire import Repertoire

MAX_DENSITY_CELLS = 1 << 22

# name -> ("module:Class", imported when first used, the SelectionConfig fields it reads, which checkpoints
# record). Uniform records none (not even `selection`) so that checkpoints older than the setting resume.
SELECTIONS: dict[str, tuple[str, tuple[str, ...]]] = {
    "uniform": ("hte_jax.qd.selection:UniformSelection", ()),
    "density": ("hte_jax.qd.selection:DensitySelection", ("selection", "density_bins", "density_dims")),
    "frontier": ("hte_jax.hbr.selection:FrontierSelection",
                 ("selection", "frontier_fraction", "frontier_angle_bins", "frontier_level_bins")),
}


@dataclasses.dataclass(frozen=True)
class SelectionConfig:
    """The settings of `SELECTIONS` (inlined in `MapElitesConfig` and `LayerSchedule`)."""

    # "uniform" (the original's), "density" (`density_selection` over a density_bins^density_dims grid) or "frontier"
    # (`hbr.selection`: a share frontier_fraction among the outermost elites of angle x level bins, the rest uniformly)
    selection: str = choice("uniform", SELECTIONS)
    density_bins: int = integer(16)
    density_dims: int = integer(3)
    frontier_fraction: float = number(0.5, 0.0, 1.0)
    frontier_angle_bins: int = integer(16)
    frontier_level_bins: int = integer(16)

    def __post_init__(self):
        check_fields(self)
        if self.density_bins**self.density_dims > MAX_DENSITY_CELLS:
            raise ConfigError(f"density_bins^density_dims = {self.density_bins}^{self.density_dims} exceeds "
                              f"{MAX_DENSITY_CELLS} cells")


def selection_from_config(config: SelectionConfig, container):
    """The selection object `config.selection` names, set up from `config` for `container`."""
    module, name = SELECTIONS[config.selection][0].split(":")
    return getattr(importlib.import_module(module), name).from_config(config, container)


def uniform_among(key: jax.Array, mask: jax.Array, num: int) -> jax.Array:
    """(num,) slots drawn uniformly, with replacement, among those where `mask` (C,) is True (by rank)."""
    cumulative = jnp.cumsum(mask, dtype=jnp.int32)
    rank = jax.random.randint(key, (num,), 0, jnp.maximum(cumulative[-1], 1))
    return jnp.searchsorted(cumulative, rank + 1, side="left").astype(jnp.int32)


def density_selection(key: jax.Array, repertoire: Repertoire, num: int, low: jax.Array, high: jax.Array, bins: int,
                      dims: int) -> jax.Array:
    """(num,) filled slots drawn with replacement, every occupied cell of a `bins`^`dims` grid over the first `dims`
    descriptor dimensions equally likely: sparse regions (a layer's frontier) get more offspring than uniformly."""
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
    """Every elite equally likely (the original's; there must be some)."""

    @classmethod
    def from_config(cls, config, container) -> UniformSelection:
        return cls()

    def select(self, key: jax.Array, repertoire: Repertoire, num: int) -> jax.Array:
        return uniform_among(key, repertoire.filled, num)


@dataclasses.dataclass(frozen=True)
class DensitySelection:
    """`density_selection`: every occupied cell of a `bins`^`dims` grid over [low, high] equally likely."""

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
