"""Hierarchical execution, batched and jittable: per 1 s step, the middle elite (optionally of one contact
pattern) whose primary descriptor is nearest to the next waypoint seen from the robot's current pose, so
a step that fell short is corrected by the next (as the original does at deployment)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hte_jax.hbr.composition import PatternTable, StepModel, plan_batch
from hte_jax.geometry import compose_pose, planar_pose, relative_pose
from hte_jax.hbr.middle import PRIMARY, MiddleTask, elite_controllers, pattern_code
from hte_jax.hbr.skill_grid import TopTask
from hte_jax.qd.archive import map_rows, squared_distance
from hte_jax.qd.repertoire import Repertoire
from hte_jax.sim.damage import Damage, batch_damage
from hte_jax.sim.robot import NUM_JOINTS, NUM_LEGS, Robot
from hte_jax.sim.env import SimState, ValidityLimits
from hte_jax.sim.rollout import RolloutSpec, rollout

STEPS_PER_SKILL = 3
ANY_PATTERN = -1


@struct.dataclass
class HBR:
    """A trained hierarchical behavioural repertoire: bottom genotypes (Cb, 6), descriptors (Cb, 3) (swing,
    height, duty); middle (Cm, 18), (Cm, 9) (x, y, yaw, 6 contact bits); top (Ct, 9), (Ct, 2) (final x, y).
    middle_params: (Cm, 36) controllers (zeros where empty). middle_patterns: (Cm,) int32 (-1 where empty).
    step_model: measured steps (`composition.StepModel`) or None. middle_task, top_task (Ct = bins^2): static.
    spare_count: the last middle slots, `spare.with_spare`'s elites (static; never `filled`, so unseen)."""

    bottom: Repertoire
    middle: Repertoire
    top: Repertoire
    middle_params: jax.Array
    middle_patterns: jax.Array
    middle_task: MiddleTask = struct.field(pytree_node=False, default=MiddleTask())
    step_model: StepModel | None = None
    top_task: TopTask = struct.field(pytree_node=False, default=TopTask())
    spare_count: int = struct.field(pytree_node=False, default=0)

    @classmethod
    def build(cls, bottom: Repertoire, middle: Repertoire, top: Repertoire, middle_task: MiddleTask,
              step_model: StepModel | None = None, top_task: TopTask = TopTask()) -> HBR:
        """Assemble the layers (concrete arrays) and precompute the middle elites' controllers and patterns (on
        the host)."""
        params = elite_controllers(bottom, middle.genotypes, middle.filled)
        codes = pattern_code(np.asarray(middle.descriptors)[:, PRIMARY:], xp=np)
        patterns = np.where(np.asarray(middle.filled), codes, ANY_PATTERN).astype(np.int32)
        return cls(bottom, middle, top, params, jax.device_put(patterns), middle_task, step_model, top_task)


@struct.dataclass
class StepResult:
    """One 1 s step of B robots: state (B, ...) after it, valid (B,), invalid_reason (B,) int32 `InvalidReason`
    bits, middle_index (B,) int32 elite run, pattern_found (B,) (False: no elite has the pattern, the nearest
    of any ran), displacement (B, 3) (x, y, yaw) in the step's start frame, contact_fraction (B, 6), qpos
    (B, F, 25) every `record_every` control steps or None, leg_travel (B, 6) rad each leg's joints moved and
    leg_commanded (B, 6) rad its joint targets moved (`RolloutResult.target_travel`: after the tilt reflex)."""

    state: SimState
    valid: jax.Array
    invalid_reason: jax.Array
    middle_index: jax.Array
    pattern_found: jax.Array
    displacement: jax.Array
    contact_fraction: jax.Array
    qpos: jax.Array | None = None
    leg_travel: jax.Array | None = None
    leg_commanded: jax.Array | None = None


@struct.dataclass
class SkillResult:
    """A 3 s skill of B robots: state (B, ...) at the end, valid (B,) (every step), displacement (B, 3)
    (x, y, yaw) in the start frame, steps: StepResult with leading (3, B)."""

    state: SimState
    valid: jax.Array
    displacement: jax.Array
    steps: StepResult


def state_pose(state: SimState, xp=jnp) -> jax.Array:
    """(B, 3) planar pose (x, y, heading) of robots `state` (B, ...) (jax or NumPy, `geometry.planar_pose`)."""
    return planar_pose(state.qpos[:, :3], state.qpos[:, 3:7], xp)


def select_middle(hbr: HBR, desired: jax.Array, pattern: jax.Array, chunk: int = 1024,
                  spare: jax.Array | None = None):
    """(index (B,) int32, found (B,) bool): the nearest middle elite in primary descriptor to `desired`
    (B, 3) among elites with `pattern` (B,) (-1: any); where none has it, the nearest of any (found False).
    spare: (B,) bool rows that also choose among the spare slots (`spare_count`, unfilled, so else unseen)."""
    points = hbr.middle.descriptors[:, :PRIMARY]
    spare_slots = jnp.arange(hbr.middle.capacity) >= hbr.middle.capacity - hbr.spare_count

    def block(args):
        q, p, *asks = args  # asks: (the rows' spare flags,) where `spare` is given
        usable = hbr.middle.filled[None, :]
        if asks:
            usable = usable | (spare_slots & asks[0][:, None])
        anywhere = jnp.where(usable, squared_distance(q, points), jnp.inf)
        matching = jnp.where((p[:, None] < 0) | (hbr.middle_patterns[None, :] == p[:, None]), anywhere, jnp.inf)
        found = jnp.isfinite(matching).any(axis=-1)
        index = jnp.where(found, jnp.argmin(matching, axis=-1), jnp.argmin(anywhere, axis=-1))
        return index.astype(jnp.int32), found

    rows, fills = (desired, pattern.astype(jnp.int32)), (0.0, ANY_PATTERN)
    if spare is not None:
        rows, fills = (*rows, jnp.asarray(spare, bool)), (*fills, False)
    return map_rows(block, rows, fills, chunk)


def step_elite(hbr: HBR, here: jax.Array, target: jax.Array, pattern: jax.Array,
               elite: jax.Array | None = None, spare: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """`select_middle`'s (index, found) for a step from world pose `here` (B, 3) towards `target` (B, 3), the
    spare slots seen by the rows of `spare`; elite (B,) int32: run instead where >= 0 (a planner's choice)."""
    index, found = select_middle(hbr, hbr.middle_task.normalise(relative_pose(here, target)), pattern, spare=spare)
    if elite is not None:
        index, found = jnp.where(elite >= 0, elite, index), found | (elite >= 0)
    return index, found


def run_controllers(robot: Robot, params: jax.Array, state: SimState, damage: jax.Array | Damage, steps: int,
                    limits: ValidityLimits = ValidityLimits(), record_every: int = 0) -> StepResult:
    """Simulate controllers `params` (B, 36) for one step of `steps` control steps from `state` under `damage` (a leg
    mask or a `Damage`, as `rollout` takes it); record_every > 0 also records qpos. middle_index is -1 and
    pattern_found True (no elite named)."""
    spec = RolloutSpec(num_steps=steps, pose_steps=(0, steps), record_contacts=True, limits=limits,
                       record_qpos_every=record_every, record_joint_travel=True)
    result = rollout(robot, params, damage, state, spec)
    poses = planar_pose(result.base_pos, result.base_quat)

    def per_leg(joints):  # (B, 18) -> (B, 6)
        return joints.reshape(-1, NUM_LEGS, NUM_JOINTS // NUM_LEGS).sum(axis=-1)

    batch = params.shape[0]
    return StepResult(state=result.final_state, valid=result.valid, invalid_reason=result.invalid_reason,
                      middle_index=jnp.full(batch, -1, jnp.int32), pattern_found=jnp.ones(batch, bool),
                      displacement=relative_pose(poses[:, 0], poses[:, 1]),
                      contact_fraction=result.foot_contacts.mean(axis=1), qpos=result.qpos,
                      leg_travel=per_leg(result.joint_travel), leg_commanded=per_leg(result.target_travel))


def run_elite(robot: Robot, hbr: HBR, state: SimState, damage: jax.Array | Damage, index: jax.Array,
              found: jax.Array, limits: ValidityLimits = ValidityLimits(), record_every: int = 0) -> StepResult:
    """Simulate middle elites `index` (B,) for one step from `state` (`run_controllers`)."""
    result = run_controllers(robot, hbr.middle_params[index], state, damage, hbr.middle_task.steps, limits,
                             record_every)
    return result.replace(middle_index=index, pattern_found=found)


def execute_step(robot: Robot, hbr: HBR, state: SimState, damage: jax.Array | Damage, target: jax.Array,
                 pattern: jax.Array, limits: ValidityLimits = ValidityLimits(), record_every: int = 0,
                 elite: jax.Array | None = None) -> StepResult:
    """Walk one second towards the world pose `target` (B, 3) with contact `pattern` (B,) (-1: any)."""
    index, found = step_elite(hbr, state_pose(state), target, pattern, elite)
    return run_elite(robot, hbr, state, damage, index, found, limits, record_every)


def skill_waypoints(task: MiddleTask, genotypes: jax.Array) -> jax.Array:
    """(..., 9) top genotypes -> (..., 3, 3) waypoints (x, y, yaw) in the skill's start frame."""
    steps = task.denormalise(genotypes.reshape(*genotypes.shape[:-1], STEPS_PER_SKILL, PRIMARY))
    pose, waypoints = jnp.zeros_like(steps[..., 0, :]), []
    for k in range(STEPS_PER_SKILL):
        pose = compose_pose(pose, steps[..., k, :])
        waypoints.append(pose)
    return jnp.stack(waypoints, axis=-2)


def execute_skill(robot: Robot, hbr: HBR, genotypes: jax.Array, start: SimState,
                  damage: jax.Array | Damage | None = None, patterns: jax.Array | None = None, record_every: int = 0,
                  table: PatternTable | None = None, ends: jax.Array | None = None,
                  limits: ValidityLimits = ValidityLimits()) -> SkillResult:
    """Execute (B, 9) top genotypes from `start` (B, ...) with damage (a (B, 6) or (6,) bool leg mask, or a `Damage`
    batched or not; None: intact), contact patterns (B, 3) (None or -1: any) and `run_elite`'s record_every
    (`steps.qpos` (3, B, F, 25)). table, ends (B, 3)
    (end poses in the start frame): a step with a pattern >= 0 runs the first step of a plan towards the end
    (`composition`). limits: when a step is invalid (default: training's)."""
    batch = genotypes.shape[0]
    damage = jnp.zeros((batch, NUM_LEGS), bool) if damage is None else batch_damage(damage, batch)
    patterns = jnp.full((batch, STEPS_PER_SKILL), ANY_PATTERN, jnp.int32) if patterns is None else patterns
    origin = state_pose(start)
    targets = compose_pose(origin[:, None, :], skill_waypoints(hbr.middle_task, genotypes))  # (B, 3, 3)
    goal = None if table is None else compose_pose(origin, ends)

    def one_step(state, xs):
        target, pattern, remaining = xs
        here = state_pose(state)
        elite = None if table is None else plan_batch(table, hbr.middle_task, here, goal, pattern, remaining)
        step = execute_step(robot, hbr, state, damage, target, pattern, limits, record_every=record_every, elite=elite)
        return step.state, step

    remaining = jnp.arange(STEPS_PER_SKILL, 0, -1, dtype=jnp.int32)
    xs = (jnp.swapaxes(targets, 0, 1), jnp.swapaxes(patterns, 0, 1), remaining)
    final, steps = jax.lax.scan(one_step, start, xs)
    return SkillResult(state=final, valid=steps.valid.all(axis=0),
                       displacement=relative_pose(origin, state_pose(final)), steps=steps)
