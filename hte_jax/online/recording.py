"""Recording chosen episodes for replay (`python -m experiments.render episode`): a `Recorder` collects
their states during `run_episodes`; `replay_of` makes one episode's `Replay`, kept in a run folder as
`replays/<variant>_ep<I>.npz` (a `qd.io` checkpoint; I counts the variant's episodes in run order).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import numpy as np

from hte_jax.errors import ConfigError, require_int
from hte_jax.online.action import SECONDS_PER_ACTION, STEP_CONTROL_STEPS
from hte_jax.online.maze import Maze, maze_from_dict
from hte_jax.qd.io import CheckpointError, read_checkpoint, save_checkpoint
from hte_jax.sim.damage import DAMAGE_PARTS, Damage, damage_legs, make_damage

KIND = "hte_jax.replay"
REPLAY_DIR = "replays"
ARRAYS = ("qpos", "action", "map", "patterns", "trajectory", "damage")


@dataclasses.dataclass
class Recorder:
    """Collects the states of chosen episodes of a batch during `run_episodes`. rows: the batch rows to
    record. every: control steps between recorded states (divides 100). frames: row -> one (400 / every,
    25) float32 array per action the episode took, filled by `add`."""

    rows: tuple[int, ...]
    every: int = 4
    frames: dict[int, list[np.ndarray]] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        require_int("record every", self.every)
        if STEP_CONTROL_STEPS % self.every:
            raise ConfigError(f"record every must divide {STEP_CONTROL_STEPS} control steps, got {self.every}")
        self.rows = tuple(int(r) for r in self.rows)
        if any(r < 0 for r in self.rows) or len(set(self.rows)) != len(self.rows):
            raise ConfigError(f"recorded rows must be distinct and >= 0, got {self.rows}")

    def add(self, qpos, active: np.ndarray) -> None:
        """Keep one action's states (B, F, 25) (jax or NumPy) of the recorded rows that were running (`active`
        (B,))."""
        if not self.rows:
            return
        rows = np.asarray(self.rows)
        kept = qpos[rows] if isinstance(qpos, np.ndarray) else np.asarray(_take_rows(qpos, rows))
        for row, states in zip(self.rows, kept):
            if active[row]:
                self.frames.setdefault(row, []).append(states)


@jax.jit
def _take_rows(states: jax.Array, rows: jax.Array) -> jax.Array:
    """states[rows] in one program: only the recorded rows leave the device."""
    return states[rows]


@dataclasses.dataclass(frozen=True)
class Replay:
    """One recorded episode of N actions, F = 400 / k states per action (k = `every`): qpos (N F + 1, 25) float32
    (state j F + s F / 4 starts second s of action j), action and map (N,) int32, patterns (N, 3) int32,
    trajectory (4 N + 1, 3) float32, damage (6,) bool the damaged legs, info JSON-able labels (variant, damage (its
    label), seed, replicate, row, reached, broken, damage_model, damage_fraction, damage_friction (`damage_info`),
    maze, max_actions, every, episode)."""

    qpos: np.ndarray
    action: np.ndarray
    map: np.ndarray
    patterns: np.ndarray
    trajectory: np.ndarray
    damage: np.ndarray
    info: dict

    @property
    def every(self) -> int:
        return int(self.info["every"])

    @property
    def actions(self) -> int:
        return int(self.action.shape[0])

    @property
    def states_per_action(self) -> int:
        return SECONDS_PER_ACTION * STEP_CONTROL_STEPS // self.every

    @property
    def maze(self) -> Maze:
        return maze_from_dict(self.info["maze"])

    @property
    def robot_damage(self) -> Damage:
        """The episode's `Damage` (unbatched, NumPy): its legs under its model, fraction and floor friction."""
        info = self.info
        return make_damage(self.damage, info["damage_model"], info.get("damage_fraction", 1.0),
                           info.get("damage_friction", 1.0), xp=np)


def damage_info(damage: Damage) -> dict:
    """The JSON-able labels of an unbatched `damage` that a `Replay` keeps beside its legs: damage_model (a name of
    `DAMAGE_PARTS`), damage_fraction, damage_friction."""
    return {"damage_model": list(DAMAGE_PARTS)[int(damage.model)], "damage_fraction": float(damage.fraction),
            "damage_friction": float(damage.friction)}


def replay_of(recorder: Recorder, episodes, row: int, info: dict) -> Replay:
    """The ended episode in batch `row` of the `episode.Episodes` that `run_episodes` ran with `recorder`."""
    taken = int(episodes.taken[row])
    frames = recorder.frames.get(row, [])
    if len(frames) != taken:
        raise ValueError(f"row {row}: {len(frames)} recorded actions for {taken} taken")
    final = np.asarray(episodes.sim.qpos[row], np.float32)[None]
    history = episodes.history
    return Replay(
        qpos=np.concatenate([*frames, final]).astype(np.float32), action=np.asarray(history.action[row, :taken]),
        map=np.asarray(history.map[row, :taken]), patterns=np.asarray(history.patterns[row, :taken]),
        trajectory=np.asarray(episodes.trajectory[row, : SECONDS_PER_ACTION * taken + 1]),
        damage=np.asarray(damage_legs(episodes.damage)[row], bool),
        info={**info, "row": int(row), "every": recorder.every, "actions": taken,
              "reached": bool(episodes.reached[row]), "broken": bool(episodes.broken[row])})


def replay_path(run: str | Path, variant: str, episode: int) -> Path:
    return Path(run) / REPLAY_DIR / f"{variant}_ep{episode}.npz"


def save_replay(path: str | Path, replay: Replay) -> None:
    save_checkpoint(path, {key: getattr(replay, key) for key in ARRAYS}, {"kind": KIND, **replay.info}, compress=True)


def load_replay(path: str | Path) -> Replay:
    """A replay file; CheckpointError naming the problem if it is not one."""
    arrays, header = read_checkpoint(path)
    info = header.get("metadata", {})
    if info.get("kind") != KIND or any(name not in arrays for name in ARRAYS):
        raise CheckpointError(f"{path}: not a replay file")
    replay = Replay(**{name: arrays[name] for name in ARRAYS}, info={k: v for k, v in info.items() if k != "kind"})
    if replay.qpos.shape[0] != replay.actions * replay.states_per_action + 1:
        raise CheckpointError(f"{path}: {replay.qpos.shape[0]} states do not match {replay.actions} actions")
    return replay


def recorded_episodes(run: str | Path) -> dict[str, list[int]]:
    """variant -> the episode numbers with a replay file in run folder `run`, in order."""
    found: dict[str, list[int]] = {}
    folder = Path(run) / REPLAY_DIR
    for path in sorted(folder.glob("*_ep*.npz")) if folder.is_dir() else ():
        variant, _, number = path.stem.rpartition("_ep")
        if number.isdigit():
            found.setdefault(variant, []).append(int(number))
    return {variant: sorted(numbers) for variant, numbers in found.items()}
