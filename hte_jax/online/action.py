"""One action of B robots: a 3 s skill, then 1 s of the neutral pose (`docs/design.md`, Reset-free episodes).

The robots are a strategy object with `pose`, `second`, `neutral`, `flat`, `steps` and `staged`:
`SimulatedRobots` (MJX, inside the episode's jit) or `external.ExecutorRobot` (driven from the host).
`joint_action` acts several batches of simulated robots at once, each second one rollout of all of them.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
from flax import struct

from hte_jax.geometry import compose_pose, planar_pose, relative_pose
from hte_jax.hbr.composition import plan_batch
from hte_jax.hbr.hierarchy import (ANY_PATTERN, HBR, STEPS_PER_SKILL, StepResult, run_controllers, run_elite,
                                   skill_waypoints, state_pose, step_elite)
from hte_jax.online.rules import RuleBatch, StepContext, StepObservation, choose_patterns, learn_rules, relative_error_of
from hte_jax.online.secondary import ERROR_DIM
from hte_jax.online.skills import Skills, displacement_of
from hte_jax.sharding import join_rows, split_rows, where_rows
from hte_jax.sim.controller import NUM_PARAMS
from hte_jax.sim.damage import Damage, damage_legs
from hte_jax.sim.robot import NUM_LEGS, Robot
from hte_jax.sim.env import SimState, ValidityLimits
from hte_jax.sim.rollout import RolloutSpec, rollout

STEP_CONTROL_STEPS = 100  # one second
SECONDS_PER_ACTION = STEPS_PER_SKILL + 1
ONLINE_LIMITS = ValidityLimits(max_tilt=math.pi / 2, min_base_height=0.0, body_on_floor=False)


@struct.dataclass
class Second:
    """What B robots did in one second: state SimState (B, ...) (None if host-driven), pose (B, 3) world, displacement
    (B, 3) in the frame before, valid (B,), invalid_reason (B,) int32, contact_fraction (B, 6) share of the second
    each foot was down, leg_travel (B, 6) rad each leg's joints moved, qpos (B, F, 25) or None, leg_commanded (B, 6)
    rad its joint targets moved (what its controller commanded, after the tilt reflex) or None (not reported)."""

    state: SimState | None
    pose: jax.Array
    displacement: jax.Array
    valid: jax.Array
    invalid_reason: jax.Array
    contact_fraction: jax.Array
    leg_travel: jax.Array
    qpos: jax.Array | None = None
    leg_commanded: jax.Array | None = None


@struct.dataclass
class ActionOutcome:
    """B robots after one action: state (as `Second`), valid (B,), invalid_reason (B,) int32, poses (B, 4, 3) after
    each second, displacement (B, 3) in the pre-action frame; per step (-1 or 0 for flat skills and steps not run)
    patterns (B, 3) int32, middle_index (B, 3) int32, errors (B, 3, 3) relative, contacts and leg_travel (B, 3, 6);
    rules after it (None for flat skills); qpos (B, 400 / k, 25) every k = `record_every` control steps, or None."""

    state: SimState | None
    valid: jax.Array
    invalid_reason: jax.Array
    poses: jax.Array
    displacement: jax.Array
    patterns: jax.Array
    middle_index: jax.Array
    errors: jax.Array
    contacts: jax.Array
    leg_travel: jax.Array
    rules: RuleBatch | None
    qpos: jax.Array | None = None


@dataclasses.dataclass(frozen=True)
class SimulatedRobots:
    """B robots in MJX with damage: a (B, 6) bool leg mask (under the robot's `damage_model`) or a `Damage` (B, ...);
    record_every k > 0 (dividing 100) records the state every k steps."""

    robot: Robot
    damage: jax.Array | Damage
    record_every: int = 0

    def pose(self, state: SimState) -> jax.Array:
        return state_pose(state)

    def staged(self, fn):
        return fn  # already inside the episode's jitted program

    def steps(self, step, carry, xs):
        return jax.lax.scan(step, carry, xs)

    def second(self, state: SimState, hbr: HBR, elite: jax.Array, found: jax.Array, alive: jax.Array) -> Second:
        return second_of(run_elite(self.robot, hbr, state, self.damage, elite, found, ONLINE_LIMITS, self.record_every))

    def controllers(self, state: SimState, params: jax.Array) -> Second:
        """Controllers `params` (B, 36) for one second."""
        return second_of(run_controllers(self.robot, params, state, self.damage, STEP_CONTROL_STEPS, ONLINE_LIMITS,
                                         self.record_every))

    def neutral(self, state: SimState) -> Second:
        spec = RolloutSpec(num_steps=STEP_CONTROL_STEPS, record_contacts=False, limits=ONLINE_LIMITS,
                           record_qpos_every=self.record_every)
        result = rollout(self.robot, jnp.zeros((state.qpos.shape[0], NUM_PARAMS)), self.damage, state, spec)
        zeros = jnp.zeros_like(damage_legs(self.damage), jnp.float32)
        return Second(state=result.final_state, pose=state_pose(result.final_state), displacement=jnp.zeros_like(
            zeros[:, :3]), valid=result.valid, invalid_reason=result.invalid_reason, contact_fraction=zeros,
            leg_travel=zeros, qpos=result.qpos)

    def flat(self, state: SimState, params: jax.Array) -> tuple[Second, jax.Array]:
        """Controllers `params` (B, 36) for 3 s, then the neutral second, in one rollout: the last `Second`
        (displacement: the whole action's) and the poses (B, 4, 3)."""
        segments = jnp.stack([params] * STEPS_PER_SKILL + [jnp.zeros_like(params)], axis=1)  # (B, 4, 36)
        total = SECONDS_PER_ACTION * STEP_CONTROL_STEPS
        spec = RolloutSpec(num_steps=total, pose_steps=tuple(range(0, total + 1, STEP_CONTROL_STEPS)),
                           record_contacts=False, limits=ONLINE_LIMITS, record_qpos_every=self.record_every)
        result = rollout(self.robot, segments, self.damage, state, spec)
        poses = planar_pose(result.base_pos, result.base_quat)  # (B, 5, 3)
        zeros = jnp.zeros_like(damage_legs(self.damage), jnp.float32)
        last = Second(state=result.final_state, pose=poses[:, -1], displacement=relative_pose(poses[:, 0], poses[:, -1]),
                      valid=result.valid, invalid_reason=result.invalid_reason, contact_fraction=zeros,
                      leg_travel=zeros, qpos=result.qpos)
        return last, poses[:, 1:]


def second_of(result: StepResult) -> Second:
    """The `Second` of a simulated step."""
    return Second(state=result.state, pose=state_pose(result.state), displacement=result.displacement,
                  valid=result.valid, invalid_reason=result.invalid_reason, contact_fraction=result.contact_fraction,
                  leg_travel=result.leg_travel, qpos=result.qpos, leg_commanded=result.leg_commanded)


def skill_targets(skills: Skills, index: jax.Array, origin: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World waypoints (B, 3, 3) and stored end poses (B, 3) of HBR skills `index` (B,) from poses `origin` (B, 3)."""
    targets = compose_pose(origin[:, None, :], skill_waypoints(skills.hbr.middle_task, skills.genotypes[index]))
    goal = compose_pose(origin, displacement_of(skills.actions.prior[index]))
    return targets, goal


def choose_step(skills: Skills, rules: RuleBatch, here: jax.Array, target: jax.Array, goal: jax.Array,
                step: jax.Array, taken: jax.Array, keys: jax.Array, alive: jax.Array):
    """Before step `step` (0-2), robots at world poses `here` (B, 3) heading for `target` (B, 3), then `goal`
    (B, 3): each rule's pattern (B,) int32 (-1 unless `alive`), the middle elite (B,) and whether it has that
    pattern (B,) bool. taken: (B,) actions so far (GP-UCB's t = 1 + step + 3 taken). keys: (B, 2)."""
    hbr, task = skills.hbr, skills.hbr.middle_task
    desired = task.normalise(relative_pose(here, target))
    context = StepContext(hbr=hbr, desired=desired, t=1 + step + STEPS_PER_SKILL * taken, keys=keys)
    pattern, spare = choose_patterns(rules, context)
    pattern = jnp.where(alive, pattern, ANY_PATTERN)
    left = STEPS_PER_SKILL - step  # steps of the plan towards `goal`
    elite = None if skills.table is None else plan_batch(skills.table, task, here, goal, pattern, left)
    sees_spare = None
    if skills.spare is not None:
        elite = jnp.where(spare, plan_batch(skills.spare, task, here, goal, pattern, left), elite)
        sees_spare = spare & (pattern < 0) & alive  # no pattern to plan for: the nearest elite, spare ones included
    index, found = step_elite(hbr, here, target, pattern, elite=elite, spare=sees_spare)
    return pattern, index, found


def learn_step(skills: Skills, rules: RuleBatch, elite: jax.Array, second: Second) -> tuple[RuleBatch, jax.Array]:
    """The rules after learning from the step of middle elites `elite` (B,), and its relative errors (B, 3)."""
    observation = StepObservation(hbr=skills.hbr, elite=elite, observed=skills.hbr.middle_task.normalise(second.displacement),
                                  contact_fraction=second.contact_fraction, leg_travel=second.leg_travel,
                                  leg_commanded=second.leg_commanded)
    return learn_rules(rules, observation), relative_error_of(observation)


def hbr_choose(robots, skills: Skills, goal: jax.Array, taken: jax.Array, carry, xs):
    """Each robot's pattern, middle elite and whether it has the pattern (`choose_step`) before one 1 s step of
    HBR skills. carry: (state, rules, alive (B,) bool); xs: (target (B, 3), step () int32, keys (B, 2))."""
    state, rules, alive = carry
    target, step, keys = xs
    return robots.staged(choose_step)(skills, rules, robots.pose(state), target, goal, step, taken, keys, alive)


def hbr_learn(robots, skills: Skills, carry, chosen, second: Second):
    """The carry after the step `second` of the `chosen` elites, and the step's record."""
    _, rules, alive = carry
    pattern, elite, _ = chosen
    rules, error = robots.staged(learn_step)(skills, rules, elite, second)
    record = (pattern, jnp.where(alive, elite, -1), error, second.invalid_reason, second.pose, second.contact_fraction,
              second.leg_travel, second.qpos)
    return (second.state, rules, alive & (second.invalid_reason == 0)), record


def hbr_step(robots, skills: Skills, goal: jax.Array, taken: jax.Array, carry, xs):
    """One 1 s step of B HBR skills: choose, run, learn. carry and xs as `hbr_choose`'s. Returns the carry and
    the step's record."""
    chosen = hbr_choose(robots, skills, goal, taken, carry, xs)
    second = robots.second(carry[0], skills.hbr, chosen[1], chosen[2], carry[2])
    return hbr_learn(robots, skills, carry, chosen, second)


def hbr_start(robots, skills: Skills, state: SimState | None, rules: RuleBatch, action: jax.Array, keys: jax.Array):
    """(origin (B, 3), goal (B, 3), carry, xs (3, ...)) of HBR skills `action` (B,) from `state`: `hbr_step`'s scan."""
    origin = robots.pose(state)
    targets, goal = robots.staged(skill_targets)(skills, action, origin)  # (B, 3, 3), (B, 3)
    step_keys = jnp.swapaxes(jax.vmap(lambda k: jax.random.split(k, STEPS_PER_SKILL))(keys), 0, 1)  # (3, B, 2)
    xs = (jnp.swapaxes(targets, 0, 1), jnp.arange(STEPS_PER_SKILL, dtype=jnp.int32), step_keys)
    return origin, goal, (state, rules, jnp.ones(action.shape[0], bool)), xs


def hbr_outcome(origin: jax.Array, rules: RuleBatch, records, rest: Second) -> ActionOutcome:
    """The outcome of HBR skills from world poses `origin` (B, 3): their steps' stacked `hbr_learn` records
    (3, B, ...), the rules after them and the neutral second `rest`."""
    patterns, middle, errors, reasons, poses, contacts, travel, qpos = records
    return ActionOutcome(
        state=rest.state, valid=(reasons == 0).all(axis=0) & rest.valid,
        invalid_reason=jnp.bitwise_or.reduce(reasons, axis=0) | rest.invalid_reason,
        poses=jnp.concatenate([jnp.swapaxes(poses, 0, 1), rest.pose[:, None]], axis=1),
        displacement=relative_pose(origin, rest.pose), patterns=patterns.T, middle_index=middle.T,
        errors=jnp.swapaxes(errors, 0, 1), contacts=jnp.swapaxes(contacts, 0, 1),
        leg_travel=jnp.swapaxes(travel, 0, 1), rules=rules, qpos=_action_states(qpos, rest.qpos))


def _action_states(steps: jax.Array | None, rest: jax.Array | None) -> jax.Array | None:
    """An action's recorded states (B, F, 25) from its steps' (3, B, F / 4, 25) and the neutral second's
    (B, F / 4, 25); None when not recorded."""
    if steps is None:
        return None
    steps = jnp.swapaxes(steps, 0, 1)
    return jnp.concatenate([steps.reshape(steps.shape[0], -1, steps.shape[-1]), rest], axis=1)


def hbr_action(robots, skills: Skills, state: SimState | None, rules: RuleBatch, action: jax.Array, taken: jax.Array,
               keys: jax.Array) -> ActionOutcome:
    """Run HBR skills `action` (B,) step by step from `state`, then 1 s neutral; keys (B, 2) are split per step."""
    origin, goal, carry, xs = hbr_start(robots, skills, state, rules, action, keys)
    (state, rules, _), records = robots.steps(lambda c, x: hbr_step(robots, skills, goal, taken, c, x), carry, xs)
    return hbr_outcome(origin, rules, records, robots.neutral(state))


def flat_action(robots, state: SimState | None, params: jax.Array) -> ActionOutcome:
    """Run flat controllers `params` (B, 36), each for 3 s, then 1 s neutral."""
    return flat_outcome(*robots.flat(state, params))


def flat_outcome(last: Second, poses: jax.Array) -> ActionOutcome:
    """The outcome of a flat action from its last `Second` (displacement: the whole action's) and its poses (B, 4, 3)
    after each second."""
    batch = poses.shape[0]
    still = jnp.zeros((batch, STEPS_PER_SKILL, NUM_LEGS), jnp.float32)  # no contacts or leg travel recorded
    return ActionOutcome(
        state=last.state, valid=last.valid, invalid_reason=last.invalid_reason, poses=poses,
        displacement=last.displacement, patterns=jnp.full((batch, STEPS_PER_SKILL), ANY_PATTERN, jnp.int32),
        middle_index=jnp.full((batch, STEPS_PER_SKILL), -1, jnp.int32), contacts=still, leg_travel=still,
        errors=jnp.zeros((batch, STEPS_PER_SKILL, ERROR_DIM), jnp.float32), rules=None, qpos=last.qpos)


@struct.dataclass
class Part:
    """One batch's share of a `joint_action`: skills; state SimState (B, ...); rules RuleBatch (None for flat
    skills); choice (B,) int32 HBR skills, or (B, 36) flat controllers; taken (B,) int32 actions so far; keys
    (B, 2) the execution's."""

    skills: Skills
    state: SimState
    rules: RuleBatch | None
    choice: jax.Array
    taken: jax.Array
    keys: jax.Array


def _flat_second(carry, second: Second):
    """A flat part's carry (state, first invalid reason (B,) int32) after `second`, and its record (pose, qpos)."""
    state, reason = carry
    alive = reason == 0  # a robot that went invalid stays where it stopped
    state = where_rows(alive, second.state, state)
    qpos = None
    if second.qpos is not None:  # an invalid robot's states: where it stopped
        qpos = where_rows(alive, second.qpos, jnp.broadcast_to(state.qpos[:, None], second.qpos.shape))
    return (state, jnp.where(alive, second.invalid_reason, reason)), (state_pose(state), qpos)


def joint_action(robots: SimulatedRobots, parts: tuple[Part, ...]) -> tuple[ActionOutcome, ...]:
    """One action of several batches of simulated robots (`hbr_action` or `flat_action` each) with every second of
    all of them one rollout: a batch's action costs what its rows add, not a rollout of its own. `robots.damage`
    holds every part's rows, in order. A flat part's robot that goes invalid stays where it stopped, as in
    `flat_action`'s single rollout."""
    sizes = [p.choice.shape[0] for p in parts]
    starts, carries, xs = [], [], []
    for p in parts:
        if p.skills.hierarchical:
            origin, goal, carry, x = hbr_start(robots, p.skills, p.state, p.rules, p.choice, p.keys)
        else:
            origin, goal, x = robots.pose(p.state), None, None
            carry = (p.state, jnp.zeros(p.choice.shape[0], jnp.int32))
        starts.append((origin, goal))
        carries.append(carry)
        xs.append(x)

    def second(carries, xs):
        chosen = [hbr_choose(robots, p.skills, goal, p.taken, c, x) if p.skills.hierarchical else None
                  for p, (_, goal), c, x in zip(parts, starts, carries, xs)]
        params = [p.skills.hbr.middle_params[c[1]] if p.skills.hierarchical else p.choice
                  for p, c in zip(parts, chosen)]
        seconds = split_rows(robots.controllers(join_rows([c[0] for c in carries]), join_rows(params)), sizes)
        stepped = [hbr_learn(robots, p.skills, c, ch, s) if p.skills.hierarchical else _flat_second(c, s)
                   for p, c, ch, s in zip(parts, carries, chosen, seconds)]
        return tuple(s[0] for s in stepped), tuple(s[1] for s in stepped)

    carries, records = jax.lax.scan(second, tuple(carries), tuple(xs), length=STEPS_PER_SKILL)
    rests = split_rows(robots.neutral(join_rows([c[0] for c in carries])), sizes)
    outcomes = []
    for p, (origin, _), carry, record, rest in zip(parts, starts, carries, records, rests):
        if p.skills.hierarchical:
            outcomes.append(hbr_outcome(origin, carry[1], record, rest))
            continue
        (state, reason), last = _flat_second(carry, rest)
        poses = jnp.concatenate([jnp.swapaxes(record[0], 0, 1), last[0][:, None]], axis=1)  # (B, 4, 3)
        qpos = _action_states(record[1], last[1])
        zeros = jnp.zeros((reason.shape[0], NUM_LEGS), jnp.float32)
        outcomes.append(flat_outcome(Second(
            state=state, pose=poses[:, -1], displacement=relative_pose(origin, poses[:, -1]), valid=reason == 0,
            invalid_reason=reason, contact_fraction=zeros, leg_travel=zeros, qpos=qpos), poses))
    return tuple(outcomes)
