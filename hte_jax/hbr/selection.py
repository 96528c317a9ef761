"""Frontier selection: parents from the outer shell of the hexapod's displacement descriptors
("frontier" in `qd.selection.SELECTIONS`, picked by `SelectionConfig(selection="frontier")`)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from hte_jax.errors import ConfigError
from hte_jax.qd.repertoire import Repertoire
from hte_jax.qd.selection import uniform_among


def frontier_elites(repertoire: Repertoire, low: jax.Array, high: jax.Array, angle_bins: int,
                    level_bins: int) -> jax.Array:
    """(C,) bool: in every cell of `angle_bins` sectors around (0.5, 0.5) of descriptors 0 and 1 (scaled
    to [0, 1] by low, high) x `level_bins` levels of descriptor 2 (if any), the elite farthest from the
    centre (ties to the lowest slot): for (x, y[, yaw]) the fastest motions in every direction."""
    low, high = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
    scaled = (repertoire.descriptors - low) / (high - low)
    offset = scaled[:, :2] - 0.5
    angle = jnp.arctan2(offset[:, 1], offset[:, 0])  # (-pi, pi]
    sector = jnp.clip(jnp.floor((angle + jnp.pi) / (2 * jnp.pi) * angle_bins), 0, angle_bins - 1).astype(jnp.int32)
    if scaled.shape[1] > 2 and level_bins > 1:
        level = jnp.clip(jnp.floor(scaled[:, 2] * level_bins), 0, level_bins - 1).astype(jnp.int32)
    else:
        level = jnp.zeros_like(sector)
    cell = sector * level_bins + level
    cells = angle_bins * level_bins
    radius = jnp.where(repertoire.filled, jnp.linalg.norm(offset, axis=-1), -1.0)
    farthest = jax.ops.segment_max(radius, cell, num_segments=cells)
    slots = jnp.arange(radius.shape[0], dtype=jnp.int32)
    is_max = repertoire.filled & (radius == farthest[cell])
    first = jax.ops.segment_min(jnp.where(is_max, slots, radius.shape[0]), cell, num_segments=cells)
    return repertoire.filled & (slots == first[cell])


def frontier_selection(key: jax.Array, repertoire: Repertoire, num: int, low: jax.Array, high: jax.Array,
                       angle_bins: int, level_bins: int, fraction: float) -> jax.Array:
    """(num,) filled slots: the first round(fraction * num) uniformly among the `frontier_elites` (whom
    uniform selection gives a tiny share), the rest uniformly among all elites (with replacement)."""
    edge = min(num, int(round(fraction * num)))
    key_edge, key_rest = jax.random.split(key)
    mask = frontier_elites(repertoire, low, high, angle_bins, level_bins)
    return jnp.concatenate([uniform_among(key_edge, mask, edge),
                            uniform_among(key_rest, repertoire.filled, num - edge)])


@dataclasses.dataclass(frozen=True)
class FrontierSelection:
    """`frontier_selection` with its settings, bounds from the container."""

    low: tuple[float, ...]
    high: tuple[float, ...]
    angle_bins: int
    level_bins: int
    fraction: float

    @classmethod
    def from_config(cls, config, container) -> FrontierSelection:
        return cls(container.low, container.high, config.frontier_angle_bins, config.frontier_level_bins,
                   config.frontier_fraction)

    def select(self, key: jax.Array, repertoire: Repertoire, num: int) -> jax.Array:
        if repertoire.descriptors.shape[-1] < 2:
            raise ConfigError("selection='frontier' needs a container with at least 2 descriptor dimensions")
        return frontier_selection(key, repertoire, num, self.low, self.high, self.angle_bins, self.level_bins,
                                  self.fraction)
