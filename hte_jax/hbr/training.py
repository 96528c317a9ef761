"""Training an HBR: bottom, then middle, then top, each a resumable MAP-Elites run. `train_hbr` writes
config.json, <layer>/checkpoint.npz and metrics.csv, hbr.npz (`store.load_hbr`), summary.json and plots/;
a killed run resumes (`resume_run=True`) from its last block, bit-identical for the same seed."""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
from jax.sharding import Mesh

from hte_jax.config import config_dict, config_from_dict, inline
from hte_jax.config import with_overrides as _with_overrides
from hte_jax.errors import ConfigError, check_fields, choice, integer, lookup, number
from hte_jax.hbr import bottom as bottom_layer
from hte_jax.hbr import middle as middle_layer
from hte_jax.hbr.analysis import hbr_statistics
from hte_jax.hbr.bottom import BOTTOM_FITNESSES, BottomTask, bottom_spec, evaluate_bottom
from hte_jax.hbr.composition import measure_steps
from hte_jax.hbr.hierarchy import HBR
from hte_jax.hbr.middle import PRIMARY, MiddleTask, elite_controllers, evaluate_middle, middle_spec, pattern_code
from hte_jax.hbr.plots import plot_hbr
from hte_jax.hbr.spare import SPARE_L, SPARE_STREAM, STRICT_CONTACT
from hte_jax.hbr.store import LAYERS, SPARE_FILE, bottom_fingerprint, save_hbr, save_spare
from hte_jax.hbr.top import TopTask, evaluate_top, top_spec
from hte_jax.qd import io
from hte_jax.qd.loop import MapElites, MapElitesConfig, QDState, layer_seconds, run_to_end
from hte_jax.sim.mjx_import import require_impl
from hte_jax.sim.robot import Robot, RobotConfig, SolverConfig, load_robot, stored_solver
from hte_jax.sim.rollout import standing_state

with_overrides = _with_overrides  # the configurations' one override rule, re-exported
# A layer's settings of the density and frontier parent selections (levers E, F in docs/levers.md)
RETIRED_SELECTION = ("selection", "density_bins", "density_dims", "frontier_fraction", "frontier_angle_bins",
                     "frontier_level_bins")


class StoredConfig:
    """What a training configuration with an inlined `solver: SolverConfig` shares: robot, stored layout."""

    @property
    def robot(self) -> RobotConfig:
        return self.solver.robot()

    def to_dict(self) -> dict:  # the stored layout: the solver's settings among the others
        return config_dict(self)

    @classmethod
    def from_dict(cls, data: dict):
        """From `to_dict`'s layout or `dataclasses.asdict`'s; missing solver settings: `LEGACY_SOLVER`."""
        return config_from_dict(cls, {**data, **stored_solver(data)})


@dataclasses.dataclass(frozen=True)
class LayerSchedule:
    """MAP-Elites budget and variation of one layer: `MapElitesConfig`'s settings, generations after the
    initial batch, block_size generations per jitted block (one CSV row and checkpoint), capacity: archive
    slots (bottom and middle; the top layer is a grid)."""

    batch_size: int
    init_size: int
    generations: int = integer(minimum=0)
    block_size: int = integer()
    mutation_rate: float
    eta_m: float = 10.0
    capacity: int = integer(1)

    def __post_init__(self):
        check_fields(self)
        self.map_elites_config(qd_offset=0.0)  # batch, init size and mutation checks live there

    @property
    def evaluations(self) -> int:
        return self.init_size + self.generations * self.batch_size

    def map_elites_config(self, qd_offset: float) -> MapElitesConfig:
        return MapElitesConfig(batch_size=self.batch_size, init_size=self.init_size, mutation_rate=self.mutation_rate,
                               eta_m=self.eta_m, qd_offset=qd_offset)


@dataclasses.dataclass(frozen=True)
class HBRConfig(StoredConfig):
    """Everything that defines a trained HBR (the paper's values: docs/design.md): the layers' schedules, the
    tasks' settings (`MiddleTask`'s samples, contact_threshold, purity; `BottomTask.fitness`; top_bins),
    bottom_l / middle_l archive distance thresholds, solver (`SolverConfig`, inlined; stored without:
    `LEGACY_SOLVER`), step_starts / step_chunk: `composition.measure_steps`'s (0 starts: no step model)."""

    bottom: LayerSchedule
    middle: LayerSchedule
    top: LayerSchedule
    seed: int = integer(0, minimum=0)
    middle_samples: int = integer(10)
    contact_threshold: float = number(0.3, 0.0, 1.0)
    contact_purity: float = number(0.0, 0.0)
    bottom_l: float = number(bottom_layer.ARCHIVE_L, 0.0, open_low=True)
    middle_l: float = number(middle_layer.ARCHIVE_L, 0.0, open_low=True)
    top_bins: int = integer(100)
    bottom_fitness: str = choice("commands", BOTTOM_FITNESSES)
    solver: SolverConfig = inline(SolverConfig())
    step_starts: int = integer(8, minimum=0)
    step_chunk: int = integer(8192)

    def __post_init__(self):
        check_fields(self)

    @classmethod
    def from_dict(cls, data: dict) -> HBRConfig:
        """`StoredConfig.from_dict`, a layer's settings of the parent selections that left (`RETIRED_SELECTION`)
        dropped where it selected uniformly."""
        data = dict(data)
        for layer in LAYERS:
            if isinstance(data.get(layer), dict):
                if data[layer].get("selection", "uniform") != "uniform":
                    raise ConfigError(f"{layer}.selection {data[layer]['selection']!r} left hte-jax (docs/levers.md)")
                data[layer] = {k: v for k, v in data[layer].items() if k not in RETIRED_SELECTION}
        return super().from_dict(data)

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


def _preset(bottom: tuple, middle: tuple, top: tuple, **settings) -> HBRConfig:
    """bottom / middle: (batch, init, generations, block, capacity); top: the first four; Table 1's mutation."""
    return HBRConfig(LayerSchedule(*bottom[:4], 0.17, capacity=bottom[4]),
                     LayerSchedule(*middle[:4], 0.11, capacity=middle[4]), LayerSchedule(*top, 0.14), **settings)


PRESETS: dict[str, HBRConfig] = {
    # CI: all three layers end to end in seconds of compute (plus compilation).
    "tiny": _preset((16, 32, 2, 1, 256), (16, 32, 2, 1, 256), (16, 32, 2, 1), middle_samples=2, step_starts=2),
    # The default: a usable small HBR on a 2-core CPU in about 15 minutes.
    "cpu": _preset((256, 512, 8, 4, 2048), (256, 512, 14, 2, 8192), (256, 512, 14, 2), middle_samples=3),
    # One H100 / H200 in about 10 minutes.
    "gpu": _preset((16384, 16384, 16, 8, 16384), (32768, 32768, 36, 4, 65536), (16384, 16384, 120, 10),
                   middle_samples=5),
    # The paper's evaluation counts (5001 / 30000 / 20000 generations of 200) in batches of 8000.
    "paper": _preset((8000, 8000, 125, 5, 32768), (8000, 8000, 750, 10, 131072), (8000, 8000, 500, 10),
                     middle_samples=10),
}


def normalised_config(data: dict) -> dict:
    """A stored configuration read through today's HBRConfig (settings added since take their defaults)."""
    return HBRConfig.from_dict(data).to_dict()


def preset(name: str) -> HBRConfig:
    return lookup("preset", name, PRESETS)


def layer_algorithms(config: HBRConfig, robot: Robot, start, lower: dict,
                     mesh: Mesh | None = None) -> dict[str, Callable[[], MapElites]]:
    """Factories of each layer's MapElites over `mesh` (None: all devices); `lower`: the trained layers so far."""

    def algorithm(layer: str, spec) -> MapElites:
        return MapElites.from_spec(spec, getattr(config, layer).map_elites_config(spec.qd_offset), mesh=mesh)

    def bottom() -> MapElites:
        evaluate = functools.partial(evaluate_bottom, robot, start, config.bottom_task)
        return algorithm("bottom", bottom_spec(config.bottom.capacity, config.bottom_l, evaluate=evaluate))

    def middle() -> MapElites:
        evaluate = functools.partial(evaluate_middle, robot, start, config.middle_task, lower["bottom"])
        return algorithm("middle", middle_spec(config.middle.capacity, config.middle_l, evaluate=evaluate))

    def top() -> MapElites:
        task = config.top_task
        hbr = HBR.build(lower["bottom"], lower["middle"], top_spec(task).empty(), config.middle_task, top_task=task)
        return algorithm("top", top_spec(task, evaluate=functools.partial(evaluate_top, robot, start, task, hbr)))

    return {"bottom": bottom, "middle": middle, "top": top}


@dataclasses.dataclass
class TrainingOutcome:
    hbr: HBR
    summary: dict


def train_hbr(config: HBRConfig, out_dir: str | Path, *, resume_run: bool = False, progress: bool = True,
              on_block: Callable[[str, int, QDState, dict], None] | None = None, plots: bool = True,
              mesh: Mesh | None = None) -> TrainingOutcome:
    """Train (or finish training) the three layers (see the module docstring), spread over `mesh` (None: all
    devices; the results do not depend on it). In a multi-process run only process 0 writes files."""
    out = Path(out_dir)
    writer = jax.process_index() == 0
    require_impl(config.robot.impl)  # before the run folder is made: a missing extra writes nothing
    io.prepare_run_dir(out, config.to_dict(), resume_run, normalise=normalised_config)
    robot = load_robot(config.robot)
    start = standing_state(robot)
    keys = dict(zip(LAYERS, jax.random.split(jax.random.PRNGKey(config.seed), len(LAYERS))))
    lower: dict = {}
    summary: dict = {"config": config.to_dict(), "layers": {}}
    for layer in LAYERS:
        algo = layer_algorithms(config, robot, start, lower, mesh)[layer]()
        schedule: LayerSchedule = getattr(config, layer)
        began = time.perf_counter()
        hook = None if on_block is None else (lambda block, st, row, _layer=layer: on_block(_layer, block, st, row))
        state = run_to_end(algo, keys[layer], out / layer, schedule.generations, schedule.block_size,
                           progress=progress, on_block=hook, description=layer, write=writer)
        metrics = jax.device_get(algo.metrics(state))
        lower[layer] = state.repertoire
        summary["layers"][layer] = {
            "evaluations": algo.evaluations(state), "filled": int(metrics.filled),
            "capacity": state.repertoire.capacity, "mean_fitness": float(metrics.mean_fitness),
            "max_fitness": float(metrics.max_fitness), "qd_score": float(metrics.qd_score),
            "wall_time_s": layer_seconds(out / layer / "metrics.csv", began)}
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
    if writer:
        save_hbr(out / "hbr.npz", hbr, metadata={"training": summary})
        io.write_json(out / "summary.json", summary)
        if plots:
            plot_hbr(hbr, config.top_task, out, out / "plots")
    return TrainingOutcome(hbr=hbr, summary=summary)


def _normalised_spare(stored: dict) -> dict:
    """A spare run's stored configuration with its HBR configuration read through today's."""
    return {**stored, "hbr_config": normalised_config(stored["hbr_config"])} if "hbr_config" in stored else stored


def train_spare(hbr: HBR, base: HBRConfig, out_dir: str | Path, *, threshold: float = STRICT_CONTACT,
                l: float = SPARE_L, resume_run: bool = False, progress: bool = True) -> dict:
    """Train a second middle archive for `hbr`'s spare sets on its bottom layer (`base`'s middle task and
    budget at contact threshold `threshold`, distance threshold `l`) and measure its steps; writes
    config.json, middle/, spare.npz and summary.json (resumable); returns the summary."""
    config = dataclasses.replace(base, contact_threshold=threshold, middle_l=l, contact_purity=0.0)
    out = Path(out_dir)
    require_impl(config.robot.impl)  # before the run folder is made: a missing extra writes nothing
    io.prepare_run_dir(out, {"hbr_config": config.to_dict(), "bottom": bottom_fingerprint(hbr)}, resume_run,
                       normalise=_normalised_spare)
    robot = load_robot(config.robot)
    start = standing_state(robot)
    algo = layer_algorithms(config, robot, start, {"bottom": hbr.bottom})["middle"]()
    key, step_key = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(config.seed), SPARE_STREAM))
    began = time.perf_counter()
    state = run_to_end(algo, key, out / "middle", config.middle.generations, config.middle.block_size,
                       progress=progress, description="spare")
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
        "devices": [str(d) for d in jax.devices()]}
    save_spare(out / SPARE_FILE, hbr, spare, steps, l, metadata={"training": summary})
    io.write_json(out / "summary.json", summary)
    return summary
