"""Training flat repertoires: the 2-D and 8-D baselines and APROL's 21 damaged repertoires.

Every variant is a `BatchedMapElites` over damages: one run ("none") for "2d" and "8d", the
21 single- and two-leg damages for "aprol", all in one jitted call per block of generations.
`train_flat(config, out_dir)` writes, under out_dir:
  config.json               the full configuration (a resumed run must match it)
  checkpoint.npz, metrics.csv   resumable state and per-block metrics (pooled over damages)
  repertoires.npz           the trained repertoires (`store.load_flat`)
  summary.json              per-damage elites, Table 2 statistics, wall time
  plots/*.png               x-y maps (one per damage for APROL) and metric curves
A killed run continues with `resume_run=True` and gives bit-identical repertoires for the same seed.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from hte_jax.config import config_dict, config_from_dict, inline
from hte_jax.config import with_overrides as _with_overrides
from hte_jax.errors import ConfigError, require_int, require_number
from hte_jax.flat.plots import plot_flat
from hte_jax.flat.store import FlatRepertoires, save_flat
from hte_jax.flat.task import QD_OFFSET, FlatTask, evaluate_flat, flat_spec
from hte_jax.qd import io
from hte_jax.qd.batched import BatchedMapElites
from hte_jax.qd.loop import MapElitesConfig, QDState, run, start_or_resume
from hte_jax.qd.metrics import projected_statistics
from hte_jax.sharding import mesh_size
from hte_jax.sim.damage import APROL_DAMAGES, damage_masks
from hte_jax.sim.mjx_import import require_impl
from hte_jax.sim.robot import RobotConfig, SolverConfig, load_robot, stored_solver
from hte_jax.sim.rollout import standing_state

with_overrides = _with_overrides  # the configurations' one override rule, re-exported

# variant -> (descriptor, damages the repertoires are trained on)
VARIANTS: dict[str, tuple[str, tuple[str, ...]]] = {
    "2d": ("2d", ("none",)),
    "8d": ("8d", ("none",)),
    "aprol": ("2d", tuple(APROL_DAMAGES)),
}


@dataclasses.dataclass(frozen=True)
class FlatConfig:
    """Everything that defines a trained set of flat repertoires.

    variant: "2d", "8d" or "aprol". batch_size / init_size / generations: per repertoire
    (init_size a multiple of batch_size). block_size: generations per jitted block (one progress
    tick, CSV row and checkpoint). mutation_rate / eta_m: polynomial mutation. seed: PRNG seed.
    bins: x-y cells per axis. contact_threshold: contact-bit threshold of the 8-D descriptor.
    solver: the physics' Newton solver and MJX implementation (`SolverConfig`, inlined: settings
    solver_iterations, ls_iterations, solver_tolerance, impl); a configuration stored without them
    ran 4 / 8 / 1e-8 on "jax" and resumes with that.
    """

    variant: str
    batch_size: int
    init_size: int
    generations: int
    block_size: int
    mutation_rate: float = 0.14
    eta_m: float = 10.0
    seed: int = 0
    bins: int = 100
    contact_threshold: float = 0.3
    solver: SolverConfig = inline(SolverConfig())

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ConfigError(f"variant must be one of {sorted(VARIANTS)}, got {self.variant!r}")
        require_int("generations", self.generations, minimum=0)
        require_int("block_size", self.block_size)
        require_int("seed", self.seed, minimum=0)
        require_number("eta_m", self.eta_m, 0.0)
        self.task  # noqa: B018 - validates bins and contact_threshold
        self.map_elites_config()  # validates batch, init and mutation
        if self.solver.impl == "warp" and len(self.damages) > 1:  # vmapped runs: Warp's contact buffer is per call
            raise ConfigError(f"impl='warp' runs one repertoire per call, not the {len(self.damages)} "
                              f"batched runs of variant {self.variant!r}: use impl='jax'")

    @property
    def robot(self) -> RobotConfig:
        """The simulated robot's options."""
        return self.solver.robot()

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
        return MapElitesConfig(
            batch_size=self.batch_size,
            init_size=self.init_size,
            mutation_rate=self.mutation_rate,
            eta_m=self.eta_m,
            qd_offset=QD_OFFSET,
        )

    def to_dict(self) -> dict:
        """The stored layout (`config.config_dict`: the solver's settings among the others)."""
        return config_dict(self)

    @classmethod
    def from_dict(cls, data: dict) -> FlatConfig:
        """A configuration from `to_dict`'s output or the nested layout of `dataclasses.asdict`;
        missing solver settings are the ones it ran with (`LEGACY_SOLVER`)."""
        return config_from_dict(cls, {**data, **stored_solver(data)})


def normalised_config(data: dict) -> dict:
    """A stored configuration read through today's FlatConfig (solver settings it lacks: `LEGACY_SOLVER`)."""
    return FlatConfig.from_dict(data).to_dict()


def _config(variant, batch, init, generations, block) -> FlatConfig:
    return FlatConfig(variant, batch, init, generations, block)


# Budgets: "2d" / "8d" match the HBR top layer's evaluations of the same preset (gpu: 16384 x 121,
# paper: 8000 x 501 = 4e6); "aprol" gives each of its 21 repertoires about 1/20 of that.
PRESETS: dict[str, dict[str, FlatConfig]] = {
    "tiny": {"2d": _config("2d", 16, 32, 2, 1), "8d": dataclasses.replace(_config("8d", 16, 32, 2, 1), bins=20),
             "aprol": _config("aprol", 4, 8, 1, 1)},
    "cpu": {"2d": _config("2d", 256, 512, 16, 4), "8d": _config("8d", 256, 512, 16, 4),
            "aprol": _config("aprol", 32, 64, 6, 2)},
    "gpu": {"2d": _config("2d", 16384, 16384, 120, 10), "8d": _config("8d", 16384, 16384, 120, 10),
            "aprol": _config("aprol", 1024, 1024, 96, 8)},
    "paper": {"2d": _config("2d", 8000, 8000, 500, 10), "8d": _config("8d", 8000, 8000, 500, 10),
              "aprol": _config("aprol", 1000, 1000, 199, 10)},
}


def preset(name: str, variant: str) -> FlatConfig:
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    if variant not in VARIANTS:
        raise ConfigError(f"unknown variant {variant!r}; choose one of {sorted(VARIANTS)}")
    return PRESETS[name][variant]


def flat_algorithm(config: FlatConfig, mesh: Mesh | None = None) -> BatchedMapElites:
    """The batched MAP-Elites of a configuration: one run per damage, each from its own standing state;
    every run's batch spread over `mesh` (None: all visible devices)."""
    robot = load_robot(config.robot)
    task = config.task
    masks = jnp.asarray(damage_masks(config.damages))
    conditions = {"damage": masks, "start": standing_state(robot, masks)}
    spec = flat_spec(task, evaluate=lambda key, genes, c: evaluate_flat(robot, task, c["start"], c["damage"], key, genes))
    return BatchedMapElites.from_spec(spec, conditions, config.damages, config.map_elites_config(), mesh=mesh)


@dataclasses.dataclass
class FlatOutcome:
    repertoires: FlatRepertoires
    summary: dict


def flat_statistics(flat: FlatRepertoires) -> dict:
    """Per damage: Table 2 statistics (`projected_statistics`) of each repertoire."""
    rep = jax.device_get(flat.repertoire)
    return {
        name: projected_statistics(rep.descriptors[r], rep.fitnesses[r], rep.filled[r], flat.task.bins)
        for r, name in enumerate(flat.damages)
    }


def train_flat(
    config: FlatConfig,
    out_dir: str | Path,
    *,
    resume_run: bool = False,
    progress: bool = True,
    on_block: Callable[[int, QDState, dict], None] | None = None,
    plots: bool = True,
    mesh: Mesh | None = None,
) -> FlatOutcome:
    """Train (or finish training) a variant's repertoires; see the module docstring for the outputs.
    mesh: the devices every generation is spread over (None: all visible); the repertoires do not
    depend on it. In a multi-process run only process 0 writes files."""
    writer = jax.process_index() == 0
    out = Path(out_dir)
    require_impl(config.robot.impl, jax.device_count() if mesh is None else mesh_size(mesh))  # before the run folder
    if writer:
        out = io.prepare_run_dir(out_dir, config.to_dict(), resume_run, normalise=normalised_config)
    algo = flat_algorithm(config, mesh)
    checkpoint = out / "checkpoint.npz"
    began = time.perf_counter()
    state = start_or_resume(algo, jax.random.PRNGKey(config.seed), checkpoint, progress=progress,
                            description=f"flat {config.variant}")
    state = run(
        algo,
        state,
        config.generations,
        block_size=config.block_size,
        log_path=out / "metrics.csv",
        checkpoint_path=checkpoint,
        progress=progress,
        on_block=on_block,
        description=f"flat {config.variant}",
    )
    if writer and not checkpoint.exists():  # no block ran (generations = 0)
        io.save_checkpoint(checkpoint, state, algo.checkpoint_metadata())
    flat = FlatRepertoires(task=config.task, damages=config.damages, repertoire=state.repertoire)
    statistics = flat_statistics(flat)
    summary = {
        "config": config.to_dict(),
        "evaluations": algo.evaluations(state),
        "wall_time_s": time.perf_counter() - began,
        "statistics": statistics,
        "elites": {name: s["size"] for name, s in statistics.items()},
        "mean_elites": float(np.mean([s["size"] for s in statistics.values()])),
        "devices": [str(d) for d in jax.devices()],
    }
    if not writer:
        return FlatOutcome(repertoires=flat, summary=summary)
    save_flat(out / "repertoires.npz", flat, {"training": summary})
    io.write_json(out / "summary.json", summary)
    if plots:
        plot_flat(flat, out / "metrics.csv", out / "plots")
    return FlatOutcome(repertoires=flat, summary=summary)
