"""A flat repertoire's evaluation (paper section 5; `docs/original_code.md` §6): a 36-parameter controller
run 3 s from the (damaged) standing robot. Descriptor: final (x, y) on the top layer's grid ("2d"), plus
six contact bits ("8d"); fitness: the circular-trajectory angle error."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from hte_jax.errors import check_fields, choice, integer, number
from hte_jax.geometry import angle_error, planar_pose, relative_pose
from hte_jax.hbr.top import TopTask
from hte_jax.qd.grid import Grid
from hte_jax.qd.repertoire import Evaluation
from hte_jax.qd.task_spec import EvaluateFn, TaskSpec
from hte_jax.sim.controller import NUM_PARAMS
from hte_jax.sim.robot import NUM_LEGS, Robot
from hte_jax.sim.env import SimState
from hte_jax.sim.rollout import RolloutSpec, rollout

GENES = NUM_PARAMS  # 36
DESCRIPTOR_DIMS = {"2d": 2, "8d": 2 + NUM_LEGS}
EXTRAS = {"arrival_yaw": ((), "float32"), "contact_fraction": ((NUM_LEGS,), "float32")}
QD_OFFSET = -math.pi  # the lowest angle error


@dataclasses.dataclass(frozen=True)
class FlatTask:
    """What a flat repertoire measures (hashable): descriptor "2d" or "8d", `bins` x-y cells per axis over
    [-extent, extent] m, `steps` control steps (100 per s), contact_threshold of the 8d contact bits."""

    descriptor: str = choice("2d", DESCRIPTOR_DIMS)
    bins: int = integer(100)
    extent: float = number(1.5, 0.0, open_low=True)
    steps: int = integer(300)
    contact_threshold: float = number(0.3, 0.0, 1.0)

    def __post_init__(self):
        check_fields(self)

    @property
    def descriptor_dim(self) -> int:
        return DESCRIPTOR_DIMS[self.descriptor]

    @property
    def xy(self) -> TopTask:
        """The x-y grid alone (shared with the HBR top layer)."""
        return TopTask(bins=self.bins, extent=self.extent)

    def grid(self) -> Grid:
        dims = self.descriptor_dim
        return Grid(bins=(self.bins, self.bins) + (2,) * (dims - 2), low=(0.0,) * dims, high=(1.0,) * dims)

    def spec(self) -> RolloutSpec:
        return RolloutSpec(num_steps=self.steps, pose_steps=(0, self.steps), record_contacts=True)


def flat_spec(task: FlatTask, evaluate: EvaluateFn | None = None) -> TaskSpec:
    """A flat repertoire as a QD task; for `BatchedMapElites`, `evaluate` also takes the run's condition."""
    return TaskSpec(f"flat-{task.descriptor}", GENES, task.grid(), evaluate, EXTRAS, QD_OFFSET)


def evaluate_flat(robot: Robot, task: FlatTask, start: SimState, damage: jax.Array, key: jax.Array,
                  genotypes: jax.Array) -> Evaluation:
    """Evaluate (B, 36) controllers from the unbatched `start` with damage (6,) (key unused); extras
    "arrival_yaw" (B,) rad in the start frame, "contact_fraction" (B, 6)."""
    del key
    result = rollout(robot, genotypes, damage, start, task.spec())
    poses = planar_pose(result.base_pos, result.base_quat)
    displacement = relative_pose(poses[:, 0], poses[:, 1])
    xy = task.xy.normalise(displacement[:, :2])
    fraction = result.foot_contacts.mean(axis=1)
    descriptors = xy
    if task.descriptor == "8d":
        descriptors = jnp.concatenate([xy, (fraction > task.contact_threshold).astype(jnp.float32)], axis=-1)
    in_range = jnp.all((xy >= 0.0) & (xy <= 1.0), axis=-1)
    return Evaluation(fitnesses=angle_error(displacement), descriptors=descriptors, valid=result.valid & in_range,
                      extras={"arrival_yaw": displacement[:, 2], "contact_fraction": fraction})
