"""Frontier selection: parents from the outer shell of the hexapod's displacement descriptors.

Registered in `hte_jax.qd.selection.SELECTIONS` as "frontier", so `SelectionConfig(selection=
"frontier")` (a `MapElitesConfig`'s or an HBR `LayerSchedule`'s parents; setting "selection") picks it.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from hte_jax.errors import ConfigError
from hte_jax.qd.repertoire import Repertoire
from hte_jax.qd.selection import uniform_among


def frontier_elites(
    repertoire: Repertoire, low: jax.Array, high: jax.Array, angle_bins: int, level_bins: int
) -> jax.Array:
    """(C,) bool: the elites farthest from the centre of the plane of descriptor dimensions 0 and 1.

    Descriptors are scaled to [0, 1] by (low, high); the plane around (0.5, 0.5) is cut into
    `angle_bins` equal sectors and, when the container has a third dimension, its range into
    `level_bins` equal levels. In every occupied (sector, level) cell the elite at the largest
    distance from the centre is marked (ties to the lowest slot). For displacement descriptors
    (x, y[, yaw]) these are the fastest motions in every direction [at every turn rate]: the
    outer shell of what the repertoire can do.
    """
    low, high = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
    scaled = (repertoire.descriptors - low) / (high - low)
    offset = scaled[:, :2] - 0.5
    radius = jnp.linalg.norm(offset, axis=-1)
    angle = jnp.arctan2(offset[:, 1], offset[:, 0])  # (-pi, pi]
    sector = jnp.clip(jnp.floor((angle + jnp.pi) / (2 * jnp.pi) * angle_bins), 0, angle_bins - 1).astype(jnp.int32)
    if scaled.shape[1] > 2 and level_bins > 1:
        level = jnp.clip(jnp.floor(scaled[:, 2] * level_bins), 0, level_bins - 1).astype(jnp.int32)
    else:
        level = jnp.zeros_like(sector)
    cell = sector * level_bins + level
    cells = angle_bins * level_bins
    radius = jnp.where(repertoire.filled, radius, -1.0)
    farthest = jax.ops.segment_max(radius, cell, num_segments=cells)
    slots = jnp.arange(radius.shape[0], dtype=jnp.int32)
    is_max = repertoire.filled & (radius == farthest[cell])
    first = jax.ops.segment_min(jnp.where(is_max, slots, radius.shape[0]), cell, num_segments=cells)
    return repertoire.filled & (slots == first[cell])


def frontier_selection(
    key: jax.Array,
    repertoire: Repertoire,
    num: int,
    low: jax.Array,
    high: jax.Array,
    angle_bins: int,
    level_bins: int,
    fraction: float,
) -> jax.Array:
    """(num,) filled slots: the first round(fraction * num) drawn uniformly among the
    `frontier_elites`, the rest uniformly among all elites (with replacement).

    Uniform selection gives the few elites on the edge of the descriptor space a tiny share of
    the offspring, so the edge moves outwards by novelty alone, slowly. Here a fixed share of
    every batch is spent on exactly those elites; the rest keeps filling the interior.
    """
    edge = min(num, int(round(fraction * num)))
    key_edge, key_rest = jax.random.split(key)
    mask = frontier_elites(repertoire, low, high, angle_bins, level_bins)
    return jnp.concatenate(
        [uniform_among(key_edge, mask, edge), uniform_among(key_rest, repertoire.filled, num - edge)]
    )


@dataclasses.dataclass(frozen=True)
class FrontierSelection:
    """A share `fraction` of every batch among the `frontier_elites` (`angle_bins` sectors x
    `level_bins` levels, bounds low, high), the rest uniformly; `frontier_selection`."""

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
        return frontier_selection(
            key, repertoire, num, self.low, self.high, self.angle_bins, self.level_bins, self.fraction
        )
