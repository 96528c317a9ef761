"""Training an HBR: bottom, then middle, then top, each a resumable MAP-Elites run.

`train_hbr(config, out_dir)` writes, under out_dir:
  config.json                      the full configuration (a resumed run must match it)
  <layer>/checkpoint.npz, metrics.csv   per layer (bottom, middle, top)
  hbr.npz                          the trained repertoire (`store.load_hbr`)
  summary.json                     per-layer metrics, evaluations and wall times
  plots/*.png                      maps of every layer and metric curves
A killed run continues with `resume=True` from the last block of the layer it was in and gives
bit-identical repertoires for the same seed.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
from jax.sharding import Mesh

from hte_jax.config import config_dict, config_from_dict, inline
from hte_jax.config import with_overrides as _with_overrides
from hte_jax.errors import ConfigError, require_choice, require_int, require_number
from hte_jax.hbr import bottom as bottom_layer
from hte_jax.hbr import middle as middle_layer
from hte_jax.hbr.analysis import hbr_statistics
from hte_jax.hbr.bottom import BOTTOM_FITNESSES, BottomTask, bottom_spec, evaluate_bottom
from hte_jax.hbr.composition import measure_steps
from hte_jax.hbr.hierarchy import HBR
from hte_jax.hbr.middle import PRIMARY, MiddleTask, elite_controllers, evaluate_middle, middle_spec, pattern_code
from hte_jax.hbr.plots import plot_hbr
from hte_jax.hbr.spare import SPARE_L, SPARE_STREAM, STRICT_CONTACT
from hte_jax.hbr.store import SPARE_FILE, bottom_fingerprint, save_hbr, save_spare
from hte_jax.hbr.top import TopTask, evaluate_top, top_spec
from hte_jax.qd import io
from hte_jax.qd.loop import MapElites, MapElitesConfig, QDState, run, start_or_resume
from hte_jax.qd.selection import SelectionConfig
from hte_jax.sharding import mesh_size
from hte_jax.sim.mjx_import import require_impl
from hte_jax.sim.robot import Robot, RobotConfig, SolverConfig, load_robot, stored_solver
from hte_jax.sim.rollout import standing_state

with_overrides = _with_overrides  # the configurations' one override rule, re-exported

LAYERS = ("bottom", "middle", "top")


@dataclasses.dataclass(frozen=True)
class LayerSchedule:
    """MAP-Elites budget and variation of one layer.

    batch_size: offspring per generation; init_size: random individuals first (a multiple of
    batch_size); generations: after the initial batch; block_size: generations per jitted block
    (one progress tick, CSV row and checkpoint each); mutation_rate / eta_m: polynomial mutation;
    capacity: archive slots (bottom and middle; the top layer is a fixed grid).
    parents: parent selection (`qd.selection.SelectionConfig`, inlined: settings selection
    ("uniform", the original's, "density" or "frontier"), density_bins, density_dims,
    frontier_fraction, frontier_angle_bins, frontier_level_bins).
    """

    batch_size: int
    init_size: int
    generations: int
    block_size: int
    mutation_rate: float
    eta_m: float = 10.0
    capacity: int = 1
    parents: SelectionConfig = inline(SelectionConfig())

    def __post_init__(self):
        require_int("generations", self.generations, minimum=0)
        require_int("block_size", self.block_size)
        require_int("capacity", self.capacity)
        self.map_elites_config(qd_offset=0.0)  # batch, init size and mutation checks live there

    @property
    def evaluations(self) -> int:
        return self.init_size + self.generations * self.batch_size

    def map_elites_config(self, qd_offset: float) -> MapElitesConfig:
        """The MapElitesConfig of this layer: its batch, variation and parent selection, and `qd_offset`."""
        return MapElitesConfig(batch_size=self.batch_size, init_size=self.init_size, mutation_rate=self.mutation_rate,
                               eta_m=self.eta_m, qd_offset=qd_offset, parents=self.parents)


@dataclasses.dataclass(frozen=True)
class HBRConfig:
    """Everything that defines a trained HBR (the paper's values are in docs/design.md).

    bottom / middle / top: the layers' schedules. seed: PRNG seed.
    middle_samples: chained 1 s samples per middle evaluation (original 10).
    contact_threshold: fraction of a second a foot must be down for its contact bit.
    contact_purity: middle fitness penalty per unit of contact on the legs a pattern lifts (0: the
      paper's fitness; `MiddleTask.purity`).
    bottom_l / middle_l: archive distance thresholds. top_bins: grid cells per axis.
    bottom_fitness: "commands" (measured joint commands) or "genes" (the original's gene sum).
    solver: the physics' Newton solver and MJX implementation (`SolverConfig`, inlined: settings
      solver_iterations, ls_iterations, solver_tolerance, impl); a configuration stored without them
      ran 4 / 8 / 1e-8 on "jax" and resumes with that.
    step_starts: start states from which every middle elite's step is measured once the layers
      are trained (`composition.measure_steps`, stored in hbr.npz); 0: no step model.
    step_chunk: samples per jitted rollout of the step model (memory; on a CPU the block's size
      also sets the last bits of its steps).
    """

    bottom: LayerSchedule
    middle: LayerSchedule
    top: LayerSchedule
    seed: int = 0
    middle_samples: int = 10
    contact_threshold: float = 0.3
    contact_purity: float = 0.0
    bottom_l: float = bottom_layer.ARCHIVE_L
    middle_l: float = middle_layer.ARCHIVE_L
    top_bins: int = 100
    bottom_fitness: str = "commands"
    solver: SolverConfig = inline(SolverConfig())
    step_starts: int = 8
    step_chunk: int = 8192

    def __post_init__(self):
        require_int("seed", self.seed, minimum=0)
        require_int("middle_samples", self.middle_samples)
        require_int("step_starts", self.step_starts, minimum=0)
        require_int("step_chunk", self.step_chunk)
        require_number("contact_threshold", self.contact_threshold, 0.0, 1.0)
        require_number("contact_purity", self.contact_purity, 0.0)
        require_number("bottom_l", self.bottom_l, 0.0, open_low=True)
        require_number("middle_l", self.middle_l, 0.0, open_low=True)
        require_int("top_bins", self.top_bins)
        require_choice("bottom_fitness", self.bottom_fitness, BOTTOM_FITNESSES)

    @property
    def robot(self) -> RobotConfig:
        """The simulated robot's options."""
        return self.solver.robot()

    @property
    def bottom_task(self) -> BottomTask:
        return BottomTask(fitness=self.bottom_fitness)

    @property
    def middle_task(self) -> MiddleTask:
        return MiddleTask(samples=self.middle_samples, contact_threshold=self.contact_threshold,
                          purity=self.contact_purity)

    @property
    def top_task(self) -> TopTask:
        return TopTask(bins=self.top_bins)

    def to_dict(self) -> dict:
        """The stored layout (`config.config_dict`: the solver's settings among the others)."""
        return config_dict(self)

    @classmethod
    def from_dict(cls, data: dict) -> HBRConfig:
        """A configuration from `to_dict`'s output or the nested layout of `dataclasses.asdict`;
        missing solver settings are the ones it ran with (`LEGACY_SOLVER`)."""
        return config_from_dict(cls, {**data, **stored_solver(data)})


def _schedule(batch, init, generations, block, mutation, capacity=1) -> LayerSchedule:
    return LayerSchedule(batch, init, generations, block, mutation, capacity=capacity)


# Mutation rates are the paper's (Table 1): 0.17 bottom, 0.11 middle, 0.14 top; eta_m = 10.
PRESETS: dict[str, HBRConfig] = {
    # CI: all three layers end to end in seconds of compute (plus compilation).
    "tiny": HBRConfig(
        bottom=_schedule(16, 32, 2, 1, 0.17, capacity=256),
        middle=_schedule(16, 32, 2, 1, 0.11, capacity=256),
        top=_schedule(16, 32, 2, 1, 0.14),
        middle_samples=2,
        step_starts=2,
    ),
    # The default: a usable small HBR on a 2-core CPU in about 15 minutes.
    "cpu": HBRConfig(
        bottom=_schedule(256, 512, 8, 4, 0.17, capacity=2048),
        middle=_schedule(256, 512, 14, 2, 0.11, capacity=8192),
        top=_schedule(256, 512, 14, 2, 0.14),
        middle_samples=3,
    ),
    # One H100 / H200 in about 10 minutes.
    "gpu": HBRConfig(
        bottom=_schedule(16384, 16384, 16, 8, 0.17, capacity=16384),
        middle=_schedule(32768, 32768, 36, 4, 0.11, capacity=65536),
        top=_schedule(16384, 16384, 120, 10, 0.14),
        middle_samples=5,
    ),
    # The paper's evaluation counts (5001 / 30000 / 20000 generations of 200) in batches of 8000.
    "paper": HBRConfig(
        bottom=_schedule(8000, 8000, 125, 5, 0.17, capacity=32768),
        middle=_schedule(8000, 8000, 750, 10, 0.11, capacity=131072),
        top=_schedule(8000, 8000, 500, 10, 0.14),
        middle_samples=10,
    ),
}


def normalised_config(data: dict) -> dict:
    """A stored configuration read through today's HBRConfig: settings added since take their defaults,
    except the solver settings, which take the values such runs were trained with (`LEGACY_SOLVER`)."""
    return HBRConfig.from_dict(data).to_dict()


def preset(name: str) -> HBRConfig:
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return PRESETS[name]


def layer_algorithms(config: HBRConfig, robot: Robot, start, lower: dict,
                     mesh: Mesh | None = None) -> dict[str, Callable[[], MapElites]]:
    """Factories of each layer's MapElites; `lower` holds the already trained layers' repertoires.
    mesh: the devices each generation's batch is spread over (`sharding.batch_mesh`; None: all)."""

    def bottom() -> MapElites:
        task = config.bottom_task
        spec = bottom_spec(config.bottom.capacity, config.bottom_l,
                           evaluate=lambda key, genes: evaluate_bottom(robot, start, task, key, genes))
        return MapElites.from_spec(spec, config.bottom.map_elites_config(qd_offset=spec.qd_offset), mesh=mesh)

    def middle() -> MapElites:
        task, repertoire = config.middle_task, lower["bottom"]
        spec = middle_spec(config.middle.capacity, config.middle_l,
                           evaluate=lambda key, genes: evaluate_middle(robot, start, task, repertoire, key, genes))
        return MapElites.from_spec(spec, config.middle.map_elites_config(qd_offset=spec.qd_offset), mesh=mesh)

    def top() -> MapElites:
        task = config.top_task
        empty_top = top_spec(task).empty()
        hbr = HBR.build(lower["bottom"], lower["middle"], empty_top, config.middle_task, top_task=task)
        spec = top_spec(task, evaluate=lambda key, genes: evaluate_top(robot, start, task, hbr, key, genes))
        return MapElites.from_spec(spec, config.top.map_elites_config(qd_offset=spec.qd_offset), mesh=mesh)

    return {"bottom": bottom, "middle": middle, "top": top}


@dataclasses.dataclass
class TrainingOutcome:
    hbr: HBR
    summary: dict


def train_hbr(
    config: HBRConfig,
    out_dir: str | Path,
    *,
    resume_run: bool = False,
    progress: bool = True,
    on_block: Callable[[str, int, QDState, dict], None] | None = None,
    plots: bool = True,
    mesh: Mesh | None = None,
) -> TrainingOutcome:
    """Train (or finish training) the three layers; see the module docstring for the outputs.
    mesh: the devices every generation is spread over (None: all visible); the repertoires do not
    depend on it. In a multi-process run only process 0 writes files."""
    out = Path(out_dir)
    writer = jax.process_index() == 0
    require_impl(config.robot.impl, jax.device_count() if mesh is None else mesh_size(mesh))  # before the run folder
    if writer:
        io.prepare_run_dir(out, config.to_dict(), resume_run, normalise=normalised_config)
    robot = load_robot(config.robot)
    start = standing_state(robot)
    keys = dict(zip(LAYERS, jax.random.split(jax.random.PRNGKey(config.seed), len(LAYERS))))
    lower: dict = {}
    summary: dict = {"config": config.to_dict(), "layers": {}}
    for layer in LAYERS:
        algo = layer_algorithms(config, robot, start, lower, mesh)[layer]()
        schedule: LayerSchedule = getattr(config, layer)
        checkpoint = out / layer / "checkpoint.npz"
        began = time.perf_counter()
        state = start_or_resume(algo, keys[layer], checkpoint, progress=progress, description=layer)
        hook = None if on_block is None else (lambda block, st, row, _layer=layer: on_block(_layer, block, st, row))
        state = run(
            algo,
            state,
            schedule.generations,
            block_size=schedule.block_size,
            log_path=out / layer / "metrics.csv",
            checkpoint_path=checkpoint,
            progress=progress,
            on_block=hook,
            description=layer,
        )
        if writer and not checkpoint.exists():  # no block ran (generations = 0)
            io.save_checkpoint(checkpoint, state, algo.checkpoint_metadata())
        metrics = jax.device_get(algo.metrics(state))
        lower[layer] = state.repertoire
        summary["layers"][layer] = {
            "evaluations": algo.evaluations(state),
            "filled": int(metrics.filled),
            "capacity": state.repertoire.capacity,
            "mean_fitness": float(metrics.mean_fitness),
            "max_fitness": float(metrics.max_fitness),
            "qd_score": float(metrics.qd_score),
            "wall_time_s": time.perf_counter() - began,
        }
    hbr = HBR.build(lower["bottom"], lower["middle"], lower["top"], config.middle_task, top_task=config.top_task)
    if config.step_starts:
        began = time.perf_counter()
        key = jax.random.fold_in(jax.random.PRNGKey(config.seed), len(LAYERS))
        model = measure_steps(robot, hbr.middle_params, hbr.middle.filled, config.middle_task, start, key,
                              starts=config.step_starts, chunk=config.step_chunk, mesh=mesh, progress=progress)
        hbr = hbr.replace(step_model=model)
        summary["step_model"] = {"starts": config.step_starts, "wall_time_s": time.perf_counter() - began}
    summary["statistics"] = hbr_statistics(hbr, config.top_task)
    summary["devices"] = [str(d) for d in jax.devices()]
    if not writer:
        return TrainingOutcome(hbr=hbr, summary=summary)
    save_hbr(out / "hbr.npz", hbr, metadata={"training": summary})
    io.write_json(out / "summary.json", summary)
    if plots:
        plot_hbr(hbr, config.top_task, out, out / "plots")
    return TrainingOutcome(hbr=hbr, summary=summary)


def _normalised_spare(stored: dict) -> dict:
    """A spare run's stored configuration with its HBR configuration read through today's (settings added since)."""
    return {**stored, "hbr_config": normalised_config(stored["hbr_config"])} if "hbr_config" in stored else stored


def train_spare(hbr: HBR, base: HBRConfig, out_dir: str | Path, *, threshold: float = STRICT_CONTACT,
                l: float = SPARE_L, resume_run: bool = False, progress: bool = True) -> dict:
    """Train a second middle archive for `hbr`'s spare sets (`hbr.spare`): its middle layer's task and budget
    (`base.middle`, samples, solver) at contact threshold `threshold` and distance threshold `l`, on
    the HBR's own bottom layer; then measure its steps (`base.step_starts`). Writes the run folder
    (config.json, middle/ checkpoint and metrics, spare.npz, summary.json; a killed run resumes)
    and returns the summary."""
    config = dataclasses.replace(base, contact_threshold=threshold, middle_l=l, contact_purity=0.0)
    out = Path(out_dir)
    require_impl(config.robot.impl, jax.device_count())  # before the run folder is made: a missing extra writes nothing
    io.prepare_run_dir(out, {"hbr_config": config.to_dict(), "bottom": bottom_fingerprint(hbr)}, resume_run,
                       normalise=_normalised_spare)
    robot = load_robot(config.robot)
    start = standing_state(robot)
    algo = layer_algorithms(config, robot, start, {"bottom": hbr.bottom})["middle"]()
    key, step_key = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(config.seed), SPARE_STREAM))
    checkpoint = out / "middle" / "checkpoint.npz"
    began = time.perf_counter()
    state = start_or_resume(algo, key, checkpoint, progress=progress, description="spare")
    state = run(algo, state, config.middle.generations, block_size=config.middle.block_size,
                log_path=out / "middle" / "metrics.csv", checkpoint_path=checkpoint, progress=progress,
                description="spare")
    if not checkpoint.exists():  # no block ran (generations = 0)
        io.save_checkpoint(checkpoint, state, algo.checkpoint_metadata())
    trained = time.perf_counter() - began
    spare = state.repertoire
    steps = None
    if config.step_starts:
        params = elite_controllers(hbr.bottom, spare.genotypes, spare.filled)
        steps = jax.device_get(measure_steps(robot, params, spare.filled, config.middle_task, start, step_key,
                                             starts=config.step_starts, chunk=config.step_chunk, progress=progress))
    filled = np.asarray(spare.filled)
    fraction = np.asarray(spare.extras["contact_fraction"])[filled]
    own = np.asarray(hbr.middle.extras["contact_fraction"])[np.asarray(hbr.middle.filled)]
    summary = {
        "threshold": threshold, "l": l, "evaluations": algo.evaluations(state), "elites": int(filled.sum()),
        "patterns": int(np.unique(np.asarray(pattern_code(spare.descriptors[:, PRIMARY:]))[filled]).size),
        "lifting_each_leg": {"spare": (fraction < threshold).sum(axis=0).tolist(),
                             "hbr": (own < threshold).sum(axis=0).tolist()},
        "wall_time_s": {"training": trained, "steps": time.perf_counter() - began - trained},
        "devices": [str(d) for d in jax.devices()],
    }
    save_spare(out / SPARE_FILE, hbr, spare, steps, l, metadata={"training": summary})
    io.write_json(out / "summary.json", summary)
    return summary
