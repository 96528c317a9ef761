"""Emitters make each generation's offspring: `init(repertoire, key) -> state` after the initial batch (on an empty
repertoire: the checkpoint template), `emit(repertoire, state, key) -> (genotypes (B, G) in [0, 1], state)` and
`update(state, repertoire, genotypes, evaluation, insertion) -> state`; the state is a pytree kept in `QDState`."""

from __future__ import annotations

import abc
import dataclasses
from typing import Any

import jax
from flax import struct

from hte_jax.qd.repertoire import Evaluation, Insertion, Repertoire
from hte_jax.qd.selection import UniformSelection
from hte_jax.qd.variation import SbxPolynomial


@struct.dataclass
class EmptyState:
    """The state of a stateless emitter: no fields, so no checkpoint entries."""


class Emitter(abc.ABC):
    """Base of emitters: stateless unless `init` and `update` are overridden; `emit` is required."""

    def init(self, repertoire: Repertoire, key: jax.Array) -> Any:
        return EmptyState()

    @abc.abstractmethod
    def emit(self, repertoire: Repertoire, emitter_state: Any, key: jax.Array) -> tuple[jax.Array, Any]:
        """(genotypes (B, G), the new emitter state)."""

    def update(self, emitter_state: Any, repertoire: Repertoire, genotypes: jax.Array, evaluation: Evaluation,
               insertion: Insertion) -> Any:
        return emitter_state


@dataclasses.dataclass(frozen=True)
class VariationEmitter(Emitter):
    """`batch_size` children of `variation.vary(key, draw_parents)`, parents drawn by `selection.select`."""

    selection: Any
    variation: Any
    batch_size: int

    def select(self, repertoire: Repertoire, key: jax.Array) -> jax.Array:
        """(batch_size,) parent slots."""
        return self.selection.select(key, repertoire, self.batch_size)

    def emit(self, repertoire: Repertoire, emitter_state: Any, key: jax.Array) -> tuple[jax.Array, Any]:
        children = self.variation.vary(key, lambda k: repertoire.genotypes[self.select(repertoire, k)])
        return children, emitter_state


def config_emitter(config, container) -> VariationEmitter:
    """The emitter `MapElitesConfig` describes: uniform selection, SBX crossover and polynomial mutation."""
    return VariationEmitter(UniformSelection(), SbxPolynomial.from_config(config), config.batch_size)
