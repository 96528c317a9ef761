"""Adaptation episodes on a robot this library does not simulate, driven through an `Executor`; and
`MujocoExecutor`, native MuJoCo as the stand-in for hardware (`docs/design.md`, Executors).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Protocol

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from hte_jax.geometry import planar_pose, relative_pose
from hte_jax.online.action import ONLINE_LIMITS, SECONDS_PER_ACTION, STEP_CONTROL_STEPS, Second
from hte_jax.online.arena import maze_config, place
from hte_jax.online.episode import AdaptationConfig, Episodes, execute, plan_step, record_action, start_episodes
from hte_jax.online.maze import Maze, distance_field
from hte_jax.online.skills import Skills
from hte_jax.online.variants import variant as variant_named
from hte_jax.sim.controller import NUM_PARAMS, SAMPLES_PER_PERIOD, target_table
from hte_jax.sim.damage import Damage, as_damage, edited_native_model, edits_model, held_targets, touching_feet
from hte_jax.sim.robot import FOOT_RADIUS, NUM_LEGS, RobotConfig, mj_model, robot_info
from hte_jax.sim.env import SimState, ValidityLimits, check_state, control
from hte_jax.sim.rollout import RolloutSpec


@struct.dataclass
class Seconds:
    """What a robot reports after S one-second controllers: poses (S, 3) float32 world (x, y, heading) after each,
    contacts (S, 6) float32 share each foot was down, invalid_reason int `InvalidReason` bits (later seconds repeat
    the last valid pose, no contact), leg_travel (S, 6) float32 rad each leg's joints moved, or None (no leg is
    judged stuck), leg_commanded (S, 6) float32 rad its joint targets moved (what its controller commanded, after
    the tilt reflex: `rollout.RolloutResult.target_travel`), or None (judged against the controllers' periods)."""

    poses: np.ndarray
    contacts: np.ndarray
    invalid_reason: int = 0
    leg_travel: np.ndarray | None = None
    leg_commanded: np.ndarray | None = None


class Executor(Protocol):
    """A robot the online loop drives (one robot, unbatched)."""

    def pose(self) -> np.ndarray:
        """(3,) its world planar pose (x, y, heading) now."""

    def run(self, params: np.ndarray) -> Seconds:
        """Run controllers `params` (S, 36) back to back, each for 1 s with its clock restarted, and report."""


class ExecutorRobot:
    """One robot driven from the host through `executor` (the robots of `action`), one `executor.run` per
    second; an invalid robot is not driven again (later seconds report its pose and reason)."""

    def __init__(self, executor: Executor):
        self.executor, self.reason = executor, 0
        self._jitted = {}

    def pose(self, state=None) -> jax.Array:
        return jnp.asarray(self.executor.pose(), jnp.float32)[None]

    def staged(self, fn):
        return self._jitted.setdefault(fn, jax.jit(fn))

    def steps(self, step, carry, xs):
        records = []
        for i in range(len(xs[1])):
            carry, record = step(carry, jax.tree.map(lambda x: x[i], xs))
            records.append(record)
        return carry, jax.tree.map(lambda *r: jnp.stack(r), *records)

    def _run(self, params: np.ndarray) -> Seconds:
        """`executor.run(params)` (S, 36) unless the robot stopped; a stopped robot's report."""
        count = params.shape[0]
        if self.reason:
            pose = np.asarray(self.executor.pose(), np.float32)
            still = np.zeros((count, NUM_LEGS), np.float32)
            return Seconds(poses=np.repeat(pose[None], count, axis=0), contacts=still, invalid_reason=self.reason,
                           leg_travel=still, leg_commanded=still)
        seconds = self.executor.run(params)
        self.reason = int(seconds.invalid_reason)
        return seconds

    def _last(self, before: jax.Array, seconds: Seconds) -> Second:
        """The last of the reported `seconds` as a `Second`, its displacement from the pose `before` (1, 3)."""
        after = jnp.asarray(seconds.poses[-1:], jnp.float32)
        travel = np.zeros((1, NUM_LEGS), np.float32) if seconds.leg_travel is None else seconds.leg_travel[-1:]
        commanded = None if seconds.leg_commanded is None else jnp.asarray(seconds.leg_commanded[-1:], jnp.float32)
        reason = jnp.asarray([int(seconds.invalid_reason)], jnp.int32)
        return Second(state=None, pose=after, displacement=relative_pose(before, after), valid=reason == 0,
                      invalid_reason=reason, contact_fraction=jnp.asarray(seconds.contacts[-1:], jnp.float32),
                      leg_travel=jnp.asarray(travel, jnp.float32), leg_commanded=commanded)

    def second(self, state, hbr, elite, found, alive) -> Second:
        return self._last(self.pose(), self._run(np.asarray(hbr.middle_params[elite], np.float32)))

    def neutral(self, state) -> Second:
        return self._last(self.pose(), self._run(np.zeros((1, NUM_PARAMS), np.float32)))

    def flat(self, state, params) -> tuple[Second, jax.Array]:
        origin = self.pose()
        controller = np.asarray(params[0], np.float32)
        seconds = self._run(np.stack([controller] * (SECONDS_PER_ACTION - 1) + [np.zeros(NUM_PARAMS, np.float32)]))
        return self._last(origin, seconds), jnp.asarray(np.asarray(seconds.poses, np.float32)[None])  # (1, 4, 3)


def run_episode(maze: Maze, config: AdaptationConfig, skills: Skills, executor: Executor, variant: str = "hte",
                key: jax.Array | None = None, damage: np.ndarray | Damage | None = None) -> Episodes:
    """One episode of `variant` on the robot `executor` drives, from where it stands, as `Episodes` (B = 1, no
    `sim`). damage: the true damage that only Perfect HTE's oracle reads (its legs), a (6,) bool leg mask or an
    unbatched `Damage` (default: intact)."""
    chosen = variant_named(variant)
    chosen.check_skills(skills)
    damage = np.zeros(NUM_LEGS, bool) if damage is None else damage
    key = jax.random.PRNGKey(0) if key is None else key
    robot = ExecutorRobot(executor)
    batched = jax.tree.map(lambda x: np.asarray(x)[None], damage)
    episodes = start_episodes(config, skills, robot.pose(), batched, (chosen.rule,), np.zeros(1, np.int32), key)
    # Committed inputs, as in `episode.run_episodes` (jit keys its cache on committed-ness).
    field, skills, episodes = jax.device_put((distance_field(maze, config.grid), skills, episodes), jax.devices()[0])
    while not bool(episodes.done[0]):
        decision = plan_step(maze, config, skills, field, episodes)
        episodes = record_action(maze, config, skills, episodes, decision, execute(robot, skills, episodes, decision))
    return episodes


_target_tables = jax.jit(jax.vmap(target_table))  # (S, 36) -> (S, 100, 18)


@functools.partial(jax.jit, static_argnames=("limits",))
def _reasons(qpos: jax.Array, qvel: jax.Array, limits: ValidityLimits) -> jax.Array:
    """(T,) `check_state` bits of T states (T, 25), (T, 24)."""
    return jax.vmap(lambda q, v: check_state(q, v, limits))(qpos, qvel)


def _host_damage(damage, config: RobotConfig) -> Damage:
    """`damage` (a (6,) bool leg mask under `config.damage_model`, or an unbatched `Damage`) in NumPy."""
    damage = damage if isinstance(damage, Damage) else np.asarray(damage, bool)
    return jax.tree.map(np.asarray, as_damage(damage, config.damage_model, xp=np))


def _damaged_model(config: RobotConfig, given, damage: Damage) -> mujoco.MjModel:
    """The native model of `config` (shared), or a copy with the model values of `damage` (`damage.edited_native_model`)
    where it changes them."""
    model = mj_model(config)
    if not edits_model(given, config.damage_model):
        return model
    return edited_native_model(model, damage, robot_info(model, config))


class MujocoExecutor:
    """One hexapod in native MuJoCo, run second by second as the MJX rollout runs it (damage a (6,) bool leg mask or
    an unbatched `Damage`, start an unbatched SimState); at its first invalid state (`limits`) it is put back to the
    state before and stops."""

    def __init__(self, config: RobotConfig, damage: np.ndarray | Damage, start: SimState,
                 limits: ValidityLimits = ONLINE_LIMITS):
        self.config, self.limits = config, limits
        self.damage = _host_damage(damage, config)
        self.touching = np.asarray(touching_feet(self.damage))
        self.model = _damaged_model(config, damage, self.damage)
        self.data = mujoco.MjData(self.model)
        info = robot_info(self.model, config)
        self.joints, self.feet = np.asarray(info.joint_qpos), np.asarray(info.foot_geoms)
        self.neutral = np.asarray(_target_tables(jnp.zeros((1, NUM_PARAMS), jnp.float32)), np.float64)[0]
        self._set(np.asarray(start.qpos), np.asarray(start.qvel), np.asarray(start.qacc_warmstart))

    @classmethod
    def in_maze(cls, maze: Maze, damage: np.ndarray | Damage, base: RobotConfig = RobotConfig()) -> MujocoExecutor:
        """A robot with `damage` (a (6,) bool leg mask under `base.damage_model` or an unbatched `Damage`, e.g. of
        `damage.parse_damages`) settled standing (as `arena.start_states`) and turned to the maze's start."""
        plain = dataclasses.replace(base, walls=())
        model = mj_model(plain)
        qpos = model.qpos0.copy()
        joints = np.asarray(robot_info(model, plain).joint_qpos)
        qpos[joints] = held_targets(qpos[joints], _host_damage(damage, plain), np)
        zeros = np.zeros(model.nv)
        settling = cls(plain, damage, SimState(qpos=qpos, qvel=zeros, qacc_warmstart=zeros), ValidityLimits())
        settling.run(np.zeros((1, NUM_PARAMS), np.float32))
        settled = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32)[None], settling.state())
        settled = settled.replace(qpos=settled.qpos.at[:, :2].set(0.0))
        placed = place(settled, jnp.asarray(maze.start, jnp.float32)[None])
        return cls(maze_config(maze, base), damage, jax.tree.map(lambda x: x[0], placed))

    def _set(self, qpos: np.ndarray, qvel: np.ndarray, warmstart: np.ndarray) -> None:
        self.data.qpos[:], self.data.qvel[:], self.data.qacc_warmstart[:] = qpos, qvel, warmstart

    def state(self) -> SimState:
        """The robot's state now (unbatched, float64 NumPy)."""
        return SimState(qpos=self.data.qpos.copy(), qvel=self.data.qvel.copy(),
                        qacc_warmstart=self.data.qacc_warmstart.copy())

    def pose(self) -> np.ndarray:
        qpos = jnp.asarray(self.data.qpos[:7], jnp.float32)
        return np.asarray(planar_pose(qpos[:3], qpos[3:7]))

    def run(self, params: np.ndarray) -> Seconds:
        params = np.asarray(params, np.float32).reshape(-1, NUM_PARAMS)
        tables = np.asarray(_target_tables(jnp.asarray(params)), np.float64)  # (S, 100, 18)
        poses, contacts, travel, asked = (np.zeros((tables.shape[0], size), np.float32)
                                          for size in (3, NUM_LEGS, NUM_LEGS, NUM_LEGS))
        reason = 0
        for second, table in enumerate(tables):
            if not reason:
                reason, contacts[second], travel[second], asked[second] = self._second(table)
            poses[second] = self.pose()
        return Seconds(poses=poses, contacts=contacts, invalid_reason=reason, leg_travel=travel, leg_commanded=asked)

    def _second(self, table: np.ndarray) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """One second of joint targets `table` (100, 18): (invalid reason, contact fractions (6,), leg travel (6,),
        commanded leg travel (6,): the gait's target moves on the control steps the tilt reflex did not hold)."""
        model, data = self.model, self.data
        steps, substeps = STEP_CONTROL_STEPS, self.config.substeps
        qpos, qvel, warm = (np.zeros((steps + 1, size)) for size in (model.nq, model.nv, model.nv))
        qpos[0], qvel[0], warm[0] = data.qpos, data.qvel, data.qacc_warmstart  # row k + 1: after control step k
        touching = np.zeros((steps, NUM_LEGS), bool)
        braced = np.False_
        gait_moves = np.abs(table - np.roll(table, 1, axis=0))  # (100, 18) row k: |target(k) - target(k - 1)|
        asked = np.zeros((steps, table.shape[1]))  # the gait's moves on the steps it ran, as in `rollout`
        for k in range(steps):
            row = k % SAMPLES_PER_PERIOD
            data.ctrl[:], braced = control(self.config, self.joints, data.qpos, table[row], self.neutral[row],
                                           self.damage, braced, np.False_, xp=np)
            if not braced:
                asked[k] = gait_moves[row]
            for _ in range(substeps):
                mujoco.mj_step(model, data)
            # geom_xpos comes from the step's forward pass: the feet at the start of the step, as in MJX.
            touching[k] = (data.geom_xpos[self.feet, 2] - FOOT_RADIUS < RolloutSpec.contact_tolerance) & self.touching
            qpos[k + 1], qvel[k + 1], warm[k + 1] = data.qpos, data.qvel, data.qacc_warmstart
        reasons = np.asarray(_reasons(jnp.asarray(qpos[1:], jnp.float32), jnp.asarray(qvel[1:], jnp.float32),
                                      self.limits))
        bad = np.flatnonzero(reasons)
        valid = int(bad[0]) if bad.size else steps  # control steps before the first invalid state
        if bad.size:  # back to the last valid state
            self._set(qpos[valid], qvel[valid], warm[valid])
        moved = np.abs(np.diff(qpos[: valid + 1, self.joints], axis=0))  # (valid, 18) per control step

        def per_leg(travel):  # (valid, 18) -> (6,)
            return travel.sum(axis=0).reshape(NUM_LEGS, -1).sum(axis=-1)

        return (int(reasons[valid]) if bad.size else 0, touching[:valid].sum(axis=0) / steps, per_leg(moved),
                per_leg(asked[:valid]))
