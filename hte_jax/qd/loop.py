"""MAP-Elites as pure `init` / `ask` / `tell` functions, run in jitted blocks of generations with atomic checkpoints."""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from jax.sharding import Mesh
from tqdm.auto import tqdm

from hte_jax import sharding
from hte_jax.config import config_dict
from hte_jax.errors import ConfigError, check_fields, integer, number, require_int
from hte_jax.qd import io
from hte_jax.qd.emitters import Emitter, config_emitter
from hte_jax.qd.metrics import MetricsLog, RepertoireMetrics, repertoire_metrics
from hte_jax.qd.repertoire import Evaluation, Repertoire
from hte_jax.qd.task_spec import TaskSpec, container_metadata
from hte_jax.warp_calls import waited

# evaluate(key, genotypes (B, G)) -> Evaluation with B rows; must be jittable.
EvaluateFn = Callable[[jax.Array, jax.Array], Evaluation]


@dataclasses.dataclass(frozen=True)
class MapElitesConfig:
    """Hyper-parameters (hashable; the original's per layer in docs/design.md); a `MapElites` given its own emitter
    reads only batch_size, init_size and qd_offset."""

    batch_size: int = integer(200)  # offspring per generation
    init_size: int = integer(200)  # random individuals first, a multiple of batch_size
    mutation_rate: float = number(0.14, 0.0, 1.0)  # per gene, polynomial mutation
    eta_m: float = number(10.0, 0.0)
    crossover_rate: float = number(0.0, 0.0, 1.0)  # share of offspring made by SBX crossover
    eta_c: float = number(10.0, 0.0)
    qd_offset: float = number(0.0)  # fitness lower bound of the QD score

    def __post_init__(self):
        check_fields(self)
        if self.init_size % self.batch_size:
            raise ConfigError(f"init_size={self.init_size} must be a multiple of batch_size={self.batch_size}")


@struct.dataclass
class QDState:
    """Everything a run needs to continue: the container's repertoire, key (2,) uint32 (the next generation's),
    generation (int32 scalar, done after the initial batch), emitter_state (`emitters.EmptyState`: stateless)."""

    repertoire: Repertoire
    key: jax.Array
    generation: jax.Array
    emitter_state: Any


def spec_config(spec: TaskSpec, config: MapElitesConfig) -> MapElitesConfig:
    """`config` with the spec's qd_offset (if it has one); ConfigError if the spec has no evaluation."""
    if spec.evaluate is None:
        raise ConfigError(f"task {spec.name!r} has no evaluation; give it one with spec.with_evaluate(...)")
    return config if spec.qd_offset is None else dataclasses.replace(config, qd_offset=spec.qd_offset)


class OnMesh:
    """`active_mesh`, the `mesh` field or (None) all visible devices; `place`, a state replicated on it; and
    `run_block`, `generations` calls of `generation_step` (state -> (state, accepted)) under lax.scan."""

    @functools.cached_property
    def active_mesh(self) -> Mesh:
        return sharding.batch_mesh() if self.mesh is None else self.mesh

    def place(self, state: QDState) -> QDState:
        return sharding.put_replicated(state, self.active_mesh)

    @functools.partial(jax.jit, static_argnums=(0, 2))
    def run_block(self, state: QDState, generations: int) -> tuple[QDState, jax.Array]:
        """(state, total accepted), replicated on the mesh."""
        state, accepted = jax.lax.scan(lambda s, _: self.generation_step(s), state, None, length=generations)
        return sharding.replicate((state, accepted.sum()), self.active_mesh)


@dataclasses.dataclass(frozen=True, eq=False)
class MapElites(OnMesh):
    """A MAP-Elites algorithm: a container (`Grid` or `Archive`), an evaluation of genotype_dim genes in [0, 1]."""

    container: Any
    evaluate: EvaluateFn
    genotype_dim: int
    config: MapElitesConfig = MapElitesConfig()
    extras: Any = None  # example pytree of the evaluation's per-individual extras (shapes without B)
    emitter: Emitter | None = None  # None: the one `config` describes
    mesh: Mesh | None = None  # the devices a batch's rows are spread over (None: all); results do not depend on it

    @classmethod
    def from_spec(cls, spec: TaskSpec, config: MapElitesConfig = MapElitesConfig(), emitter: Emitter | None = None,
                  mesh: Mesh | None = None) -> MapElites:
        """The MAP-Elites of a task spec, `config` with the spec's qd_offset (`spec_config`)."""
        config = spec_config(spec, config)
        return cls(spec.container, spec.evaluate, spec.genotype_dim, config, spec.extras_example(), emitter, mesh)

    def evaluate_batch(self, key: jax.Array, genotypes: jax.Array) -> Evaluation:
        """`evaluate`, its rollouts' rows spread over the mesh (`sharding.spread_over`)."""
        with sharding.spread_over(self.active_mesh):
            return self.evaluate(key, genotypes)

    @functools.cached_property
    def active_emitter(self) -> Emitter:
        return config_emitter(self.config, self.container) if self.emitter is None else self.emitter

    def evaluations(self, state: QDState) -> int:
        """Evaluations done so far (host int)."""
        return self.config.init_size + int(state.generation) * self.config.batch_size

    def empty_state(self, key: jax.Array) -> QDState:
        """A state with an empty repertoire (also the template checkpoints are loaded into)."""
        repertoire = self.container.empty(self.genotype_dim, self.extras)
        return QDState(repertoire, key, jnp.int32(0), self.active_emitter.init(repertoire, key))

    @functools.partial(jax.jit, static_argnums=0)
    def init(self, key: jax.Array) -> QDState:
        """Evaluate init_size uniform random genotypes and insert them, batch by batch."""
        key, key_init = jax.random.split(key)
        state = self.empty_state(key)
        batches = self.config.init_size // self.config.batch_size

        def insert(repertoire, batch_key):
            key_genes, key_eval = jax.random.split(batch_key)
            genotypes = jax.random.uniform(key_genes, (self.config.batch_size, self.genotype_dim))
            repertoire, _ = self.container.add(repertoire, genotypes, self.evaluate_batch(key_eval, genotypes))
            return repertoire, None

        repertoire, _ = jax.lax.scan(insert, state.repertoire, jax.random.split(key_init, batches))
        key_emitter = jax.random.fold_in(key_init, 0)  # a key of its own: the batches' keys stay as they were
        emitter_state = self.active_emitter.init(repertoire, key_emitter)
        return sharding.replicate(state.replace(repertoire=repertoire, emitter_state=emitter_state), self.active_mesh)

    def ask(self, repertoire: Repertoire, emitter_state: Any, key: jax.Array) -> tuple[jax.Array, Any]:
        """(batch_size, G) offspring and the emitter's new state."""
        genotypes, emitter_state = self.active_emitter.emit(repertoire, emitter_state, key)
        if genotypes.shape != (self.config.batch_size, self.genotype_dim):
            raise ConfigError(f"the emitter made genotypes of shape {genotypes.shape}, expected (batch_size, "
                              f"genotype_dim) = {(self.config.batch_size, self.genotype_dim)}")
        return genotypes, emitter_state

    def tell(self, repertoire: Repertoire, emitter_state: Any, genotypes: jax.Array, evaluation: Evaluation):
        """Insert an evaluated batch and update the emitter: (repertoire, emitter state, Insertion)."""
        repertoire, insertion = self.container.add(repertoire, genotypes, evaluation)
        emitter_state = self.active_emitter.update(emitter_state, repertoire, genotypes, evaluation, insertion)
        return repertoire, emitter_state, insertion

    def generation_step(self, state: QDState) -> tuple[QDState, jax.Array]:
        """One generation; returns the new state and the number of accepted offspring."""
        key, key_ask, key_eval = jax.random.split(state.key, 3)
        genotypes, emitter_state = self.ask(state.repertoire, state.emitter_state, key_ask)
        evaluation = self.evaluate_batch(key_eval, genotypes)
        repertoire, emitter_state, insertion = self.tell(state.repertoire, emitter_state, genotypes, evaluation)
        new = QDState(repertoire=repertoire, key=key, generation=state.generation + 1, emitter_state=emitter_state)
        return new, insertion.accepted.sum(dtype=jnp.int32)

    @functools.partial(jax.jit, static_argnums=0)
    def metrics(self, state: QDState) -> RepertoireMetrics:
        return repertoire_metrics(state.repertoire, self.config.qd_offset)

    def checkpoint_metadata(self) -> dict:
        """What a resumed checkpoint must match."""
        metadata = {"container": container_metadata(self.container), "config": config_dict(self.config),
                    "genotype_dim": self.genotype_dim}
        if self.emitter is not None:
            metadata["emitter"] = repr(self.emitter)
        return metadata


def run(algo: MapElites, state: QDState, generations: int, *, block_size: int = 10, log_path: str | Path | None = None,
        checkpoint_path: str | Path | None = None, progress: bool = True,
        on_block: Callable[[int, QDState, dict], None] | None = None, description: str | None = None,
        started: float | None = None) -> QDState:
    """Run until `state.generation == generations` in jitted blocks (at multiples of block_size), each followed by a
    replica check, a CSV row, an atomic checkpoint (process 0), the progress bar and `on_block(block, state, row)`.
    A row's wall_time_s counts from `started` (a `time.perf_counter()`; default now), on from the last kept row's
    when the run resumes."""
    require_int("block_size", block_size)
    log = MetricsLog(log_path) if log_path is not None and jax.process_index() == 0 else None
    done = int(state.generation)
    earlier = 0.0  # seconds of the sessions before this one
    if log is not None:  # drop rows written after the checkpoint we start from
        log.truncate_after(done // block_size - 1 if done else -2)
        earlier = log.last_wall_time() if done else 0.0
    total_blocks = -(-generations // block_size)
    bar = tqdm(total=total_blocks, initial=done // block_size, disable=not progress, unit="block", desc=description)
    start = time.perf_counter() if started is None else started

    def record(block, accepted):
        metrics = jax.device_get(algo.metrics(state))
        row = {"block": block, "generation": int(state.generation), "evaluations": algo.evaluations(state),
               **dataclasses.asdict(metrics), "accepted": metrics.filled if accepted is None else accepted,
               "wall_time_s": earlier + time.perf_counter() - start}
        if log is not None:
            log.append(row)
        return metrics, row

    state = algo.place(state)
    if done == 0:
        record(-1, None)  # the initial random batch, as block -1
    while done < generations:
        block = done // block_size
        count = min(block_size * (block + 1), generations) - done
        state, accepted = waited(algo.run_block, state, count)
        sharding.check_replicas(state, what=f"block {block}: state")
        done = int(state.generation)
        metrics, row = record(block, accepted)
        if checkpoint_path is not None and jax.process_index() == 0:
            io.save_checkpoint(checkpoint_path, state, algo.checkpoint_metadata())
        bar.update(1)
        bar.set_postfix(filled=int(metrics.filled), qd=f"{float(metrics.qd_score):.4g}", max=f"{float(metrics.max_fitness):.3g}")
        if on_block is not None:
            on_block(block, state, row)
    bar.close()
    return state


def resume(algo: MapElites, checkpoint_path: str | Path) -> QDState:
    """Load a checkpoint written by `run` for this algorithm (clear error on any mismatch)."""
    return io.load_checkpoint(checkpoint_path, algo.empty_state(jax.random.PRNGKey(0)), algo.checkpoint_metadata())


def start_or_resume(algo: MapElites, key: jax.Array, checkpoint_path: str | Path, *, progress: bool = True,
                    description: str | None = None) -> QDState:
    """The state a `run` starts from: the checkpoint at checkpoint_path if there is one (`resume`),
    else `algo.init(key)`, whose compilation and initial batch (minutes on a CPU) show as a bar."""
    if Path(checkpoint_path).exists():
        return resume(algo, checkpoint_path)
    label = "initial batch" if description is None else f"{description}: initial batch"
    with tqdm(total=1, desc=label, unit="batch", disable=not progress, leave=False) as bar:
        state = waited(algo.init, key)
        bar.update()
    return state


def run_to_end(algo: MapElites, key: jax.Array, out_dir: Path, generations: int, block_size: int, *,
               progress: bool = True, on_block: Callable[[int, QDState, dict], None] | None = None,
               description: str | None = None, write: bool = True) -> QDState:
    """`start_or_resume` then `run` with out_dir/checkpoint.npz and out_dir/metrics.csv (its wall times counting
    the initial batch or the resume too); if no block ran (generations = 0), the checkpoint is written here (when
    `write`)."""
    checkpoint = out_dir / "checkpoint.npz"
    started = time.perf_counter()
    state = start_or_resume(algo, key, checkpoint, progress=progress, description=description)
    state = run(algo, state, generations, block_size=block_size, log_path=out_dir / "metrics.csv",
                checkpoint_path=checkpoint, progress=progress, on_block=on_block, description=description,
                started=started)
    if write and not checkpoint.exists():
        io.save_checkpoint(checkpoint, state, algo.checkpoint_metadata())
    return state


def layer_seconds(log_path: str | Path, began: float) -> float:
    """A trained layer's wall seconds over every session of its run: the last row of its metrics log (written by
    `run_to_end`, process 0), else those since `began` (a `time.perf_counter()` of this session)."""
    path = Path(log_path)
    return MetricsLog(path).last_wall_time() if path.exists() else time.perf_counter() - began
