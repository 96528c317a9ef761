"""Reset-free adaptation episodes in the maze, B at once (paper section 4; `docs/design.md`, Online adaptation).

Each action: the RTE GP predicts every skill's outcome, MCTS plans from the measured pose, the skill runs
from wherever the robot stands, and the GP learns the measured displacement. An episode ends at the goal,
after `max_actions` or when the robot goes invalid.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, PartitionSpec
from tqdm.auto import tqdm

from hte_jax import sharding
from hte_jax.errors import ConfigError, require_int
from hte_jax.hbr.hierarchy import STEPS_PER_SKILL, state_pose
from hte_jax.online.action import (SECONDS_PER_ACTION, STEP_CONTROL_STEPS, ActionOutcome, Part, SimulatedRobots,
                                   flat_action, hbr_action, joint_action)
from hte_jax.online.aprol import MapBelief, closeness, initial_belief, select_entry, update_belief
from hte_jax.online.gp import GPData, add_observation, empty_gp
from hte_jax.online.maze import GridSpec, Maze, distance_field, planning_start, reached_goal
from hte_jax.online.mcts import PlannerConfig, PlanResult, plan, world_of
from hte_jax.online.recording import Recorder
from hte_jax.online.rules import PatternRule, RuleBatch, rule_indices, start_rules
from hte_jax.online.secondary import ERROR_DIM
from hte_jax.online.skills import OUTCOME_DIM, Skills, displacement_of, predict
from hte_jax.online.skills import outcome as outcome_of
from hte_jax.sim.damage import Damage, as_damage, damage_legs
from hte_jax.sim.robot import NUM_LEGS, Robot
from hte_jax.sim.env import SimState
from hte_jax.warp_calls import waited


@dataclasses.dataclass(frozen=True)
class AdaptationConfig:
    """Settings of an adaptation run (hashable: a static jit argument). max_actions: actions before an
    episode fails (paper 80). planner: MCTS settings. grid: the planner's distance-field grid."""

    max_actions: int = 80
    planner: PlannerConfig = PlannerConfig()
    grid: GridSpec = GridSpec()

    def __post_init__(self):
        require_int("max_actions", self.max_actions)


@struct.dataclass
class History:
    """What happened at each action of B episodes (L = max_actions, D = planner depth): action, map (its
    repertoire) and planned (B, L) int32 (-1 after the end); start, predicted and observed (B, L, 3) (the
    planner's start pose, the GP's and the measured displacement); value (B, L); path (B, L, D + 1, 3) and
    path_length (B, L) int32; the `ActionOutcome` step records patterns, errors, contacts and leg_travel."""

    action: jax.Array
    map: jax.Array
    planned: jax.Array
    start: jax.Array
    predicted: jax.Array
    observed: jax.Array
    value: jax.Array
    path: jax.Array
    path_length: jax.Array
    patterns: jax.Array
    errors: jax.Array
    contacts: jax.Array
    leg_travel: jax.Array


@struct.dataclass
class Episodes:
    """B adaptation episodes: sim SimState (B, ...) (None when an executor drives the robots), damage what is wrong
    with each robot (a (B, 6) bool leg mask under the robot's `damage_model`, or a `Damage` (B, ...)), rte GPData
    (B, K, L, D, 4) per repertoire, belief MapBelief (B, K), rules, key (B, 2), taken (B,) int32, reached and broken
    (B,) bool, reason (B,) int32 `InvalidReason` bits, trajectory (B, 4 L + 1, 3) world pose every second (the last
    repeated after the end), history."""

    sim: SimState
    damage: jax.Array | Damage
    rte: GPData
    belief: MapBelief
    rules: RuleBatch
    key: jax.Array
    taken: jax.Array
    reached: jax.Array
    broken: jax.Array
    reason: jax.Array
    trajectory: jax.Array
    history: History

    @property
    def done(self) -> jax.Array:
        return self.reached | self.broken | (self.taken >= self.history.action.shape[1])

    @property
    def pose(self) -> jax.Array:
        """(B, 3) each robot's world planar pose now (the trajectory's latest without a `sim`)."""
        if self.sim is None:
            return self.trajectory[jnp.arange(self.taken.shape[0]), SECONDS_PER_ACTION * self.taken]
        return state_pose(self.sim)


def start_episodes(config: AdaptationConfig, skills: Skills, start: SimState | jax.Array,
                   damages: np.ndarray | Damage, rules: tuple[PatternRule, ...], which: np.ndarray,
                   key: jax.Array) -> Episodes:
    """B fresh episodes of robots `start` (SimState (B, ...), or world poses (B, 3) of executor-driven robots)
    with `damages` (a (B, 6) bool leg mask or a `Damage` (B, ...)), episode b running `rules[which[b]]` (whose
    `init` reads the damaged legs) and planning first with a random repertoire."""
    damages = damages if isinstance(damages, Damage) else np.asarray(damages, bool)
    legs = np.asarray(damage_legs(damages), bool)
    simulated = isinstance(start, SimState)
    pose = state_pose(jax.device_get(start), xp=np) if simulated else np.asarray(start, np.float32)
    return _fresh_episodes(config, skills.num_maps, skills.actions.inputs.shape[-1], tuple(rules),
                           start if simulated else None, pose, damages, legs, rule_indices(which, len(rules)), key)


@functools.partial(jax.jit, static_argnames=("config", "maps", "inputs", "rules"))
def _fresh_episodes(config: AdaptationConfig, maps: int, inputs: int, rules: tuple[PatternRule, ...],
                    sim: SimState | None, pose: jax.Array, damages: jax.Array | Damage, legs: jax.Array,
                    which: jax.Array, key: jax.Array) -> Episodes:
    """`start_episodes`' episodes, in one program: robots `sim` (None: executor-driven) at world poses `pose`
    (B, 3), `maps` repertoires of actions with `inputs` GP inputs, episode b running `rules[which[b]]`."""
    batch, length, depth = legs.shape[0], config.max_actions, config.planner.depth
    first_map = jax.random.randint(jax.random.fold_in(key, 1), (batch,), 0, maps)
    history = History(
        action=jnp.full((batch, length), -1, jnp.int32), map=jnp.full((batch, length), -1, jnp.int32),
        planned=jnp.full((batch, length), -1, jnp.int32), start=jnp.zeros((batch, length, 3), jnp.float32),
        predicted=jnp.zeros((batch, length, 3), jnp.float32), observed=jnp.zeros((batch, length, 3), jnp.float32),
        value=jnp.zeros((batch, length), jnp.float32), path=jnp.zeros((batch, length, depth + 1, 3), jnp.float32),
        path_length=jnp.zeros((batch, length), jnp.int32),
        patterns=jnp.full((batch, length, STEPS_PER_SKILL), -1, jnp.int32),
        errors=jnp.zeros((batch, length, STEPS_PER_SKILL, ERROR_DIM), jnp.float32),
        contacts=jnp.zeros((batch, length, STEPS_PER_SKILL, NUM_LEGS), jnp.float32),
        leg_travel=jnp.zeros((batch, length, STEPS_PER_SKILL, NUM_LEGS), jnp.float32))
    return Episodes(
        sim=sim, damage=damages,
        rte=jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, maps, *x.shape)), empty_gp(length, inputs, OUTCOME_DIM)),
        belief=jax.vmap(lambda k: initial_belief(maps, k))(first_map), rules=start_rules(rules, which, legs, length),
        key=jax.random.split(key, batch), taken=jnp.zeros(batch, jnp.int32), reached=jnp.zeros(batch, bool),
        broken=jnp.zeros(batch, bool), reason=jnp.zeros(batch, jnp.int32),
        trajectory=jnp.broadcast_to(pose[:, None, :], (batch, SECONDS_PER_ACTION * length + 1, 3)), history=history)


@struct.dataclass
class Decision:
    """The next action of B episodes: plan PlanResult (B,), map and action (B,) int32 to execute, start (B, 3)
    the planner's start pose, predicted (B, 3) and prior (B, 4) the GP's displacement and prior outcome of the
    executed skill, keys (B, 3, 2) the episode's next key, the plan's and the execution's."""

    plan: PlanResult
    map: jax.Array
    action: jax.Array
    start: jax.Array
    predicted: jax.Array
    keys: jax.Array
    prior: jax.Array


@struct.dataclass
class _Outlook:
    """What an action's search needs of B episodes, and what its decision reads after it: mean (B, K, A, 4) and
    variance (B, K, A) the RTE GPs' predictions of every repertoire's actions, displacement (B, A, 3) and usable
    (B, A) the current repertoire's, start (B, 3) the planner's start pose, keys (B, 3, 2) next, plan, act."""

    mean: jax.Array
    variance: jax.Array
    displacement: jax.Array
    usable: jax.Array
    start: jax.Array
    keys: jax.Array


def _outlook(maze: Maze, skills: Skills, episodes: Episodes) -> _Outlook:
    """Every episode's predicted outcomes and planning start (the part of `plan_step` before its search)."""
    maps = skills.map_actions
    mean, variance = jax.vmap(lambda gps: jax.vmap(predict)(gps, maps))(episodes.rte)  # (B, K, A, 4), (B, K, A)
    rows, current = jnp.arange(mean.shape[0]), episodes.belief.current
    pose = episodes.pose
    return _Outlook(mean=mean, variance=variance, displacement=displacement_of(mean[rows, current]),
                    usable=maps.mask[current],
                    start=jnp.concatenate([planning_start(maze, pose[:, :2]), pose[:, 2:]], axis=-1),
                    keys=jax.vmap(lambda k: jax.random.split(k, 3))(episodes.key))


def _search(maze: Maze, config: AdaptationConfig, field: jax.Array, displacement: jax.Array, usable: jax.Array,
            keys: jax.Array, start: jax.Array) -> PlanResult:
    """B plans (vmapped `mcts.plan`): displacement (B, A, 3), usable (B, A), keys (B, 2), start (B, 3)."""

    def one(moves, mask, key, state):
        return plan(maze, config.grid, config.planner, world_of(moves, mask, field), key, state)

    return jax.vmap(one)(displacement, usable, keys, start)


def _decide(skills: Skills, episodes: Episodes, outlook: _Outlook, result: PlanResult) -> Decision:
    """The decision from a plan (APROL then picks among all repertoires)."""
    mean, variance = outlook.mean, outlook.variance
    rows, maps = jnp.arange(mean.shape[0]), skills.map_actions
    if skills.num_maps > 1:
        goal = outlook.displacement[rows, result.action, :2]  # what the plan expects the skill to do
        chosen_map, action = jax.vmap(select_entry)(episodes.belief, mean, variance,
                                                    jnp.broadcast_to(maps.mask, variance.shape), goal)
    else:
        chosen_map, action = jnp.zeros_like(result.action), result.action
    predicted = displacement_of(mean[rows, chosen_map, action])
    return Decision(plan=result, map=chosen_map, action=action, start=outlook.start, predicted=predicted,
                    keys=outlook.keys, prior=maps.prior[chosen_map, action])


@functools.partial(jax.jit, static_argnames=("maze", "config"))
def plan_step(maze: Maze, config: AdaptationConfig, skills: Skills, field: jax.Array, episodes: Episodes) -> Decision:
    """Plan every episode's next action on its RTE GP's predictions (APROL then picks among all repertoires)."""
    outlook = _outlook(maze, skills, episodes)
    result = _search(maze, config, field, outlook.displacement, outlook.usable, outlook.keys[:, 1], outlook.start)
    return _decide(skills, episodes, outlook, result)


def _pad_actions(x: jax.Array, size: int, fill) -> jax.Array:
    """(B, A, ...) -> (B, size, ...), the added actions `fill`."""
    return jnp.pad(x, [(0, 0), (0, size - x.shape[1])] + [(0, 0)] * (x.ndim - 2), constant_values=fill)


@functools.partial(jax.jit, static_argnames=("maze", "config"))
def plan_steps(maze: Maze, config: AdaptationConfig, skills: tuple[Skills, ...], field: jax.Array,
               episodes: tuple[Episodes, ...]) -> tuple[Decision, ...]:
    """`plan_step` of several batches (each its skills and episodes) as one search of all their episodes: the
    action sets padded to the largest with unusable actions (never drawn: a plan draws among the usable ones
    only), so each batch's decisions are its own `plan_step`'s up to float rounding."""
    outlooks = [_outlook(maze, s, e) for s, e in zip(skills, episodes)]
    width = max(o.usable.shape[1] for o in outlooks)
    join = sharding.join_rows
    result = _search(maze, config, field, join([_pad_actions(o.displacement, width, 0.0) for o in outlooks]),
                     join([_pad_actions(o.usable, width, False) for o in outlooks]),
                     join([o.keys[:, 1] for o in outlooks]), join([o.start for o in outlooks]))
    parts = sharding.split_rows(result, [o.usable.shape[0] for o in outlooks])
    return tuple(_decide(s, e, o, own.replace(visits=own.visits[:, :o.usable.shape[1]]))
                 for s, e, o, own in zip(skills, episodes, outlooks, parts))


def _check_record_every(record_every: int) -> None:
    """ConfigError unless `record_every` is 0 (nothing recorded) or an integer dividing a second's control steps."""
    if record_every and (not isinstance(record_every, int) or STEP_CONTROL_STEPS % record_every):
        raise ConfigError(f"record_every must divide {STEP_CONTROL_STEPS}, got {record_every!r}")


@functools.partial(jax.jit, static_argnames=("maze", "config", "record_every"))
def act_step(maze: Maze, config: AdaptationConfig, robot: Robot, skills: Skills, episodes: Episodes,
             decision: Decision, record_every: int = 0) -> tuple[Episodes, jax.Array | None]:
    """Execute every active episode's action on its MJX robot, learn and record it. Returns the episodes and
    the states (B, 400 / k, 25) every k = `record_every` control steps (None when k = 0)."""
    _check_record_every(record_every)
    outcome = execute(SimulatedRobots(robot, episodes.damage, record_every), skills, episodes, decision)
    return record_action(maze, config, skills, episodes, decision, outcome), outcome.qpos


@functools.partial(jax.jit, static_argnames=("maze", "config", "record_every"))
def act_steps(maze: Maze, config: AdaptationConfig, robot: Robot, skills: tuple[Skills, ...],
              episodes: tuple[Episodes, ...], decisions: tuple[Decision, ...],
              record_every: int = 0) -> tuple[tuple[Episodes, ...], tuple[jax.Array | None, ...]]:
    """`act_step` of several batches (each its skills, episodes and decision) as one program whose every second is
    one rollout of all their robots (`action.joint_action`). Returns each batch's episodes and states."""
    _check_record_every(record_every)
    damages = [e.damage for e in episodes]
    if any(isinstance(d, Damage) for d in damages):  # one kind for the joint rollout
        damages = [as_damage(d, robot.config.damage_model) for d in damages]
    damage = sharding.join_rows(damages)
    parts = tuple(Part(skills=s, state=e.sim, rules=e.rules if s.hierarchical else None, keys=d.keys[:, 2],
                       choice=d.action if s.hierarchical else s.map_genotypes[d.map, d.action], taken=e.taken)
                  for s, e, d in zip(skills, episodes, decisions))
    outcomes = joint_action(SimulatedRobots(robot, damage, record_every), parts)
    return (tuple(record_action(maze, config, s, e, d, o) for s, e, d, o in zip(skills, episodes, decisions, outcomes)),
            tuple(o.qpos for o in outcomes))


def execute(robots, skills: Skills, episodes: Episodes, decision: Decision) -> ActionOutcome:
    """Every episode's decided skill run on `robots` (`action.SimulatedRobots` or `external.ExecutorRobot`)."""
    if skills.hierarchical:
        return hbr_action(robots, skills, episodes.sim, episodes.rules, decision.action, episodes.taken,
                          decision.keys[:, 2])
    return flat_action(robots, episodes.sim, skills.map_genotypes[decision.map, decision.action])


@functools.partial(jax.jit, static_argnames=("maze", "config"))
def record_action(maze: Maze, config: AdaptationConfig, skills: Skills, episodes: Episodes, decision: Decision,
                  outcome: ActionOutcome) -> Episodes:
    """Every active episode after its executed `outcome` (B, ...): GP and belief learn it, history records it."""
    active = ~episodes.done
    index, chosen_map, maps = decision.action, decision.map, skills.map_actions

    def learn(gps, belief, k, i, displacement, prior):
        chosen = jax.tree.map(lambda x: x[k], maps)
        gp = add_observation(jax.tree.map(lambda x: x[k], gps), chosen.inputs[i], outcome_of(displacement), prior)
        gps = jax.tree.map(lambda all_, one: all_.at[k].set(one), gps, gp)
        return gps, update_belief(belief, k, closeness(chosen.prior[i], displacement))

    rte, belief = jax.vmap(learn)(episodes.rte, episodes.belief, chosen_map, index, outcome.displacement, decision.prior)
    rules = episodes.rules if outcome.rules is None else outcome.rules
    rows, slot = jnp.arange(index.shape[0]), jnp.minimum(episodes.taken, config.max_actions - 1)
    planned = decision.plan
    recorded = jax.tree.map(lambda old, new: old.at[rows, slot].set(new), episodes.history, History(
        action=index, map=chosen_map, planned=planned.action, start=decision.start, predicted=decision.predicted,
        observed=outcome.displacement, value=planned.value, path=planned.path, path_length=planned.path_length,
        patterns=outcome.patterns, errors=outcome.errors, contacts=outcome.contacts, leg_travel=outcome.leg_travel))
    first = SECONDS_PER_ACTION * episodes.taken + 1
    trajectory = episodes.trajectory
    for second in range(SECONDS_PER_ACTION):
        trajectory = trajectory.at[rows, first + second].set(outcome.poses[:, second])
    # Later slots hold the latest pose until they are written (the plot shows a still robot).
    later = jnp.arange(trajectory.shape[1])[None, :] >= (first + SECONDS_PER_ACTION)[:, None]
    trajectory = jnp.where(later[..., None], outcome.poses[:, -1:, :], trajectory)
    updated = episodes.replace(
        sim=outcome.state, rte=rte, belief=belief, rules=rules, key=decision.keys[:, 0], taken=episodes.taken + 1,
        reached=reached_goal(maze, outcome.poses[:, -1, :2]) & outcome.valid, broken=~outcome.valid,
        reason=outcome.invalid_reason, trajectory=trajectory, history=recorded)
    return sharding.where_rows(active, updated, episodes)  # ended episodes unchanged


@dataclasses.dataclass
class RunTimings:
    """Wall-clock seconds of each call of a run (the first of each includes compilation); setup: before the
    first action (what `evaluation.run_batch` spent loading the repertoire and starting the episodes)."""

    plan: list[float] = dataclasses.field(default_factory=list)
    act: list[float] = dataclasses.field(default_factory=list)
    total: float = 0.0
    setup: float = 0.0


@functools.partial(jax.jit, static_argnames=("size",))
def pad_episodes(episodes: Episodes, size: int) -> Episodes:
    """The batch grown to `size` rows with copies of its last episode marked ended (`broken`)."""
    padded = sharding.pad_rows(episodes, size)
    return padded.replace(broken=padded.broken | (jnp.arange(size) >= episodes.taken.shape[0]))


@jax.jit
def episode_status(episodes: Episodes) -> tuple[jax.Array, jax.Array]:
    """(done, reached) (B,) bool of every episode: what the run loop reads on the host after each action."""
    return episodes.done, episodes.reached


@functools.lru_cache(maxsize=32)
def sharded_steps(maze: Maze, config: AdaptationConfig, mesh: Mesh, record_every: int):
    """(plan, plan_all, act, act_all): `plan_step`, `plan_steps`, `act_step` and `act_steps` with the episode axis
    split over `mesh` (no collective inside)."""
    rows, whole = PartitionSpec(sharding.BATCH_AXIS), PartitionSpec()

    def plan(skills, field, episodes):
        return plan_step(maze, config, skills, field, episodes)

    def plan_all(skills, field, episodes):
        return plan_steps(maze, config, skills, field, episodes)

    def act(robot, skills, episodes, decision):
        return act_step(maze, config, robot, skills, episodes, decision, record_every=record_every)

    def act_all(robot, skills, episodes, decisions):
        return act_steps(maze, config, robot, skills, episodes, decisions, record_every=record_every)

    if mesh.devices.size == 1:  # one device: the step functions themselves
        return plan, plan_all, act, act_all
    split = functools.partial(jax.shard_map, mesh=mesh, out_specs=rows, check_vma=False)
    return (jax.jit(split(plan, in_specs=(whole, whole, rows))),
            jax.jit(split(plan_all, in_specs=(whole, whole, rows))),
            jax.jit(split(act, in_specs=(whole, whole, rows, rows))),
            jax.jit(split(act_all, in_specs=(whole, whole, rows, rows))))


def run_episodes(maze: Maze, config: AdaptationConfig, robot: Robot, skills: Skills, episodes: Episodes,
                 progress: bool = True, description: str = "episodes", max_steps: int | None = None,
                 recorder: Recorder | None = None, mesh: Mesh | None = None) -> tuple[Episodes, RunTimings]:
    """Run the batch until every episode has ended (or for `max_steps` actions). recorder: collects its rows'
    states. mesh: the devices the episodes are spread over (None: all visible)."""
    return run_together(maze, config, robot, [(skills, episodes)], progress, description, max_steps, [recorder],
                        mesh)[0]


def run_together(maze: Maze, config: AdaptationConfig, robot: Robot, batches: list[tuple[Skills, Episodes]],
                 progress: bool = True, description: str = "episodes", max_steps: int | None = None,
                 recorders: list[Recorder | None] | None = None,
                 mesh: Mesh | None = None) -> list[tuple[Episodes, RunTimings]]:
    """`run_episodes` of several batches (each its skills and episodes) in lockstep: each action plans all of them
    in one search (`plan_steps`), then acts all of them in one program (`act_steps`; one batch: `plan_step`,
    `act_step`), until every episode has ended. recorders: one per batch (None: not recorded). Each batch's
    timings hold the joint planning and acting."""
    mesh = sharding.batch_mesh() if mesh is None else mesh
    recorders = [None] * len(batches) if recorders is None else list(recorders)
    if len(recorders) != len(batches):
        raise ConfigError(f"{len(batches)} batches, {len(recorders)} recorders")
    every = {r.every for r in recorders if r is not None}
    if len(every) > 1:
        raise ConfigError(f"batches run together record at one interval, got {sorted(every)}")
    sizes = [episodes.taken.shape[0] for _, episodes in batches]
    # Commit every input to the mesh: jit keys its cache on committed-ness, so uncommitted first
    # inputs would compile each step function twice.
    field = sharding.put_replicated(distance_field(maze, config.grid), mesh)
    skills, robot = sharding.put_replicated(([s for s, _ in batches], robot), mesh)
    episodes = [sharding.put_batch(pad_episodes(e, sharding.padded_size(n, mesh)), mesh)
                for (_, e), n in zip(batches, sizes)]
    plan, plan_all, act, act_all = sharded_steps(maze, config, mesh, every.pop() if every else 0)
    timings, begin = [RunTimings() for _ in batches], time.perf_counter()
    bar = tqdm(total=config.max_actions, desc=description, unit="action", disable=not progress)

    def status():
        return [[np.asarray(x) for x in sharding.addressable(episode_status(e))] for e in episodes]

    done = status()
    for _ in range(config.max_actions if max_steps is None else min(max_steps, config.max_actions)):
        if all(d.all() for d, _ in done):
            break
        active = [~d[:n] for (d, _), n in zip(done, sizes)]
        tick = time.perf_counter()  # an ended batch is planned and acted on with the others: its episodes stay
        if len(batches) == 1:
            decisions = [waited(plan, skills[0], field, episodes[0])]
        else:
            decisions = waited(plan_all, tuple(skills), field, tuple(episodes))
        planned = time.perf_counter() - tick
        tick = time.perf_counter()
        if len(batches) == 1:
            episode, state = waited(act, robot, skills[0], episodes[0], decisions[0])
            episodes, states = [episode], [state]
        else:
            episodes, states = (list(x) for x in waited(act_all, robot, tuple(skills), tuple(episodes),
                                                          tuple(decisions)))
        acted = time.perf_counter() - tick
        for t in timings:
            t.plan.append(planned)
            t.act.append(acted)
        for recorder, state, running in zip(recorders, states, active):
            if recorder is not None:
                recorder.add(sharding.addressable(state), running)
        done = status()
        bar.update(1)
        bar.set_postfix(reached=int(sum(r.sum() for _, r in done)), running=int(sum((~d).sum() for d, _ in done)))
    bar.close()
    total = time.perf_counter() - begin
    for t in timings:
        t.total = total
    return [(jax.tree.map(lambda x: x[:n], sharding.addressable(e)), t) for e, n, t in zip(episodes, sizes, timings)]
