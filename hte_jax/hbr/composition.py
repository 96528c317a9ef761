"""Planned composition: a skill executed with a chosen contact pattern aims at the skill's own end.

With a pattern other than its own, a skill cannot replay the middle elites it was trained with.
The paper's execution (`hierarchy.execute_skill`) then takes, for each 1 s step, the nearest
elite of the pattern to the next waypoint; the steps' mismatches add up and a skill re-executed
this way ends a median 0.15 m from its own end. Here, before each step, the remaining steps are
planned among the pattern's elites so that their composed steps, from the robot's measured pose,
end at the skill's end pose; only the plan's first step runs, and the next step re-plans from
where the robot actually is (closed loop).

Planning is a small beam search over each pattern's elites (`PatternTable`): the first of r
remaining steps among the `beam[0]` elites nearest to 1/r of the remaining displacement, the
second among the `beam[1]` nearest to half of what is then left, the last the exact nearest to
the rest. A plan's cost is the weighted distance between its predicted end and the target,
(dx, dy, yaw_weight * dyaw) in normalised primary units, plus each planned step's penalty.

Steps are predicted by a `StepModel`: the stored primary descriptors, or the mean of each elite's
step measured from several start states (`measure_steps`), whose spread can be penalised so that
steps that depend little on where they start are preferred.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh
from tqdm.auto import tqdm

from hte_jax import sharding
from hte_jax.geometry import compose_pose, planar_pose, relative_pose
from hte_jax.hbr.middle import NUM_PATTERNS, PRIMARY, MiddleTask
from hte_jax.sim.robot import NUM_LEGS, Robot
from hte_jax.sim.rollout import RolloutSpec, SimState, rollout

COMPOSITIONS = ("planned", "waypoints")  # how a step with a chosen pattern picks its elite
DEFAULT_BEAM = (32, 16)
DEFAULT_YAW_WEIGHT = 0.25


@struct.dataclass
class StepModel:
    """What each middle elite is expected to do as one 1 s step of a skill.

    steps: (Cm, 3) normalised primary step (x, y, yaw): the stored descriptor, or the mean of the
      steps measured from several start states.
    spread: (Cm,) root mean square distance of the measured steps around `steps` (0 for the stored
      descriptors; +inf where every measured start went invalid).
    """

    steps: jax.Array
    spread: jax.Array


@struct.dataclass
class PatternTable:
    """Middle elites grouped by contact pattern, for planning.

    index: (64, M) int32 middle elite indices of each pattern, -1 padding (M: the largest pattern).
    steps: (64, M, 3) the step each elite is predicted to make (normalised primary units).
    penalty: (64, M) cost added for each planned use of the elite; +inf on padding.
    """

    index: jax.Array
    steps: jax.Array
    penalty: jax.Array


def descriptor_steps(middle_descriptors: jax.Array) -> StepModel:
    """The stored primary descriptors as the step model (no spread)."""
    steps = jnp.asarray(middle_descriptors)[:, :PRIMARY]
    return StepModel(steps=steps, spread=jnp.zeros(steps.shape[0], jnp.float32))


def pattern_table(patterns: np.ndarray, model: StepModel, spread_weight: float = 0.0) -> PatternTable:
    """Group the elites of (Cm,) `patterns` (-1 where empty) by pattern (host-side: M is static)."""
    patterns = np.asarray(patterns)
    counts = np.bincount(patterns[patterns >= 0], minlength=NUM_PATTERNS)
    width = max(int(counts.max()), 1)
    index = np.full((NUM_PATTERNS, width), -1, np.int32)
    for p in range(NUM_PATTERNS):
        members = np.flatnonzero(patterns == p)
        index[p, : members.size] = members
    rows = jnp.asarray(np.maximum(index, 0))
    present = jnp.asarray(index >= 0)
    penalty = spread_weight * jnp.asarray(model.spread)[rows]
    penalty = jnp.where(present & jnp.isfinite(penalty), penalty, jnp.inf)
    return PatternTable(index=jnp.asarray(index), steps=jnp.asarray(model.steps)[rows], penalty=penalty)


def planning_table(hbr) -> PatternTable:
    """The table an `hierarchy.HBR` plans with: its measured step model if it has one, else its descriptors."""
    model = hbr.step_model if hbr.step_model is not None else descriptor_steps(hbr.middle.descriptors)
    return pattern_table(np.asarray(hbr.middle_patterns), model)


def _weights(yaw_weight: float) -> jax.Array:
    return jnp.asarray([1.0, 1.0, yaw_weight], jnp.float32)


def plan_step(
    table: PatternTable, task: MiddleTask, here: jax.Array, target: jax.Array, pattern: jax.Array, remaining: int,
    beam: tuple[int, int] = DEFAULT_BEAM, yaw_weight: float = DEFAULT_YAW_WEIGHT,
) -> tuple[jax.Array, jax.Array]:
    """First step of the best plan of `remaining` (1-3, static) steps of `pattern` () from the world
    pose `here` (3,) to `target` (3,). Unbatched (vmap it).

    Returns (middle elite index () int32, -1 when the pattern has no elite; the plan's cost ()).
    """
    weights = _weights(yaw_weight)
    steps = table.steps[pattern]  # (M, 3)
    penalty = table.penalty[pattern]  # (M,)
    moves = task.denormalise(steps)

    def distance(query):  # (M,) weighted distance of every elite's step to `query` (3,)
        return jnp.sqrt(jnp.sum(((steps - query) * weights) ** 2, axis=-1))

    def last(pose):  # cost of the best single step from `pose` to the target
        wanted = task.normalise(relative_pose(pose, target))
        return jnp.min(distance(wanted) + penalty)

    def nearest(pose, parts, width):  # `width` elites nearest to 1/parts of what is left from `pose`
        share = task.normalise(relative_pose(pose, target) / parts)
        width = min(width, steps.shape[0])
        return jax.lax.top_k(-(distance(share) + penalty), width)[1]

    def best_of(pose, first):  # cost of the plans that start with the elites `first` from `pose`
        after = compose_pose(pose[None], moves[first])
        return after, penalty[first]

    if remaining == 1:
        wanted = task.normalise(relative_pose(here, target))
        costs = distance(wanted) + penalty
        choice = jnp.argmin(costs)
    elif remaining == 2:
        first = nearest(here, 2, beam[0])
        after, spent = best_of(here, first)
        costs = jax.vmap(last)(after) + spent
        choice = first[jnp.argmin(costs)]
    elif remaining == 3:
        first = nearest(here, 3, beam[0])
        after, spent = best_of(here, first)

        def two_left(pose):
            second = nearest(pose, 2, beam[1])
            then, cost = best_of(pose, second)
            return jnp.min(jax.vmap(last)(then) + cost)

        costs = jax.vmap(two_left)(after) + spent
        choice = first[jnp.argmin(costs)]
    else:
        raise ValueError(f"remaining must be 1, 2 or 3 steps, got {remaining}")
    index = table.index[pattern, choice]
    return jnp.where(jnp.isfinite(jnp.min(costs)), index, -1), jnp.min(costs)


def measure_steps(
    robot: Robot, middle_params: jax.Array, filled: jax.Array, task: MiddleTask, start: SimState, key: jax.Array,
    starts: int = 8, chunk: int = 8192, mesh: Mesh | None = None, progress: bool = False,
) -> StepModel:
    """Measure every filled middle elite's 1 s step from `starts` start states.

    middle_params: (Cm, 36) controllers, filled: (Cm,) bool. Start 0 is 1 s of the neutral pose
    after standing (as after an online action); the others are 1 s of a uniformly drawn filled elite
    (as inside a skill). Each sample runs the predecessor then the elite from the standing state
    `start` (unbatched); the elite's step is measured in the frame of its own start pose.

    Only the filled elites' samples are simulated (counted on the host), one jitted MJX rollout per
    block with a progress bar over the blocks. A block holds min(chunk, Cm x starts) samples at
    any fill (the last one padded): on a CPU, XLA's code for a vmapped rollout rounds differently
    with its row count, and this keeps a sample's bits those of the run that simulated every slot.
    mesh: each block's rows are split over it, everything else replicated (`sharding`'s placement
    rule; None: all visible devices). Returns host-made (uncommitted) arrays.
    """
    count = middle_params.shape[0]
    filled_rows = jnp.flatnonzero(filled, size=count, fill_value=0)
    draws = jax.random.randint(key, (count, starts - 1), 0, jnp.maximum(filled.sum(), 1))
    predecessors = jnp.concatenate([jnp.full((count, 1), -1), filled_rows[draws]], axis=1)  # (Cm, S)
    elites = np.flatnonzero(np.asarray(filled))
    own = np.repeat(elites, starts).astype(np.int32)  # (E * S,) the filled elites' samples
    before = np.asarray(predecessors, np.int32)[elites].reshape(-1)
    size = max(1, min(chunk, count * starts))  # rows per block, whatever the fill
    blocks = -(-own.size // size)
    mesh = sharding.batch_mesh() if mesh is None else mesh
    shared = sharding.put_replicated((robot, middle_params, start), mesh)
    measured = np.zeros((count * starts, PRIMARY), np.float32)
    valid = np.zeros(count * starts, bool)
    samples = (elites[:, None] * starts + np.arange(starts)).reshape(-1)  # their rows of (Cm * S,)
    for block in tqdm(range(blocks), disable=not progress, unit="block", desc="step model"):
        rows = slice(block * size, (block + 1) * size)
        take = own[rows].size
        pad = size - take  # the last block: padded as a full one (elite 0 after the neutral pose)
        indices = (np.pad(own[rows], (0, pad)), np.pad(before[rows], (0, pad), constant_values=-1))
        inputs = sharding.put_replicated(indices, mesh)
        with sharding.spread_over(mesh):
            steps, ok = _measure_block(*shared, *inputs, task)
        measured[samples[rows]] = np.asarray(steps)[:take]
        valid[samples[rows]] = np.asarray(ok)[:take]
    weights = _weights(1.0)
    measured = jnp.asarray(measured.reshape(count, starts, PRIMARY))
    valid = jnp.asarray(valid.reshape(count, starts))
    used = valid.sum(axis=1)
    mean = jnp.where(valid[..., None], measured, 0.0).sum(axis=1) / jnp.maximum(used, 1)[:, None]
    squared = jnp.sum(((measured - mean[:, None]) * weights) ** 2, axis=-1)
    spread = jnp.sqrt(jnp.where(valid, squared, 0.0).sum(axis=1) / jnp.maximum(used, 1))
    ok = jnp.asarray(np.asarray(filled)) & (used > 0)
    return StepModel(steps=jnp.where(ok[:, None], mean, 0.0), spread=jnp.where(ok, spread, jnp.inf))


@functools.partial(jax.jit, static_argnames=("task",))
def _measure_block(robot: Robot, middle_params: jax.Array, start: SimState, own: jax.Array, before: jax.Array,
                   task: MiddleTask) -> tuple[jax.Array, jax.Array]:
    """(n, 3) normalised steps and (n,) validity of elites `own` (n,) after `before` (n,) (-1: the
    neutral pose), from the standing state `start`; one batched rollout of 2 s."""
    first = jnp.where(before[:, None] >= 0, middle_params[jnp.maximum(before, 0)], 0.0)
    params = jnp.stack([first, middle_params[own]], axis=1)  # (n, 2, 36)
    spec = RolloutSpec(num_steps=2 * task.steps, pose_steps=(task.steps, 2 * task.steps), record_contacts=False)
    result = rollout(robot, params, jnp.zeros(NUM_LEGS, bool), start, spec)
    poses = planar_pose(result.base_pos, result.base_quat)
    return task.normalise(relative_pose(poses[:, 0], poses[:, 1])), result.valid


def plan_batch(table: PatternTable, task: MiddleTask, here: jax.Array, target: jax.Array, pattern: jax.Array,
               remaining: jax.Array | int, beam: tuple[int, int] = DEFAULT_BEAM,
               yaw_weight: float = DEFAULT_YAW_WEIGHT) -> jax.Array:
    """`plan_step` for B robots: here, target (B, 3), pattern (B,) (-1: no plan, returns -1).

    remaining: the steps left (1-3), a Python int or an unbatched traced scalar.
    """
    def plan(r):
        def one(h, g, p):
            return plan_step(table, task, h, g, jnp.maximum(p, 0), r, beam, yaw_weight)[0]
        return jax.vmap(one)(here, target, pattern)

    if isinstance(remaining, int):
        index = plan(remaining)
    else:
        index = jax.lax.switch(jnp.clip(remaining, 1, 3) - 1, [lambda r=r: plan(r) for r in (1, 2, 3)])
    return jnp.where(pattern >= 0, index, -1)


def skill_ends(top_descriptors: jax.Array, arrival_yaw: jax.Array, extent: float) -> jax.Array:
    """(..., 2) normalised top descriptors and (...,) arrival yaws -> (..., 3) end poses in the start frame."""
    xy = top_descriptors * (2 * extent) - extent
    return jnp.concatenate([xy, arrival_yaw[..., None]], axis=-1)
