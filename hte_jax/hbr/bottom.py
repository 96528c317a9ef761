"""Bottom layer: leg primitives (paper section 3; `docs/original_code.md` §3), one leg's (a, p, d) of the
hip and vertical signals run 1 s on a random leg of the standing robot (one repertoire serves all legs).
Descriptor: stance sweep, lift height, duty level in [0, 1]^3; fitness: minus the leg's activation."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from hte_jax.errors import check_fields, choice, integer, number
from hte_jax.qd.archive import Archive
from hte_jax.qd.repertoire import Evaluation
from hte_jax.qd.task_spec import EvaluateFn, TaskSpec
from hte_jax.sim.controller import NUM_PARAMS
from hte_jax.sim.robot import FOOT_REACH, NUM_LEGS, Robot
from hte_jax.sim.env import SimState
from hte_jax.sim.rollout import RolloutSpec, rollout

GENES = 6  # (a, p, d) hip signal, (a, p, d) vertical signal
DESCRIPTORS = 3  # swing, height, duty
BOTTOM_FITNESSES = ("commands", "genes")
EXTRAS = {"leg": ((), "int32")}  # the leg each primitive was evaluated on
ARCHIVE_L = 0.01  # default distance threshold of the layer's archive (`HBRConfig.bottom_l`)
QD_OFFSET = -1.0  # the lowest "commands" fitness


@dataclasses.dataclass(frozen=True)
class BottomTask:
    """How a leg primitive is evaluated (hashable): `steps` control steps (100 = 1 s), swing / height
    descriptors over [-range, range] m, `duty_levels` duty levels, fitness "commands" or "genes"."""

    steps: int = integer(100)
    swing_range: float = number(0.2, 0.0, open_low=True)
    height_range: float = number(0.06, 0.0, open_low=True)
    duty_levels: int = integer(4, minimum=2)
    fitness: str = choice("commands", BOTTOM_FITNESSES)

    def __post_init__(self):
        check_fields(self, "bottom ")

    @property
    def spec(self) -> RolloutSpec:
        return RolloutSpec(num_steps=self.steps, pose_steps=tuple(range(self.steps)), record_contacts=True,
                           record_feet=True, record_joints=True)


def bottom_spec(capacity: int, l: float = ARCHIVE_L, evaluate: EvaluateFn | None = None) -> TaskSpec:
    """The bottom layer as a QD task: 6 genes, an archive of `capacity` slots over [0, 1]^3, threshold `l`."""
    return TaskSpec("hbr-bottom", GENES, Archive(capacity, (0.0,) * DESCRIPTORS, (1.0,) * DESCRIPTORS, l), evaluate,
                    EXTRAS, QD_OFFSET)


def swing_distance(hip_angle: jax.Array, contact: jax.Array) -> jax.Array:
    """(..., T) hip angles and foot contacts -> (...,) signed arc (m) the foot sweeps while down at both ends
    of a step, positive as the hip angle falls (the original's start-to-end displacement is ~0 after one
    period, `docs/original_code.md` §14.7)."""
    down = contact[..., 1:] & contact[..., :-1]
    return -FOOT_REACH * jnp.sum(jnp.where(down, jnp.diff(hip_angle, axis=-1), 0.0), axis=-1)


def lift_height(foot_z: jax.Array, base_z: jax.Array) -> jax.Array:
    """(..., T) foot and base heights -> (...,) signed extreme of the foot's relative height change."""
    relative = (foot_z - base_z) - (foot_z[..., :1] - base_z[..., :1])
    extreme = jnp.argmax(jnp.abs(relative), axis=-1)
    return jnp.take_along_axis(relative, extreme[..., None], axis=-1)[..., 0]


def duty_level(duty: jax.Array, levels: int = 4) -> jax.Array:
    """Duty genes in [0, 1] -> level k / (levels - 1), k = min(floor(levels d), levels - 1) (original: 1 -> 0)."""
    return jnp.minimum(jnp.floor(duty * levels + 1e-6), levels - 1) / (levels - 1)


def activation_fitness(command_abs_sum: jax.Array, duration: float, max_velocity: float) -> jax.Array:
    """(..., 3) integrated |command| (rad) of a leg's joints -> (...,) minus their mean over the limit, in [-1, 0]."""
    return -command_abs_sum.mean(axis=-1) / (duration * max_velocity)


def gene_fitness(genes: jax.Array) -> jax.Array:
    """(..., 6) primitives -> (...,) the original's fitness, minus the sum of the genes over 3 (in [-2, 0])."""
    return -jnp.sum(jnp.abs(genes), axis=-1) / 3.0


def leg_params(genes: jax.Array, leg: jax.Array) -> jax.Array:
    """(B, 6) primitives and (B,) leg indices -> (B, 36) controllers driving only that leg."""
    onehot = jax.nn.one_hot(leg, NUM_LEGS, dtype=genes.dtype)
    return (onehot[:, :, None] * genes[:, None, :]).reshape(genes.shape[0], NUM_PARAMS)


def evaluate_bottom(robot: Robot, start: SimState, task: BottomTask, key: jax.Array, genes: jax.Array) -> Evaluation:
    """Evaluate (B, 6) leg primitives, each on a random leg, from `start`; extras "leg" (B,) int32."""
    batch = genes.shape[0]
    leg = jax.random.randint(key, (batch,), 0, NUM_LEGS)
    result = rollout(robot, leg_params(genes, leg), jnp.zeros(NUM_LEGS, bool), start, task.spec)
    rows = jnp.arange(batch)
    swing = swing_distance(result.joint_pos[rows, :, 3 * leg], result.foot_contacts[rows, :, leg])  # from (B, T)
    height = lift_height(result.foot_pos[rows, :, leg, 2], result.base_pos[:, :, 2])
    descriptors = jnp.stack([(swing + task.swing_range) / (2 * task.swing_range),
                             (height + task.height_range) / (2 * task.height_range),
                             duty_level(genes[:, 5], task.duty_levels)], axis=-1)
    if task.fitness == "genes":
        fitness = gene_fitness(genes)
    else:
        commands = result.command_abs_sum.reshape(batch, NUM_LEGS, 3)[rows, leg]
        fitness = activation_fitness(commands, task.steps * robot.config.control_dt, robot.config.max_joint_velocity)
    in_range = jnp.all((descriptors >= 0.0) & (descriptors <= 1.0), axis=-1)
    return Evaluation(fitnesses=fitness, descriptors=descriptors, valid=result.valid & in_range,
                      extras={"leg": leg.astype(jnp.int32)})
