"""Training flat repertoires: the 2-D and 8-D baselines and APROL's 21 damaged ones, each variant one
`BatchedMapElites` over its damages. `train_flat` writes config.json, checkpoint.npz, metrics.csv, repertoires.npz
(`store.load_flat`), summary.json and plots/; a killed run resumes (`resume_run=True`) bit-identically."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from hte_jax.config import inline
from hte_jax.config import with_overrides as _with_overrides
from hte_jax.errors import ConfigError, check_fields, choice, integer, lookup, number
from hte_jax.flat.plots import plot_flat
from hte_jax.flat.store import FlatRepertoires, save_flat
from hte_jax.flat.task import QD_OFFSET, FlatTask, evaluate_flat, flat_spec
from hte_jax.hbr.training import StoredConfig
from hte_jax.qd import io
from hte_jax.qd.batched import BatchedMapElites
from hte_jax.qd.loop import MapElitesConfig, QDState, layer_seconds, run_to_end
from hte_jax.qd.metrics import projected_statistics
from hte_jax.sim.damage import APROL_DAMAGES, damage_masks
from hte_jax.sim.mjx_import import require_impl
from hte_jax.sim.robot import SolverConfig, load_robot
from hte_jax.sim.rollout import standing_state

with_overrides = _with_overrides  # the configurations' one override rule, re-exported

# variant -> (descriptor, damages the repertoires are trained on)
VARIANTS: dict[str, tuple[str, tuple[str, ...]]] = {"2d": ("2d", ("none",)), "8d": ("8d", ("none",)),
                                                    "aprol": ("2d", tuple(APROL_DAMAGES))}


@dataclasses.dataclass(frozen=True)
class FlatConfig(StoredConfig):
    """Everything that defines a trained set of flat repertoires: the variant, `LayerSchedule`'s settings
    per repertoire, `FlatTask`'s bins and contact_threshold, and the solver (as `HBRConfig`'s)."""

    variant: str = choice(dataclasses.MISSING, VARIANTS)
    batch_size: int
    init_size: int
    generations: int = integer(minimum=0)
    block_size: int = integer()
    mutation_rate: float = 0.14
    eta_m: float = number(10.0, 0.0)
    seed: int = integer(0, minimum=0)
    bins: int = 100
    contact_threshold: float = 0.3
    solver: SolverConfig = inline(SolverConfig())

    def __post_init__(self):
        check_fields(self)
        self.task  # noqa: B018 - validates bins and contact_threshold
        self.map_elites_config()  # validates batch, init and mutation
        if self.solver.impl == "warp" and len(self.damages) > 1:  # vmapped runs: Warp's contact buffer is per call
            raise ConfigError(f"impl='warp' runs one repertoire per call, not the {len(self.damages)} "
                              f"batched runs of variant {self.variant!r}: use impl='jax'")

    @property
    def task(self) -> FlatTask:
        return FlatTask(descriptor=VARIANTS[self.variant][0], bins=self.bins, contact_threshold=self.contact_threshold)

    @property
    def damages(self) -> tuple[str, ...]:
        return VARIANTS[self.variant][1]

    @property
    def evaluations(self) -> int:
        """Evaluations over all repertoires."""
        return len(self.damages) * (self.init_size + self.generations * self.batch_size)

    def map_elites_config(self) -> MapElitesConfig:
        return MapElitesConfig(batch_size=self.batch_size, init_size=self.init_size, mutation_rate=self.mutation_rate,
                               eta_m=self.eta_m, qd_offset=QD_OFFSET)


def normalised_config(data: dict) -> dict:
    """A stored configuration read through today's FlatConfig (solver settings it lacks: `LEGACY_SOLVER`)."""
    return FlatConfig.from_dict(data).to_dict()


# Budgets: "2d" / "8d" match the HBR top layer's evaluations of the same preset (gpu: 16384 x 121,
# paper: 8000 x 501 = 4e6); "aprol" gives each of its 21 repertoires about 1/20 of that.
PRESETS: dict[str, dict[str, FlatConfig]] = {
    "tiny": {"2d": FlatConfig("2d", 16, 32, 2, 1), "8d": FlatConfig("8d", 16, 32, 2, 1, bins=20),
             "aprol": FlatConfig("aprol", 4, 8, 1, 1)},
    "cpu": {"2d": FlatConfig("2d", 256, 512, 16, 4), "8d": FlatConfig("8d", 256, 512, 16, 4),
            "aprol": FlatConfig("aprol", 32, 64, 6, 2)},
    "gpu": {"2d": FlatConfig("2d", 16384, 16384, 120, 10), "8d": FlatConfig("8d", 16384, 16384, 120, 10),
            "aprol": FlatConfig("aprol", 1024, 1024, 96, 8)},
    "paper": {"2d": FlatConfig("2d", 8000, 8000, 500, 10), "8d": FlatConfig("8d", 8000, 8000, 500, 10),
              "aprol": FlatConfig("aprol", 1000, 1000, 199, 10)},
}


def preset(name: str, variant: str) -> FlatConfig:
    return lookup("variant", variant, lookup("preset", name, PRESETS))


def flat_algorithm(config: FlatConfig, mesh: Mesh | None = None) -> BatchedMapElites:
    """The batched MAP-Elites of a configuration: one run per damage from its own standing state, spread over `mesh`."""
    robot = load_robot(config.robot)
    task = config.task
    masks = jnp.asarray(damage_masks(config.damages))
    conditions = {"damage": masks, "start": standing_state(robot, masks)}
    spec = flat_spec(task, evaluate=lambda key, genes, condition: evaluate_flat(
        robot, task, condition["start"], condition["damage"], key, genes))
    return BatchedMapElites.from_spec(spec, conditions, config.damages, config.map_elites_config(), mesh=mesh)


@dataclasses.dataclass
class FlatOutcome:
    repertoires: FlatRepertoires
    summary: dict


def flat_statistics(flat: FlatRepertoires) -> dict:
    """Per damage: Table 2 statistics (`projected_statistics`) of each repertoire."""
    rep = jax.device_get(flat.repertoire)
    return {name: projected_statistics(rep.descriptors[r], rep.fitnesses[r], rep.filled[r], flat.task.bins)
            for r, name in enumerate(flat.damages)}


def train_flat(config: FlatConfig, out_dir: str | Path, *, resume_run: bool = False, progress: bool = True,
               on_block: Callable[[int, QDState, dict], None] | None = None, plots: bool = True,
               mesh: Mesh | None = None) -> FlatOutcome:
    """Train (or finish training) a variant's repertoires (see the module docstring), spread over `mesh` (None:
    all devices; the results do not depend on it). In a multi-process run only process 0 writes files."""
    writer = jax.process_index() == 0
    out = Path(out_dir)
    require_impl(config.robot.impl)  # before the run folder is made: a missing extra writes nothing
    out = io.prepare_run_dir(out, config.to_dict(), resume_run, normalise=normalised_config)
    algo = flat_algorithm(config, mesh)
    began = time.perf_counter()
    state = run_to_end(algo, jax.random.PRNGKey(config.seed), out, config.generations, config.block_size,
                       progress=progress, on_block=on_block, description=f"flat {config.variant}", write=writer)
    flat = FlatRepertoires(task=config.task, damages=config.damages, repertoire=state.repertoire)
    statistics = flat_statistics(flat)
    summary = {"config": config.to_dict(), "evaluations": algo.evaluations(state),
               "wall_time_s": layer_seconds(out / "metrics.csv", began), "statistics": statistics,
               "elites": {name: s["size"] for name, s in statistics.items()},
               "mean_elites": float(np.mean([s["size"] for s in statistics.values()])),
               "devices": [str(d) for d in jax.devices()]}
    if writer:
        save_flat(out / "repertoires.npz", flat, {"training": summary})
        io.write_json(out / "summary.json", summary)
        if plots:
            plot_flat(flat, out / "metrics.csv", out / "plots")
    return FlatOutcome(repertoires=flat, summary=summary)
