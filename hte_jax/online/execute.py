"""Running the planner's chosen actions on the simulated, damaged robots: reset-free, batched.

An action is a 3 s skill followed by 1 s of the neutral pose (all controller parameters 0).
A flat repertoire's skill is its 36-parameter controller run for 3 s. An HBR's skill is a
top-layer genotype executed step by step; before each 1 s step the contact pattern of the middle
elite is chosen by the episode's rule (`variants`: the paper's GP-UCB, the oracle, a random
pattern, RTE's any pattern, and ours). A step is three parts, so that a robot simulated elsewhere
(`executor.py`) runs the same ones: `choose_step` (the pattern and the elite), the elite's second
(`hbr.execution.run_elite` here), `learn_step` (what the rules learn from it).

Rollouts here use `ONLINE_LIMITS`: the robot of the online phase has its body collide with the
floor, so a body on the floor is no longer an error, and only a robot tilted past 90 degrees (on
its side or back: it cannot get up), a non-finite or an exploding state ends an episode.

After each step the relative error (and the absolute deviation) between the executed elite's
stored primary descriptor and what the robot did is added to the secondary GP, and each leg's
sensed floor contact is added up beside the contact the elite expected, and each leg's joint travel
beside the travel its controller commanded (in every variant, so that all of them report it).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hte_jax.errors import ConfigError
from hte_jax.hbr.composition import COMPOSITIONS, PatternTable, plan_batch, planning_table
from hte_jax.hbr.execution import (
    ANY_PATTERN,
    HBR,
    STEPS_PER_SKILL,
    run_elite,
    skill_waypoints,
    state_pose,
    step_elite,
)
from hte_jax.geometry import compose_pose, planar_pose, relative_pose
from hte_jax.hbr.middle import PRIMARY
from hte_jax.hbr.pattern_ends import PatternEnds, planning_priors
from hte_jax.hbr.sparing import sparing_table
from hte_jax.hbr.top import TopTask
from hte_jax.online.actions import ActionSet, action_set, displacement_of
from hte_jax.online.gp import GPData, add_observation
from hte_jax.online.secondary import relative_error, step_targets
from hte_jax.online.variants import ERROR_DIM, PatternState, choose, rule_index, spares_now, step_context
from hte_jax.qd.repertoire import Repertoire
from hte_jax.sim.controller import NUM_PARAMS, commanded_travel
from hte_jax.sim.robot import NUM_LEGS, Robot
from hte_jax.sim.rollout import RolloutSpec, SimState, ValidityLimits, rollout

if TYPE_CHECKING:  # the episode module builds on this one
    from hte_jax.online.episode import Decision, Episodes

# The built-in rules' integers (`variants.rule_index`).
ANY_PATTERN_MODE, UCB_MODE, ORACLE_MODE, RANDOM_MODE, MISS_MODE, DRIFT_MODE, LEGS_MODE, CONTACTS_MODE = (
    rule_index(name) for name in ("any", "gp-ucb", "oracle", "random", "least-miss", "drift", "legs", "contacts"))
STEP_CONTROL_STEPS = 100  # one second
NEUTRAL_CONTROL_STEPS = 100  # the 1 s neutral pose after each skill
SECONDS_PER_ACTION = STEPS_PER_SKILL + 1
SECONDARY_DIM = 9  # the middle descriptor: x, y, yaw, 6 contact bits
SECONDARY_OUTPUTS = 3 * ERROR_DIM  # relative errors (the paper's), absolute deviations, signed deviations
ONLINE_LIMITS = ValidityLimits(max_tilt=math.pi / 2, min_base_height=0.0, body_on_floor=False)


@struct.dataclass
class Skills:
    """The A actions an episode batch plans with, from one repertoire or from K (APROL's set).

    actions: ActionSet (A,) with the RTE GP's inputs and prior; (K, A) for K repertoires.
    genotypes: (A, G) top-layer genotypes (G = 9) of an HBR, or controllers (G = 36) of a flat
      repertoire; (K, A, 36) for K flat repertoires.
    hbr: the HBR the top genotypes belong to, or None for flat repertoires.
    table: the HBR's elites grouped by pattern when a step with a chosen pattern plans its way to
      the skill's end (`composition="planned"`), or None for the paper's nearest elite to the
      next waypoint.
    sparing: the HBR's sparing sets (`hbr.sparing.sparing_table`) that episodes with
      `PatternState.sparing` plan their patterns' steps among, or None (no such episode).
    priors: (64, A, 4) each action's outcome prior when executed with each pattern (`hbr.pattern_ends
      .planning_priors`), what episodes with `PatternState.measured` plan with, or None.
    """

    actions: ActionSet
    genotypes: jax.Array
    hbr: HBR | None = None
    table: PatternTable | None = None
    sparing: PatternTable | None = None
    priors: jax.Array | None = None

    def planning_prior(self, learnt: PatternState) -> jax.Array | None:
        """(B, A, 4) the RTE GP's prior of every action for B episodes: the outcome measured under
        the pattern of each episode's last step where it plans with measured ends (and a pattern
        was chosen), the stored outcome elsewhere; None when no pattern ends were loaded."""
        if self.priors is None:
            return None
        use = learnt.measured & (learnt.last >= 0)
        measured = self.priors[jnp.maximum(learnt.last, 0)]  # (B, A, 4)
        return jnp.where(use[:, None, None], measured, self.actions.prior[None])

    @property
    def hierarchical(self) -> bool:
        return self.hbr is not None

    @property
    def num_maps(self) -> int:
        """K, the number of repertoires (1 unless APROL's set)."""
        return 1 if self.actions.mask.ndim == 1 else self.actions.mask.shape[0]

    @property
    def map_actions(self) -> ActionSet:
        """The actions with a leading (K,) repertoire axis (K = 1 for one repertoire)."""
        return self.actions if self.actions.mask.ndim == 2 else jax.tree.map(lambda x: x[None], self.actions)

    @property
    def map_genotypes(self) -> jax.Array:
        """(K, A, G) genotypes with a leading repertoire axis."""
        return self.genotypes if self.actions.mask.ndim == 2 else self.genotypes[None]


def hbr_skills(hbr: HBR, top_task: TopTask, pad_to: int | None = None, composition: str = "planned",
               sparing: bool = False, ends: PatternEnds | None = None) -> Skills:
    """The filled top-layer cells of an HBR as actions.

    composition: how a step with a chosen contact pattern picks its elite: "waypoints" (the
    paper's nearest elite to the next waypoint) or "planned" (`hbr.composition`: a plan among the
    pattern's elites to the skill's end, with the HBR's measured step model when it has one).
    sparing: also build the sparing sets (`hbr.sparing`) for variants that execute from them
    (planned composition only). ends: the skills' measured ends under each pattern
    (`hbr.pattern_ends`) for variants that plan with them (`Skills.priors`), or None.
    """
    if composition not in COMPOSITIONS:
        raise ValueError(f"unknown composition {composition!r}; choose from {', '.join(COMPOSITIONS)}")
    if sparing and composition != "planned":
        raise ConfigError("variants that execute from sparing sets need --composition planned")
    actions = action_set(hbr.top, top_task.extent, pad_to)
    genotypes = hbr.top.genotypes[jnp.maximum(actions.slots, 0)]
    table = planning_table(hbr) if composition == "planned" else None
    priors = None
    if ends is not None:
        priors = jnp.asarray(planning_priors(ends, np.asarray(actions.slots), np.asarray(actions.prior)))
    return Skills(actions=actions, genotypes=genotypes, hbr=hbr, table=table,
                  sparing=sparing_table(hbr) if sparing else None, priors=priors)


def flat_skills(repertoire: Repertoire, extent: float, pad_to: int | None = None) -> Skills:
    """The elites of a flat repertoire (2-D or 8-D descriptors) as actions."""
    actions = action_set(repertoire, extent, pad_to)
    genotypes = repertoire.genotypes[jnp.maximum(actions.slots, 0)]
    if genotypes.shape[-1] != NUM_PARAMS:
        raise ValueError(f"a flat repertoire holds {NUM_PARAMS}-parameter controllers, got {genotypes.shape[-1]} genes")
    return Skills(actions=actions, genotypes=genotypes)


def flat_skill_maps(repertoires: Repertoire, extent: float) -> Skills:
    """K flat repertoires (a `Repertoire` with a leading (K,) axis, e.g. APROL's 21) as actions with
    a leading (K,) axis, each padded to the largest one's number of elites."""
    count = int(jnp.asarray(repertoires.filled).sum(axis=-1).max())
    maps = [flat_skills(jax.tree.map(lambda x, k=k: x[k], repertoires), extent, pad_to=count)
            for k in range(repertoires.filled.shape[0])]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *maps)


@struct.dataclass
class ActionOutcome:
    """B robots after one action (3 s skill + 1 s neutral).

    state: SimState (B, ...) at the end (None when an executor drove the robot, `executor.py`). valid: (B,) bool, no rollout of the action went invalid.
    invalid_reason: (B,) int32 `InvalidReason` bits of the action's rollouts (0 if valid).
    poses: (B, 4, 3) world planar pose after each second. displacement: (B, 3) (dx, dy, dyaw) in the
    pre-action frame. patterns: (B, 3) int32 contact pattern asked for at each step (-1: any, and
    for flat skills). middle_index: (B, 3) int32 executed middle elite (-1 for flat skills).
    errors: (B, 3, 3) relative error (x, y, yaw) of each step (0 for flat skills).
    learnt: PatternState (B, ...) the pattern rules' state after this action's observations, or
      None for flat skills.
    qpos: (B, F, 25) the state every k = `record_every` control steps of the action, from its start
      (F = 400 / k; k divides 100, so every F / 4-th state starts a second), or None (not recorded).
    """

    state: SimState
    valid: jax.Array
    invalid_reason: jax.Array
    poses: jax.Array
    displacement: jax.Array
    patterns: jax.Array
    middle_index: jax.Array
    errors: jax.Array
    learnt: PatternState | None
    qpos: jax.Array | None = None


def neutral_second(robot: Robot, state: SimState, damage: jax.Array, record_every: int = 0):
    """The 1 s neutral pose (all-zero controllers) after a skill, from `state` (B, ...) under the
    online validity limits; record_every: k > 0 also records the qpos every k control steps."""
    spec = RolloutSpec(num_steps=NEUTRAL_CONTROL_STEPS, record_contacts=False, limits=ONLINE_LIMITS,
                       record_qpos_every=record_every)
    return rollout(robot, jnp.zeros((state.qpos.shape[0], NUM_PARAMS)), damage, state, spec)


def choose_patterns(
    hbr: HBR, mode: jax.Array, oracle: jax.Array, secondary: GPData, desired: jax.Array, t: jax.Array,
    keys: jax.Array, optimism: jax.Array | None = None, contacts: jax.Array | None = None,
    rules: tuple[str, ...] | None = None, motion: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Contact pattern (B,) for the next step of each robot by its rule (`variants.RULES`), and the
    primary step (B, 3) to look its elite up with (`desired`, except where a rule aims off it).

    mode, oracle: (B,) int32. secondary: GPData (B, ...). desired: (B, 3) normalised primary
    descriptor the step aims at. t: (B,) GP-UCB step count (>= 1). keys: (B, 2) PRNG keys.
    optimism: (B,) the predicted-miss rule's confidence weight (default 0). contacts: (B, 2, 6)
    sensed and expected contact seconds (default 0: nothing sensed yet). rules: the rule names in
    integer order (default: every registered rule). motion: (B, 2, 6) moved and commanded joint
    travel per leg, rad (default 0).
    """
    batch = desired.shape[0]
    optimism = jnp.zeros(batch, jnp.float32) if optimism is None else optimism
    contacts = jnp.zeros((batch, 2, NUM_LEGS), jnp.float32) if contacts is None else contacts
    motion = jnp.zeros((batch, 2, NUM_LEGS), jnp.float32) if motion is None else motion
    return choose(step_context(hbr, desired, t, keys, oracle, optimism, secondary, contacts, motion), mode, rules)


def execute_flat(robot: Robot, params: jax.Array, state: SimState, damage: jax.Array, learnt: PatternState | None = None,
                 record_every: int = 0) -> ActionOutcome:
    """Run flat controllers `params` (B, 36): each for 3 s, then 1 s neutral, in one rollout.

    record_every: k > 0 also returns the state every k control steps (`ActionOutcome.qpos`).
    """
    segments = jnp.stack([params] * STEPS_PER_SKILL + [jnp.zeros_like(params)], axis=1)  # (B, 4, 36)
    total = SECONDS_PER_ACTION * STEP_CONTROL_STEPS
    spec = RolloutSpec(num_steps=total, pose_steps=tuple(range(0, total + 1, STEP_CONTROL_STEPS)), record_contacts=False,
                       limits=ONLINE_LIMITS, record_qpos_every=record_every)
    # A controller's clock restarts with each 1 s segment; its period is 1 s, so 3 segments are one 3 s run.
    result = rollout(robot, segments, damage, state, spec)
    poses = planar_pose(result.base_pos, result.base_quat)  # (B, 5, 3)
    batch = params.shape[0]
    return ActionOutcome(
        state=result.final_state,
        valid=result.valid,
        invalid_reason=result.invalid_reason,
        poses=poses[:, 1:],
        displacement=relative_pose(poses[:, 0], poses[:, -1]),
        patterns=jnp.full((batch, STEPS_PER_SKILL), ANY_PATTERN, jnp.int32),
        middle_index=jnp.full((batch, STEPS_PER_SKILL), -1, jnp.int32),
        errors=jnp.zeros((batch, STEPS_PER_SKILL, ERROR_DIM), jnp.float32),
        learnt=learnt,
        qpos=result.qpos,
    )


def skill_targets(skills: Skills, index: jax.Array, origin: jax.Array) -> tuple[jax.Array, jax.Array]:
    """HBR skills `index` (B,) started at world poses `origin` (B, 3): their world waypoints (B, 3, 3),
    one per step, and their stored end poses (B, 3) (what a planned step plans towards)."""
    targets = compose_pose(origin[:, None, :], skill_waypoints(skills.hbr.middle_task, skills.genotypes[index]))
    goal = compose_pose(origin, displacement_of(skills.actions.prior[index]))
    return targets, goal


def choose_step(
    skills: Skills, learnt: PatternState, here: jax.Array, target: jax.Array, goal: jax.Array, step: jax.Array | int,
    action_number: jax.Array, keys: jax.Array, rules: tuple[str, ...] | None = None,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Before step `step` (0-2) of B HBR skills, robots at world poses `here` (B, 3) heading for the
    step's waypoint `target` (B, 3) and the skill's end `goal` (B, 3) (`skill_targets`): the contact
    pattern (B,) int32 each episode's rule picks (`learnt`: what the rules know), the middle elite
    (B,) int32 to run and whether it has that pattern (B,) bool.

    action_number: (B,) int32 actions already taken (GP-UCB's t = 1 + step + 3 action_number).
    keys: (B, 2) PRNG keys (random patterns). rules: the rule names in integer order.
    """
    hbr = skills.hbr
    task = hbr.middle_task
    desired = task.normalise(relative_pose(here, target))
    t = 1 + step + STEPS_PER_SKILL * action_number
    pattern, query = choose_patterns(hbr, learnt.mode, learnt.oracle, learnt.secondary, desired, t, keys,
                                     learnt.optimism, learnt.contacts, rules, learnt.motion)
    elite = None
    if skills.table is not None:
        elite = plan_batch(skills.table, task, here, goal, pattern, STEPS_PER_SKILL - step)
    if skills.sparing is not None:
        spared = plan_batch(skills.sparing, task, here, goal, pattern, STEPS_PER_SKILL - step)
        elite = jnp.where(spares_now(learnt), spared, elite)
    index, found = step_elite(hbr, here, target, pattern, query, elite)
    return pattern, index, found


def learn_step(hbr: HBR, learnt: PatternState, index: jax.Array, displacement: jax.Array,
               contact_fraction: jax.Array, leg_travel: jax.Array) -> tuple[PatternState, jax.Array]:
    """What the rules learn from one executed step of B robots: middle elites `index` (B,) moved the
    robots by `displacement` (B, 3) (x, y, yaw in the step's start frame) with each foot on the floor
    `contact_fraction` (B, 6) of the second, each leg's joints moving `leg_travel` (B, 6) rad. The
    secondary GP observes the elites' errors; each leg's sensed contact is added beside the contact
    the elite expected, and its joint travel beside the travel the elite's controller commanded. Returns the updated rules' state
    and the step's relative errors (B, 3)."""
    task = hbr.middle_task
    executed = hbr.middle.descriptors[index]  # (B, 9)
    observed = task.normalise(displacement)
    error = relative_error(executed[:, :PRIMARY], observed)
    secondary = jax.vmap(add_observation)(learnt.secondary, executed, step_targets(executed[:, :PRIMARY], observed))
    expected = hbr.middle.extras["contact_fraction"][index]  # (B, 6)
    contacts = learnt.contacts + jnp.stack([contact_fraction, expected], axis=1)
    motion = learnt.motion + jnp.stack([leg_travel, commanded_travel(hbr.middle_params[index])], axis=1)
    return learnt.replace(secondary=secondary, contacts=contacts, motion=motion), error


def execute_hbr(
    robot: Robot,
    skills: Skills,
    episodes: Episodes,
    decision: Decision,
    record_every: int = 0,
    rules: tuple[str, ...] | None = None,
) -> ActionOutcome:
    """Run the HBR skills `decision.action` (B,) of B episodes step by step from their robots'
    states, choosing each step's contact pattern by each episode's rule (`episodes.learnt`: what the
    rules know so far; the GP-UCB count is t = 1 + step + 3 x the actions already taken), then 1 s
    neutral. Random patterns draw from the decision's execution keys. rules: the rule names in
    integer order (default: every registered rule). record_every: k > 0 also returns the state every
    k control steps (`ActionOutcome.qpos`).
    """
    index, state, damage, learnt = decision.action, episodes.sim, episodes.damage, episodes.learnt
    action_number, keys = episodes.taken, decision.keys[:, 2]
    hbr = skills.hbr
    origin = state_pose(state)
    targets, goal = skill_targets(skills, index, origin)  # (B, 3, 3), (B, 3)

    def one_step(carry, xs):
        state, secondary, contacts, motion = carry
        target, step, step_keys = xs
        known = learnt.replace(secondary=secondary, contacts=contacts, motion=motion)
        pattern, elite, found = choose_step(skills, known, state_pose(state), target, goal, step, action_number,
                                            step_keys, rules)
        result = run_elite(robot, hbr, state, damage, elite, found, ONLINE_LIMITS, record_every)
        known, error = learn_step(hbr, known, elite, result.displacement, result.contact_fraction, result.leg_travel)
        return (result.state, known.secondary, known.contacts, known.motion), (pattern, elite, error, result.invalid_reason,
                                                                 state_pose(result.state), result.qpos)

    steps = jnp.arange(STEPS_PER_SKILL, dtype=jnp.int32)
    step_keys = jnp.swapaxes(jax.vmap(lambda k: jax.random.split(k, STEPS_PER_SKILL))(keys), 0, 1)  # (3, B, 2)
    xs = (jnp.swapaxes(targets, 0, 1), steps, step_keys)
    (state, secondary, contacts, motion), (patterns, middle, errors, reasons, poses, qpos) = jax.lax.scan(
        one_step, (state, learnt.secondary, learnt.contacts, learnt.motion), xs)
    rest = neutral_second(robot, state, damage, record_every)
    end = state_pose(rest.final_state)
    if record_every:  # (3, B, F / 4, 25) steps and (B, F / 4, 25) neutral -> (B, F, 25)
        steps = jnp.swapaxes(qpos, 0, 1)
        qpos = jnp.concatenate([steps.reshape(steps.shape[0], -1, steps.shape[-1]), rest.qpos], axis=1)
    return ActionOutcome(
        state=rest.final_state,
        valid=(reasons == 0).all(axis=0) & rest.valid,
        invalid_reason=jnp.bitwise_or.reduce(reasons, axis=0) | rest.invalid_reason,
        poses=jnp.concatenate([jnp.swapaxes(poses, 0, 1), end[:, None]], axis=1),
        displacement=relative_pose(origin, end),
        patterns=patterns.T,
        middle_index=middle.T,
        errors=jnp.swapaxes(errors, 0, 1),
        learnt=learnt.replace(secondary=secondary, contacts=contacts, motion=motion),
        qpos=qpos,
    )
