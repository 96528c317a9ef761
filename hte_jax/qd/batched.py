"""Several independent MAP-Elites runs in one jitted call, `vmap`-ped over a per-run condition of the evaluation (a
damage, a task parameter): run r uses the keys of `single(r)` (vmapped physics may differ in the last bits); `QDState`
holds (R, ...) repertoires, (R, 2) keys, (R, ...) emitter states and one generation, so `loop.run` drives it."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jax.sharding import Mesh

from hte_jax import sharding
from hte_jax.errors import ConfigError
from hte_jax.qd.loop import MapElites, MapElitesConfig, OnMesh, QDState, spec_config
from hte_jax.qd.metrics import RepertoireMetrics, repertoire_metrics
from hte_jax.qd.repertoire import Evaluation
from hte_jax.qd.task_spec import TaskSpec

# evaluate(key, genotypes (B, G), condition) -> Evaluation with B rows; condition is one run's slice.
ConditionedEvaluateFn = Callable[[jax.Array, jax.Array, Any], Evaluation]

# vmap axes of a batched QDState: per-run repertoire, key and emitter state, shared generation counter.
_STATE_AXES = QDState(repertoire=0, key=0, generation=None, emitter_state=0)


@dataclasses.dataclass(frozen=True, eq=False)
class BatchedMapElites(OnMesh):
    """R MAP-Elites runs, one per condition; the fields as in `MapElites`."""

    container: Any
    evaluate: ConditionedEvaluateFn
    genotype_dim: int
    conditions: Any  # pytree of (R, ...) arrays, row r run r's
    names: tuple[str, ...]  # R labels (stored in checkpoints: a resume must use the same runs)
    config: MapElitesConfig = MapElitesConfig()
    extras: Any = None
    emitter: Any = None
    mesh: Mesh | None = None

    def __post_init__(self):
        sizes = {int(x.shape[0]) for x in jax.tree.leaves(self.conditions)}
        if sizes != {len(self.names)}:
            raise ConfigError(f"conditions must all have {len(self.names)} rows (one per name), got {sorted(sizes)}")

    @classmethod
    def from_spec(cls, spec: TaskSpec, conditions: Any, names: tuple[str, ...],
                  config: MapElitesConfig = MapElitesConfig(), emitter: Any = None, mesh: Mesh | None = None,
                  ) -> BatchedMapElites:
        """R runs of a spec whose evaluation takes the run's condition, `config` as in `MapElites.from_spec`."""
        config = spec_config(spec, config)
        return cls(spec.container, spec.evaluate, spec.genotype_dim, conditions, tuple(names), config,
                   spec.extras_example(), emitter, mesh)

    @property
    def num_runs(self) -> int:
        return len(self.names)

    def _algo(self, condition) -> MapElites:
        return MapElites(self.container, lambda key, genotypes: self.evaluate(key, genotypes, condition),
                         self.genotype_dim, self.config, self.extras, self.emitter, self.active_mesh)

    def single(self, run: int) -> MapElites:
        """Run `run` on its own (same keys as inside the batch: `run_keys(key)[run]`)."""
        return self._algo(jax.tree.map(lambda x: x[run], self.conditions))

    def run_keys(self, key: jax.Array) -> jax.Array:
        """(R, 2) the key each run's `init` receives."""
        return jax.random.split(key, self.num_runs)

    def evaluations(self, state: QDState) -> int:
        """Evaluations done so far over all runs (host int)."""
        return self.num_runs * (self.config.init_size + int(state.generation) * self.config.batch_size)

    def empty_state(self, key: jax.Array) -> QDState:
        one = self.single(0).empty_state(key)
        repertoire, emitter_state = jax.tree.map(
            lambda x: jnp.broadcast_to(x, (self.num_runs, *x.shape)), (one.repertoire, one.emitter_state))
        return QDState(repertoire=repertoire, key=self.run_keys(key), generation=jnp.int32(0), emitter_state=emitter_state)

    @functools.partial(jax.jit, static_argnums=0)
    def init(self, key: jax.Array) -> QDState:
        one = jax.vmap(lambda run_key, condition: self._algo(condition).init(run_key), out_axes=_STATE_AXES)
        state = one(self.run_keys(key), self.conditions)
        return sharding.replicate(state, self.active_mesh)

    def generation_step(self, state: QDState) -> tuple[QDState, jax.Array]:
        one = jax.vmap(lambda run_state, condition: self._algo(condition).generation_step(run_state),
                       in_axes=(_STATE_AXES, 0), out_axes=(_STATE_AXES, 0))
        new, accepted = one(state, self.conditions)
        return new, accepted.sum()

    @functools.partial(jax.jit, static_argnums=0)
    def metrics(self, state: QDState) -> RepertoireMetrics:
        """Metrics of all runs' elites pooled (coverage is the mean coverage)."""
        pooled = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), state.repertoire)
        return repertoire_metrics(pooled, self.config.qd_offset)

    def checkpoint_metadata(self) -> dict:
        return {**self.single(0).checkpoint_metadata(), "runs": list(self.names)}
