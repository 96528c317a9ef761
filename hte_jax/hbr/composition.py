"""Planned composition: a skill executed with a chosen contact pattern aims at its own end. Where the paper's
nearest elite to each waypoint lets the steps' mismatches add up (a median 0.15 m), the remaining steps are
planned among the pattern's elites (`plan_step`) before each step; only the first runs, then it re-plans."""

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
from hte_jax.sim.env import SimState
from hte_jax.sim.rollout import RolloutSpec, rollout
from hte_jax.warp_calls import waited

COMPOSITIONS = ("planned", "waypoints")  # how a step with a chosen pattern picks its elite
DEFAULT_BEAM = (32, 16)
DEFAULT_YAW_WEIGHT = 0.25


@struct.dataclass
class StepModel:
    """Each middle elite's expected 1 s step: steps (Cm, 3) normalised (x, y, yaw), the descriptor or the
    measured mean; spread (Cm,) RMS distance of the measured steps to it (0: descriptors; +inf: all invalid)."""

    steps: jax.Array
    spread: jax.Array


@struct.dataclass
class PatternTable:
    """Middle elites grouped by pattern: index (64, M) int32 (-1 padding; M: the largest group), steps (64, M, 3)
    their predicted normalised steps, penalty (64, M): 0, or +inf on padding and on elites of infinite spread."""

    index: jax.Array
    steps: jax.Array
    penalty: jax.Array


def descriptor_steps(middle_descriptors: jax.Array) -> StepModel:
    """The stored primary descriptors as the step model (no spread), placed from the host."""
    steps = np.asarray(middle_descriptors, np.float32)[:, :PRIMARY]
    return StepModel(steps=jax.device_put(steps), spread=jax.device_put(np.zeros(steps.shape[0], np.float32)))


def hbr_steps(hbr) -> StepModel:
    """An `hierarchy.HBR`'s step model: the measured one if it has one, else its descriptors."""
    return hbr.step_model if hbr.step_model is not None else descriptor_steps(hbr.middle.descriptors)


def member_table(members: np.ndarray, model: StepModel) -> PatternTable:
    """The table whose row p holds the elites e of (64, Cm) bool `members[p, e]` (host-side: M is static)."""
    index = np.full((NUM_PATTERNS, max(int(members.sum(axis=1).max()), 1)), -1, np.int32)
    for p in range(NUM_PATTERNS):
        rows = np.flatnonzero(members[p])
        index[p, : rows.size] = rows
    rows = np.maximum(index, 0)
    usable = (index >= 0) & np.isfinite(np.asarray(model.spread)[rows])
    return PatternTable(index=jax.device_put(index), steps=jax.device_put(np.asarray(model.steps)[rows]),
                        penalty=jax.device_put(np.where(usable, 0.0, np.inf).astype(np.float32)))


def pattern_table(patterns: np.ndarray, model: StepModel) -> PatternTable:
    """Group the elites of (Cm,) `patterns` (-1 where empty) by pattern."""
    return member_table(np.asarray(patterns)[None, :] == np.arange(NUM_PATTERNS)[:, None], model)


def planning_table(hbr) -> PatternTable:
    """The table an `hierarchy.HBR` plans with (`hbr_steps`)."""
    return pattern_table(np.asarray(hbr.middle_patterns), hbr_steps(hbr))


def _weights(yaw_weight: float) -> jax.Array:
    return jnp.asarray([1.0, 1.0, yaw_weight], jnp.float32)


def plan_step(table: PatternTable, task: MiddleTask, here: jax.Array, target: jax.Array, pattern: jax.Array,
              remaining: int, beam: tuple[int, int] = DEFAULT_BEAM,
              yaw_weight: float = DEFAULT_YAW_WEIGHT) -> tuple[jax.Array, jax.Array]:
    """First step of the best plan of `remaining` (1-3, static) steps of `pattern` () from world pose `here` (3,)
    to `target` (3,), unbatched: (middle elite () int32, -1 if the pattern has none; cost ()). Step 1 of r is
    among the `beam[0]` elites nearest to 1/r of what is left, step 2 among the `beam[1]` nearest to half the
    rest; cost: the end's distance to the target in normalised (dx, dy, yaw_weight * dyaw) plus penalties."""
    weights = _weights(yaw_weight)
    steps = table.steps[pattern]  # (M, 3)
    penalty = table.penalty[pattern]  # (M,)
    moves = task.denormalise(steps)

    def distance(query):  # (M,) weighted distance of every elite's step to `query` (3,)
        return jnp.sqrt(jnp.sum(((steps - query) * weights) ** 2, axis=-1))

    def last(pose):  # cost of the best single step from `pose` to the target
        return jnp.min(distance(task.normalise(relative_pose(pose, target))) + penalty)

    def nearest(pose, parts, width):  # `width` elites nearest to 1/parts of what is left from `pose`
        share = task.normalise(relative_pose(pose, target) / parts)
        return jax.lax.top_k(-(distance(share) + penalty), min(width, steps.shape[0]))[1]

    def best_of(pose, first):  # poses after, and penalties of, the elites `first` from `pose`
        return compose_pose(pose[None], moves[first]), penalty[first]

    if remaining == 1:
        costs = distance(task.normalise(relative_pose(here, target))) + penalty
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
            then, cost = best_of(pose, nearest(pose, 2, beam[1]))
            return jnp.min(jax.vmap(last)(then) + cost)

        costs = jax.vmap(two_left)(after) + spent
        choice = first[jnp.argmin(costs)]
    else:
        raise ValueError(f"remaining must be 1, 2 or 3 steps, got {remaining}")
    index = table.index[pattern, choice]
    return jnp.where(jnp.isfinite(jnp.min(costs)), index, -1), jnp.min(costs)


def measure_steps(robot: Robot, middle_params: jax.Array, filled: jax.Array, task: MiddleTask, start: SimState,
                  key: jax.Array, starts: int = 8, chunk: int = 8192, mesh: Mesh | None = None,
                  progress: bool = False) -> StepModel:
    """Measure every filled middle elite's step (middle_params (Cm, 36), filled (Cm,)) from `starts` start
    states: 1 s of the neutral pose (as after an action) or of a random elite (as in a skill) after the
    unbatched standing state `start`. Blocks of min(chunk, Cm x starts) rows at any fill (XLA's CPU
    rounding depends on the row count), split over `mesh` (None: all devices). Returns uncommitted arrays."""
    count = middle_params.shape[0]
    filled_rows = jnp.flatnonzero(filled, size=count, fill_value=0)
    draws = jax.random.randint(key, (count, starts - 1), 0, jnp.maximum(filled.sum(), 1))
    predecessors = jnp.concatenate([jnp.full((count, 1), -1), filled_rows[draws]], axis=1)  # (Cm, S)
    elites = np.flatnonzero(np.asarray(filled))
    own = np.repeat(elites, starts).astype(np.int32)  # (E * S,) the filled elites' samples
    before = np.asarray(predecessors, np.int32)[elites].reshape(-1)
    size = max(1, min(chunk, count * starts))  # rows per block, whatever the fill
    mesh = sharding.batch_mesh() if mesh is None else mesh
    shared = sharding.put_replicated((robot, middle_params, start), mesh)
    measured = np.zeros((count * starts, PRIMARY), np.float32)
    valid = np.zeros(count * starts, bool)
    samples = (elites[:, None] * starts + np.arange(starts)).reshape(-1)  # their rows of (Cm * S,)
    for block in tqdm(range(-(-own.size // size)), disable=not progress, unit="block", desc="step model"):
        rows = slice(block * size, (block + 1) * size)
        take = own[rows].size
        pad = size - take  # the last block: padded as a full one (elite 0 after the neutral pose)
        indices = (np.pad(own[rows], (0, pad)), np.pad(before[rows], (0, pad), constant_values=-1))
        inputs = sharding.put_replicated(indices, mesh)
        with sharding.spread_over(mesh):
            steps, ok = waited(_measure_block, *shared, *inputs, task)
        measured[samples[rows]] = np.asarray(steps)[:take]
        valid[samples[rows]] = np.asarray(ok)[:take]
    measured = jnp.asarray(measured.reshape(count, starts, PRIMARY))
    valid = jnp.asarray(valid.reshape(count, starts))
    used = valid.sum(axis=1)
    mean = jnp.where(valid[..., None], measured, 0.0).sum(axis=1) / jnp.maximum(used, 1)[:, None]
    squared = jnp.sum(((measured - mean[:, None]) * _weights(1.0)) ** 2, axis=-1)
    spread = jnp.sqrt(jnp.where(valid, squared, 0.0).sum(axis=1) / jnp.maximum(used, 1))
    ok = jnp.asarray(np.asarray(filled)) & (used > 0)
    return StepModel(steps=jnp.where(ok[:, None], mean, 0.0), spread=jnp.where(ok, spread, jnp.inf))


@functools.partial(jax.jit, static_argnames=("task",))
def _measure_block(robot: Robot, middle_params: jax.Array, start: SimState, own: jax.Array, before: jax.Array,
                   task: MiddleTask) -> tuple[jax.Array, jax.Array]:
    """(n, 3) normalised steps and (n,) validity of elites `own` (n,) after `before` (n,) (-1: neutral pose)."""
    first = jnp.where(before[:, None] >= 0, middle_params[jnp.maximum(before, 0)], 0.0)
    params = jnp.stack([first, middle_params[own]], axis=1)  # (n, 2, 36)
    spec = RolloutSpec(num_steps=2 * task.steps, pose_steps=(task.steps, 2 * task.steps), record_contacts=False)
    result = rollout(robot, params, jnp.zeros(NUM_LEGS, bool), start, spec)
    poses = planar_pose(result.base_pos, result.base_quat)
    return task.normalise(relative_pose(poses[:, 0], poses[:, 1])), result.valid


def plan_batch(table: PatternTable, task: MiddleTask, here: jax.Array, target: jax.Array, pattern: jax.Array,
               remaining: jax.Array | int, beam: tuple[int, int] = DEFAULT_BEAM,
               yaw_weight: float = DEFAULT_YAW_WEIGHT) -> jax.Array:
    """`plan_step` for B robots (pattern -1: no plan, -1); remaining (1-3): an int or an unbatched traced scalar."""
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
    return jnp.concatenate([top_descriptors * (2 * extent) - extent, arrival_yaw[..., None]], axis=-1)
