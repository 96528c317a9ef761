"""Adaptation experiments in the maze: which repertoire, which variants, damages and replicates,
run as batched episodes, summarised and saved (the library side of `experiments.maze_eval`).

Variants: "hte", "perfect-hte", "random-hte" and "rte" plan on an HBR's top layer (its file, or
the shipped one); "rte" on a flat repertoire file plans on its elites; "2d-rte" and "8d-rte" are
RTE on the shipped flat repertoires; "aprol" is APROL on the shipped 21 damaged repertoires. All
HBR variants share one batch (the secondary mode is per episode); each flat variant is its own batch.

The paper's protocol (`PROTOCOLS["paper"]`): its six variants, the seven damages, R repertoire
seeds and `replicates` episodes each. `PROTOCOLS["hte-jax"]`: our
HTE (`hte-spare`) beside the paper's rule, RTE on the same HBR, 2D-RTE and both oracles, every
variant on the robot with the releasing tilt reflex. Seeds come from `repertoire_dir` (one subfolder per seed
holding `hbr.npz`, `flat2d.npz`, `flat8d.npz`, `aprol.npz`; `seeds` picks some, by index); without it,
the shipped repertoires are the one seed.
"""

from __future__ import annotations

import dataclasses
import re
import time
from pathlib import Path

import jax
import numpy as np
from jax.sharding import Mesh

from hte_jax.config import config_dict, config_from_dict, inline
from hte_jax.errors import ConfigError, check_fields, choice, integer, lookup
from hte_jax.config import with_overrides as _with_overrides
from hte_jax.flat.store import load_flat, shipped_flat_path
from hte_jax.hbr.store import load_hbr, load_spare, spare_beside
from hte_jax.online.arena import maze_robot, start_states
from hte_jax.hbr.composition import COMPOSITIONS
from hte_jax.online.episode import AdaptationConfig, Episodes, RunTimings, run_together, start_episodes
from hte_jax.online.skills import Skills, flat_skill_maps, flat_skills, hbr_skills
from hte_jax.online.variants import batch_rules
from hte_jax.online.variants import variant as variant_named
from hte_jax.online.maze import Maze, load_maze, maze_to_dict
from hte_jax.online.mcts import PlannerConfig
from hte_jax.online.recording import Recorder, Replay, damage_info, replay_of
from hte_jax.qd.io import CheckpointError, read_checkpoint
from hte_jax.sim.damage import Damage, mask_if_plain, parse_damages, stack_damages
from hte_jax.sim.robot import RobotConfig, SolverConfig

with_overrides = _with_overrides  # the configurations' one override rule, re-exported

# settings of levers that left (docs/levers.md), at their neutral values
RETIRED = {"optimism": 0.0, "pattern_ends": "", "reflex_rate": 0.0}
SEED_FILES = {"hbr": "hbr.npz", "2d": "flat2d.npz", "8d": "flat8d.npz", "aprol": "aprol.npz"}  # in a seed folder
# Named protocols: the EvalConfig values each fixes. paper: the paper's Fig. 6 variants, in its order,
# on the paper's robot; hte-jax: our HTE against the baselines, on the robot with the tilt reflex that
# lets go (docs/design.md, the tilt reflex; its measurements in docs/levers.md); ablations: what each half of
# hte-spare pays (its sensing alone, the spare archive alone) beside it, its oracle and RTE, on that robot.
PROTOCOLS = {
    "paper": {"variants": "perfect-hte,hte,2d-rte,8d-rte,aprol,random-hte", "damages": "all"},
    "hte-jax": {"variants": "perfect-hte,hte-spare,perfect-spare,hte,rte,2d-rte", "damages": "all",
                "reflex_tilt": 0.3, "reflex_release": 0.15},
    "ablations": {"variants": "hte-spare,hte-sense,rte-spare,rte,perfect-spare", "damages": "all",
                  "reflex_tilt": 0.3, "reflex_release": 0.15},
}


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """An adaptation experiment. Every field can be overridden from the CLI.

    variants: comma-separated variant names. damages: the damages, as `sim.damage.parse_damages` spells
    them: "all" (the paper's 7), "suite" (`DAMAGE_SUITE`: leg pairs, shortened, weak, a slippery floor), or
    comma-separated items `<legs>[:<model>[=<fraction>]][:friction=<scale>]`
    (legs "none", "leg1", "legs1+4", the original's indices -1..6 or "all"; e.g. "leg0:removed",
    "leg2:shortened=0.5:friction=0.6", "none:friction=0.5"); an item without a model is under
    `damage_model`. Episodes, summaries and statistics name each damage by its canonical label
    (`damage_list`). replicates: episodes per (variant, damage). repertoire: an HBR or single flat
    repertoire file for the HBR variants and "rte" ("" = the shipped HBR). repertoire_dir: a folder
    with one subfolder per repertoire seed (files `SEED_FILES`) used instead of the shipped
    repertoires. seeds: the seeds of `repertoire_dir` to run, comma-separated indices of its subfolders
    in name order ("" = every seed); each keeps its index, so its episodes equal a run over every seed's.
    damage_model: the model of the damages that name none: "raised" (a damaged leg blocked in the air,
    the paper's words), "locked" (in the standing pose, the original code's) or "removed". max_actions: the failure cap. planner: the MCTS settings (`PlannerConfig`,
    inlined: settings iterations, roots, exploration, widening, gamma, depth, candidates,
    collision_reward, goal_reward; 200 x 2 trees by default). composition: how an HBR step with a chosen contact pattern picks its elite: "planned" (ours,
    `hbr.composition`: a plan among the pattern's elites to the skill's end) or "waypoints" (the
    paper's nearest elite to the next waypoint); RTE's steps are the same in both. spare: the
    spare archive whose elites join the HBR's own in the spare sets of the variants that run
    steps from them (`hbr.spare`; a spare file of `experiments.train_spare` or another HBR file;
    "" = the spare.npz beside the HBR file, if any). seed: PRNG seed.
    solver: the physics' Newton solver (`SolverConfig`, inlined: settings solver_iterations,
    ls_iterations, solver_tolerance). reflex_tilt: the robot's tilt reflex (`RobotConfig.reflex_tilt`,
    rad): past this tilt a skill's gait gives way to the neutral pose for the rest of its second; 0
    (default, the paper's robot): off. reflex_release: the tilt below which the reflex lets go
    (`RobotConfig.reflex_release`; 0: at the end of the second). maze: the world, a
    shipped maze's name (assets/mazes/: "paper", "two_rooms"), "random:K" (the generated maze of seed K,
    `maze_gen.random_maze`) or a JSON file of `Maze`'s fields (`maze.load_maze`); "" (default): the paper's
    maze.
    """

    variants: str = "hte"
    damages: str = "all"
    replicates: int = integer(1)
    repertoire: str = ""
    repertoire_dir: str = ""
    seeds: str = ""
    damage_model: str = "raised"
    max_actions: int = 80
    planner: PlannerConfig = inline(PlannerConfig(iterations=200, roots=2))
    composition: str = choice("planned", COMPOSITIONS)
    spare: str = ""
    seed: int = integer(0, minimum=0)
    solver: SolverConfig = inline(SolverConfig())
    reflex_tilt: float = RobotConfig.reflex_tilt
    reflex_release: float = RobotConfig.reflex_release
    maze: str = ""

    def __post_init__(self):
        check_fields(self)
        for name in self.variant_list:
            variant_named(name)  # validates the name
        if self.repertoire and self.repertoire_dir:
            raise ConfigError("give either repertoire (one HBR file) or repertoire_dir (seed folders), not both")
        self.seed_indices  # noqa: B018 (validates the seeds)
        self.robot  # noqa: B018 (RobotConfig validates the damage model)
        self.damage_conditions  # noqa: B018 (validates the damages)
        self.adaptation  # noqa: B018 (validates max_actions)
        self.maze_task  # noqa: B018 (reads and validates the maze)

    @property
    def variant_list(self) -> tuple[str, ...]:
        names = tuple(v.strip() for v in self.variants.split(",") if v.strip())
        if not names:
            raise ConfigError("variants: give at least one variant")
        if len(set(names)) != len(names):
            raise ConfigError(f"variants: {self.variants!r} names a variant twice")
        return names

    @property
    def seed_indices(self) -> tuple[int, ...]:
        """The repertoire seeds `seeds` names, increasing; () for every seed of `repertoire_dir`."""
        items = [item.strip() for item in self.seeds.split(",")] if self.seeds.strip() else []
        if not all(re.fullmatch(r"[0-9]+", item) for item in items):
            raise ConfigError(f"seeds: {self.seeds!r} is not comma-separated seed indices (integers >= 0, e.g. 1,2,3)")
        indices = [int(item) for item in items]
        twice = sorted({i for i in indices if indices.count(i) > 1})
        if twice:
            raise ConfigError(f"seeds: {self.seeds!r} names seed {twice[0]} twice")
        if indices and not self.repertoire_dir:
            raise ConfigError("seeds picks seed folders of repertoire_dir: give repertoire_dir too")
        return tuple(sorted(indices))

    @property
    def damage_conditions(self) -> dict[str, Damage]:
        """Canonical label -> unbatched NumPy `Damage` of each damage, in order (`parse_damages` of `damages`
        under `damage_model`)."""
        return parse_damages(self.damages, self.damage_model)

    @property
    def damage_list(self) -> tuple[str, ...]:
        """The damages' canonical labels in order (indices 0..6 become the paper's names; the model is named
        where it is not `damage_model`)."""
        return tuple(self.damage_conditions)

    @property
    def maze_task(self) -> Maze:
        """The world the episodes run in (`maze.load_maze(self.maze)`)."""
        return load_maze(self.maze)

    @property
    def adaptation(self) -> AdaptationConfig:
        return AdaptationConfig(max_actions=self.max_actions, planner=self.planner)

    @property
    def robot(self) -> RobotConfig:
        """The simulated robot's options (before the maze's walls are added)."""
        return self.solver.robot(damage_model=self.damage_model, reflex_tilt=self.reflex_tilt,
                                 reflex_release=self.reflex_release)

    def to_dict(self) -> dict:
        """The stored layout (`config.config_dict`: inlined settings among the others)."""
        return config_dict(self)

    @classmethod
    def from_dict(cls, data: dict) -> EvalConfig:
        """A configuration from `to_dict`'s output (a run's config.json without its preset and
        protocol) or the nested layout of `dataclasses.asdict`. Settings of retired levers
        (`RETIRED`, docs/levers.md) are dropped where they hold their neutral value."""
        data = dict(data)
        for key, neutral in RETIRED.items():
            if key in data and data.pop(key) != neutral:
                raise ConfigError(f"setting {key!r} belongs to a lever that left hte-jax (docs/levers.md)")
        return config_from_dict(cls, data)


def protocol_overrides(name: str) -> dict:
    """The EvalConfig values a named protocol fixes (its variants, every damage, its robot); a copy
    the caller may update with its own overrides."""
    return dict(lookup("protocol", name, PROTOCOLS))


# cpu: 7 episodes per variant, 154 s on 2 cores (benchmarks/cpu_commands.py); gpu: the paper's 30 replicates with
# the simulations of RTE's original planner (1000 iterations x 4 trees) in 16 trees of 250: a GPU plans the trees
# at once, so a quarter of the sequential iterations plan 2.4x faster at the same results (docs/results.md, "Speed");
# paper: HTE's original 6000 iterations x 32 trees.
PRESETS = {
    "cpu": EvalConfig(),
    "gpu": EvalConfig(replicates=30, planner=PlannerConfig(iterations=250, roots=16)),
    "paper": EvalConfig(replicates=30, planner=PlannerConfig(iterations=6000, roots=32)),
}


def preset(name: str) -> EvalConfig:
    return lookup("preset", name, PRESETS)


def load_skills(path: str | Path | None, maps: bool = False, composition: str = "planned", spare: bool = False,
                spare_path: str | Path | None = None) -> tuple[Skills, dict]:
    """Actions of an HBR file (its top layer) or of a file holding one flat repertoire; None: the
    shipped HBR. maps: accept a flat file of several repertoires (APROL's set): actions (K, A).
    composition, spare: see `skills.hbr_skills`. spare_path: the spare archive joined to the HBR's
    own elites in the spare sets (`store.load_spare`: a spare file or another HBR file; default:
    the spare.npz beside the HBR file, if any)."""
    shipped = path is None or str(path) == ""
    header = {} if shipped else read_checkpoint(path)[1]
    kind = "hte_jax.hbr" if shipped else header.get("metadata", {}).get("kind")
    if kind == "hte_jax.hbr":
        hbr, task, _ = load_hbr(None if shipped else path)
        archive = (spare_path or spare_beside(None if shipped else path)) if spare else None
        if archive:
            hbr = load_spare(archive, hbr)
        skills = hbr_skills(hbr, task, composition=composition, spare=spare)
        return skills, {"kind": "hbr", "path": "shipped" if shipped else str(path),
                        "actions": _action_count(skills), **({"spare": str(archive)} if archive else {})}
    if kind == "hte_jax.flat":
        count = len(header["metadata"].get("damages", ()))
        if count != 1 and not maps:
            raise CheckpointError(f"{path}: holds {count} repertoires (an APROL set); RTE needs a file with one")
        flat, _ = load_flat(path)
        if maps:
            skills = flat_skill_maps(flat.repertoire, flat.task.extent)
            return skills, {"kind": f"flat-{flat.task.descriptor}-set", "path": str(path), "repertoires": len(flat),
                            "actions": _action_count(skills)}
        skills = flat_skills(jax.tree.map(lambda x: x[0], jax.device_get(flat.repertoire)), flat.task.extent)  # host
        return skills, {"kind": f"flat-{flat.task.descriptor}", "path": str(path), "actions": _action_count(skills)}
    raise CheckpointError(f"{path}: neither an HBR nor a flat repertoire file (kind {kind!r})")


def _action_count(skills: Skills) -> int:
    """The real actions of `skills`, over all its repertoires (counted on the host)."""
    return int(np.asarray(skills.actions.mask).sum())


@dataclasses.dataclass
class BatchResult:
    """One batch of episodes on one repertoire (of repertoire seed `seed`): labels per episode, damage
    (B, ...) NumPy what is wrong with each episode's robot, the final `Episodes` (NumPy) and the replays of the
    recorded episodes (in row order)."""

    seed: int
    repertoire: dict
    variants: list[str]
    damages: list[str]
    replicates: list[int]
    damage: Damage
    episodes: Episodes
    timings: RunTimings
    replays: list[Replay] = dataclasses.field(default_factory=list)


def seed_folders(config: EvalConfig) -> dict[int, Path | None]:
    """The repertoire seeds to run, by index: the subfolders of `repertoire_dir` in name order (those `seeds`
    names, or all), or {0: None} (the shipped repertoires)."""
    if not config.repertoire_dir:
        return {0: None}
    root = Path(config.repertoire_dir)
    if not root.is_dir():
        raise ConfigError(f"repertoire_dir {root} is not a folder")
    folders = sorted(p for p in root.iterdir() if p.is_dir())
    if not folders:
        raise ConfigError(f"repertoire_dir {root} holds no seed subfolders")
    chosen = config.seed_indices or tuple(range(len(folders)))
    missing = [str(i) for i in chosen if i >= len(folders)]
    if missing:
        held = "seed 0" if len(folders) == 1 else f"seeds 0 to {len(folders) - 1}"
        raise ConfigError(f"seeds: repertoire_dir {root} has no seed{'s' * (len(missing) > 1)} {', '.join(missing)} (its subfolders are {held})")
    return {i: folders[i] for i in chosen}


def batches(config: EvalConfig) -> list[tuple[int, str | None, list[str]]]:
    """(seed index, repertoire path or None for the shipped HBR, variants) for each batch to run."""
    hbr = [v for v in config.variant_list if variant_named(v).hierarchical]
    out = []
    for seed, folder in seed_folders(config).items():
        if hbr:
            out.append((seed, config.repertoire or None if folder is None else str(folder / SEED_FILES["hbr"]), hbr))
        for name in config.variant_list:
            kind = variant_named(name).repertoire
            if kind != "hbr":
                path = shipped_flat_path(kind) if folder is None else folder / SEED_FILES[kind]
                out.append((seed, str(path), [name]))
    return out


def batch_labels(config: EvalConfig, variants: list[str]) -> list[tuple[str, str, int]]:
    """(variant, damage, replicate) of each episode of a batch of `variants`, in batch order."""
    return [(v, d, r) for v in variants for d in config.damage_list for r in range(config.replicates)]


def run_batch(config: EvalConfig, path: str | None, variants: list[str], maze: Maze | None = None, progress: bool = True,
              seed: int = 0, record: tuple[int, ...] = (), record_every: int = 4, mesh: Mesh | None = None) -> BatchResult:
    """Every (variant, damage, replicate) of `variants` on one repertoire (of seed `seed`), as one
    batch of episodes. record: batch rows whose states are recorded every `record_every` control
    steps (`BatchResult.replays`); none by default, and then nothing is recorded. mesh: the devices
    the episodes are spread over (`episode.run_episodes`; None: all visible). maze: the world
    (None: the configuration's, `EvalConfig.maze_task`). The episodes' robots carry a `Damage`, or its leg
    mask where that says the same (`damage.mask_if_plain`: the rollout's program without model edits)."""
    return run_batches(config, [(path, variants)], maze, progress, seed, [record], record_every, mesh)[0]


def run_batches(config: EvalConfig, planned: list[tuple[str | None, list[str]]], maze: Maze | None = None,
                progress: bool = True, seed: int = 0, record: list[tuple[int, ...]] | None = None,
                record_every: int = 4, mesh: Mesh | None = None) -> list[BatchResult]:
    """`run_batch` of several batches (repertoire path, variants) of seed `seed`, run together: each action plans
    each batch and acts all of them in one program (`episode.run_together`). record: each batch's rows to record."""
    began = time.perf_counter()
    maze = config.maze_task if maze is None else maze
    record = [()] * len(planned) if record is None else record
    adaptation, robot, conditions = config.adaptation, maze_robot(maze, config.robot), config.damage_conditions
    key = jax.random.PRNGKey(config.seed)
    key = key if seed == 0 else jax.random.fold_in(key, seed)
    prepared = []
    for path, variants in planned:
        maps = len(variants) == 1 and variant_named(variants[0]).repertoire == "aprol"
        labels = batch_labels(config, variants)
        skills, info = load_skills(path, maps=maps, composition=config.composition,
                                   spare=any(variant_named(v).spares for v in variants),
                                   spare_path=config.spare or None)
        for name in variants:
            variant_named(name).check_skills(skills)
        rules, which = batch_rules([v for v, _, _ in labels])
        damage = stack_damages([conditions[d] for _, d, _ in labels])
        simulated = mask_if_plain(damage, config.damage_model)
        start = start_states(maze, simulated, config.robot)
        episodes = start_episodes(adaptation, skills, start, simulated, rules, np.asarray(which), key)
        prepared.append((variants, labels, skills, info, damage, episodes))
    recorders = [Recorder(tuple(rows), record_every) if rows else None for rows in record]
    setup = time.perf_counter() - began
    ran = run_together(maze, adaptation, robot, [(skills, episodes) for _, _, skills, _, _, episodes in prepared],
                       progress=progress, description=" + ".join("/".join(variants) for variants, *_ in prepared),
                       recorders=recorders, mesh=mesh)
    results = []
    for (variants, labels, skills, info, damage, _), (episodes, timings), recorder, rows in zip(
            prepared, ran, recorders, record):
        episodes = jax.device_get(episodes)  # what the records, plots and files read, on the host once
        timings.setup = setup
        replays = [replay_of(recorder, episodes, row, {
            "variant": labels[row][0], "damage": labels[row][1], "replicate": labels[row][2], "seed": seed,
            "repertoire": info["path"], "hierarchical": skills.hierarchical,
            **damage_info(conditions[labels[row][1]]), "max_actions": config.max_actions,
            "maze": maze_to_dict(maze)}) for row in rows]
        names, damages, replicates = (list(column) for column in zip(*labels))
        results.append(BatchResult(seed, info, names, damages, replicates, damage, episodes, timings, replays))
    return results


def episode_numbers(variants: list[str], earlier: dict[str, int]) -> list[int]:
    """Each row's episode number among its variant's episodes in run order, for a batch of
    `variants` (B,) (one per row) after `earlier[v]` episodes of variant v in earlier batches."""
    seen, numbers = dict(earlier), []
    for variant in variants:
        numbers.append(seen.get(variant, 0))
        seen[variant] = numbers[-1] + 1
    return numbers


def rows_to_record(variants: list[str], count: int, earlier: dict[str, int]) -> tuple[int, ...]:
    """Rows of a batch whose episodes are among the first `count` of their variant (see `episode_numbers`)."""
    return tuple(row for row, number in enumerate(episode_numbers(variants, earlier)) if number < count)


def episode_records(result: BatchResult, max_actions: int) -> list[dict]:
    """One JSON-able record per episode: actions (the cap when failed), success and the prediction errors."""
    taken, reached, broken = (np.asarray(x) for x in (result.episodes.taken, result.episodes.reached,
                                                      result.episodes.broken))
    error = prediction_errors(result.episodes)
    return [{"variant": variant, "seed": result.seed, "damage": damage, "replicate": replicate,
             "reached": bool(reached[i]), "broken": bool(broken[i]),
             "actions": int(taken[i]) if reached[i] else max_actions, "actions_taken": int(taken[i]),
             "prediction_error": [round(float(e), 4) for e in error[i, : taken[i]]]}
            for i, (variant, damage, replicate) in enumerate(zip(result.variants, result.damages, result.replicates))]


def prediction_errors(episodes: Episodes) -> np.ndarray:
    """(B, L) distance (m) between the RTE GP's predicted and the measured end position of each action."""
    h = episodes.history
    return np.linalg.norm(np.asarray(h.predicted)[..., :2] - np.asarray(h.observed)[..., :2], axis=-1)


def summarise(records: list[dict], max_actions: int) -> dict:
    """Per variant and per (variant, damage): episodes, successes, and the 25/50/75th percentiles of actions."""

    def stats(rows):
        p25, median, p75 = np.percentile([r["actions"] for r in rows], [25, 50, 75], method="nearest")
        return {"episodes": len(rows), "reached": int(sum(r["reached"] for r in rows)),
                "failure_rate": float(np.mean([not r["reached"] for r in rows])), "actions_p25": float(p25),
                "actions_median": float(median), "actions_p75": float(p75),
                "broken": int(sum(r["broken"] for r in rows))}

    out = {"max_actions": max_actions, "variants": {}}
    for variant in dict.fromkeys(r["variant"] for r in records):
        rows = [r for r in records if r["variant"] == variant]
        damages = {d: stats([r for r in rows if r["damage"] == d]) for d in dict.fromkeys(r["damage"] for r in rows)}
        out["variants"][variant] = {**stats(rows), "damages": damages}
    return out
