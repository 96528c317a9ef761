"""The top layer's grid of 3 s skills, apart from its evaluation (`hbr.top`) so that the HBR and the
flat repertoires can hold it without importing the skill execution."""

from __future__ import annotations

import dataclasses

import jax

from hte_jax.errors import check_fields, integer, number
from hte_jax.qd.grid import Grid


@dataclasses.dataclass(frozen=True)
class TopTask:
    """The top layer's grid: `bins` x `bins` cells over [-extent, extent]^2 metres."""

    bins: int = integer(100)
    extent: float = number(1.5, 0.0, open_low=True)

    def __post_init__(self):
        check_fields(self, "top ")

    def grid(self) -> Grid:
        return Grid(bins=(self.bins, self.bins), low=(0.0, 0.0), high=(1.0, 1.0))

    def normalise(self, xy: jax.Array) -> jax.Array:
        return (xy + self.extent) / (2 * self.extent)

    def denormalise(self, descriptor: jax.Array) -> jax.Array:
        return descriptor * (2 * self.extent) - self.extent
