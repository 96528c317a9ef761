"""Hierarchical execution: a top-layer genotype down to joint commands, batched and jittable.

top genotype (9) -> three waypoints -> for each 1 s step, the middle elite whose primary
descriptor is nearest to the waypoint seen from the robot's current pose (optionally only among
elites with a chosen contact pattern) -> its six leg primitives -> one 36-parameter controller,
simulated for 1 s. Training of the top layer and the modulation analysis call `execute_skill` /
`execute_step`, the online phase `step_elite` and `run_elite` (the two halves of `execute_step`:
which elite, then its simulated second), so a skill is decoded the same way everywhere.

Waypoints: the genotype holds three middle-layer primary descriptors (normalised x, y, yaw
steps); waypoint k is the pose reached by composing the first k + 1 steps from the start pose.
Before each step the next waypoint is re-expressed in the robot's current frame, so a step that
fell short is corrected by the next one (the original does the same at deployment).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from hte_jax.hbr.composition import PatternTable, StepModel, plan_batch
from hte_jax.geometry import compose_pose, planar_pose, relative_pose
from hte_jax.hbr.middle import PRIMARY, MiddleTask, elite_controllers, pattern_code
from hte_jax.hbr.skill_grid import TopTask
from hte_jax.qd.archive import map_rows, squared_distance
from hte_jax.qd.repertoire import Repertoire
from hte_jax.sim.robot import NUM_JOINTS, NUM_LEGS, Robot
from hte_jax.sim.rollout import RolloutSpec, SimState, ValidityLimits, rollout

STEPS_PER_SKILL = 3
ANY_PATTERN = -1


@struct.dataclass
class HBR:
    """A trained hierarchical behavioural repertoire.

    bottom: leg primitives, genotypes (Cb, 6), descriptors (Cb, 3) (swing, height, duty).
    middle: body motions, genotypes (Cm, 18), descriptors (Cm, 9) (x, y, yaw, 6 contact bits).
    top: skills on a grid, genotypes (Ct, 9), descriptors (Ct, 2) (final x, y).
    middle_params: (Cm, 36) the controller of every middle elite (zeros where empty).
    middle_patterns: (Cm,) int32 contact pattern of every middle elite (-1 where empty).
    middle_task: how the middle layer was evaluated (static).
    step_model: the middle elites' steps measured from several start states (`composition.StepModel`,
      (Cm, 3) and (Cm,)), or None when not measured.
    top_task: the grid the top layer was trained on (static; Ct = bins^2).
    spare_count: how many of the middle slots, at the end, are a second archive's elites appended
      for spare sets (`spare.with_spare`; static, 0 for an HBR as trained). They are never
      `filled`, so no lookup of the HBR's own sees them.
    """

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
        """Assemble the layers and precompute the middle elites' controllers and patterns."""
        params = elite_controllers(bottom, middle.genotypes, middle.filled)
        patterns = jnp.where(middle.filled, pattern_code(middle.descriptors[:, PRIMARY:]), ANY_PATTERN)
        return cls(bottom, middle, top, params, patterns.astype(jnp.int32), middle_task, step_model, top_task)


@struct.dataclass
class StepResult:
    """One 1 s step of B robots.

    state: SimState (B, ...) after the step. valid: (B,) bool. invalid_reason: (B,) int32
      `InvalidReason` bits (0 if valid).
    middle_index: (B,) int32 middle elite executed. pattern_found: (B,) bool, False when no elite
      has the requested pattern (then the nearest elite of any pattern ran).
    displacement: (B, 3) (x, y, yaw) in the frame of the pose at the start of the step.
    contact_fraction: (B, 6) fraction of the step each foot was on the ground.
    qpos: (B, F, 25) qpos every `record_every` control steps of the step (replay), or None.
    leg_travel: (B, 6) rad each leg's three joints moved during the step (sum of |angle changes|).
    """

    state: SimState
    valid: jax.Array
    invalid_reason: jax.Array
    middle_index: jax.Array
    pattern_found: jax.Array
    displacement: jax.Array
    contact_fraction: jax.Array
    qpos: jax.Array | None = None
    leg_travel: jax.Array | None = None


@struct.dataclass
class SkillResult:
    """A 3 s skill of B robots.

    state: SimState (B, ...) at the end. valid: (B,) bool, every step valid.
    displacement: (B, 3) (x, y, yaw) in the start frame. steps: StepResult with leading (3, B).
    """

    state: SimState
    valid: jax.Array
    displacement: jax.Array
    steps: StepResult


def state_pose(state: SimState) -> jax.Array:
    """(B, 3) planar pose (x, y, heading) of robots `state` (B, ...)."""
    return planar_pose(state.qpos[:, :3], state.qpos[:, 3:7])


def select_middle(hbr: HBR, desired: jax.Array, pattern: jax.Array, chunk: int = 1024):
    """Nearest middle elite in primary descriptor to `desired` (B, 3), among elites with `pattern` (B,).

    pattern -1 means any. Returns (index (B,) int32, found (B,) bool); where no elite has the
    pattern, the nearest elite of any pattern is returned and found is False.
    """
    points = hbr.middle.descriptors[:, :PRIMARY]
    filled = hbr.middle.filled

    def block(args):
        q, p = args
        anywhere = jnp.where(filled[None, :], squared_distance(q, points), jnp.inf)
        matching = jnp.where((p[:, None] < 0) | (hbr.middle_patterns[None, :] == p[:, None]), anywhere, jnp.inf)
        found = jnp.isfinite(matching).any(axis=-1)
        index = jnp.where(found, jnp.argmin(matching, axis=-1), jnp.argmin(anywhere, axis=-1))
        return index.astype(jnp.int32), found

    return map_rows(block, (desired, pattern.astype(jnp.int32)), (0.0, ANY_PATTERN), chunk)


def _step_spec(steps: int, limits: ValidityLimits, record_every: int = 0) -> RolloutSpec:
    return RolloutSpec(num_steps=steps, pose_steps=(0, steps), record_contacts=True, limits=limits,
                       record_qpos_every=record_every, record_joint_travel=True)


def step_elite(
    hbr: HBR, here: jax.Array, target: jax.Array, pattern: jax.Array, query: jax.Array | None = None,
    elite: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """The middle elite a step from world pose `here` (B, 3) towards world pose `target` (B, 3) runs,
    among elites with contact `pattern` (B,) (-1: any): (index (B,) int32, found (B,) bool, False
    where no elite has the pattern). Its controller is `hbr.middle_params[index]` (B, 36).

    query: (B, 3) normalised primary step to look the elite up with instead of the step to `target`
    (an adaptation rule that aims off the target to cancel a predicted drift). elite: (B,) int32
    middle elite to run where >= 0 (chosen by a planner), instead of the looked-up one.
    """
    desired = hbr.middle_task.normalise(relative_pose(here, target)) if query is None else query
    index, found = select_middle(hbr, desired, pattern)
    if elite is not None:
        index, found = jnp.where(elite >= 0, elite, index), found | (elite >= 0)
    return index, found


def run_elite(
    robot: Robot, hbr: HBR, state: SimState, damage: jax.Array, index: jax.Array, found: jax.Array,
    limits: ValidityLimits = ValidityLimits(), record_every: int = 0,
) -> StepResult:
    """Simulate middle elites `index` (B,) (found (B,): `step_elite`'s) for one step from `state`.

    record_every: k > 0 also returns the qpos every k control steps (`StepResult.qpos`).
    """
    result = rollout(robot, hbr.middle_params[index], damage, state,
                     _step_spec(hbr.middle_task.steps, limits, record_every))
    poses = planar_pose(result.base_pos, result.base_quat)
    return StepResult(
        state=result.final_state,
        valid=result.valid,
        invalid_reason=result.invalid_reason,
        middle_index=index,
        pattern_found=found,
        displacement=relative_pose(poses[:, 0], poses[:, 1]),
        contact_fraction=result.foot_contacts.mean(axis=1),
        qpos=result.qpos,
        leg_travel=result.joint_travel.reshape(-1, NUM_LEGS, NUM_JOINTS // NUM_LEGS).sum(axis=-1),
    )


def execute_step(
    robot: Robot, hbr: HBR, state: SimState, damage: jax.Array, target: jax.Array, pattern: jax.Array,
    limits: ValidityLimits = ValidityLimits(), query: jax.Array | None = None, record_every: int = 0,
    elite: jax.Array | None = None,
) -> StepResult:
    """Walk one second towards the world pose `target` (B, 3) with contact `pattern` (B,) (-1: any).

    query, elite: see `step_elite`. record_every: k > 0 also returns the qpos every k control steps
    (`StepResult.qpos`).
    """
    index, found = step_elite(hbr, state_pose(state), target, pattern, query, elite)
    return run_elite(robot, hbr, state, damage, index, found, limits, record_every)


def skill_waypoints(task: MiddleTask, genotypes: jax.Array) -> jax.Array:
    """(..., 9) top genotypes -> (..., 3, 3) waypoints (x, y, yaw) in the skill's start frame."""
    steps = task.denormalise(genotypes.reshape(*genotypes.shape[:-1], STEPS_PER_SKILL, PRIMARY))
    pose = jnp.zeros_like(steps[..., 0, :])
    waypoints = []
    for k in range(STEPS_PER_SKILL):
        pose = compose_pose(pose, steps[..., k, :])
        waypoints.append(pose)
    return jnp.stack(waypoints, axis=-2)


def execute_skill(
    robot: Robot,
    hbr: HBR,
    genotypes: jax.Array,
    start: SimState,
    damage: jax.Array | None = None,
    patterns: jax.Array | None = None,
    record_every: int = 0,
    table: PatternTable | None = None,
    ends: jax.Array | None = None,
    limits: ValidityLimits = ValidityLimits(),
) -> SkillResult:
    """Execute (B, 9) top genotypes from `start` (B, ...) with damage (B, 6) and contact patterns (B, 3).

    damage None: intact. patterns None or -1 entries: nearest elite of any pattern. record_every:
    k > 0 records the qpos every k control steps (`steps.qpos`, (3, B, F, 25)). table and ends
    (B, 3) (the skills' end poses in the start frame): steps with a pattern >= 0 run the first step
    of a plan among that pattern's elites towards the end (`composition`), not the nearest elite to
    the next waypoint. limits: when a step is invalid (default: training's).
    """
    batch = genotypes.shape[0]
    damage = jnp.zeros((batch, NUM_LEGS), bool) if damage is None else jnp.broadcast_to(damage, (batch, NUM_LEGS))
    if patterns is None:
        patterns = jnp.full((batch, STEPS_PER_SKILL), ANY_PATTERN, jnp.int32)
    origin = state_pose(start)
    targets = compose_pose(origin[:, None, :], skill_waypoints(hbr.middle_task, genotypes))  # (B, 3, 3)

    goal = None if table is None else compose_pose(origin, ends)

    def one_step(state, xs):
        target, pattern, remaining = xs
        elite = None
        if table is not None:
            elite = plan_batch(table, hbr.middle_task, state_pose(state), goal, pattern, remaining)
        step = execute_step(robot, hbr, state, damage, target, pattern, limits, record_every=record_every, elite=elite)
        return step.state, step

    remaining = jnp.arange(STEPS_PER_SKILL, 0, -1, dtype=jnp.int32)
    xs = (jnp.swapaxes(targets, 0, 1), jnp.swapaxes(patterns, 0, 1), remaining)
    final, steps = jax.lax.scan(one_step, start, xs)
    end = state_pose(final)
    return SkillResult(
        state=final,
        valid=steps.valid.all(axis=0),
        displacement=relative_pose(origin, end),
        steps=steps,
    )
