"""Top layer: 3 s skills on a 100 x 100 grid (paper section 3; `docs/original_code.md` §5). Genotype: three
middle-layer primary steps, run by `hierarchy.execute_skill` by primary descriptor only (paper section 4);
descriptor: final (x, y) on the `TopTask` grid; fitness: the skill's angle error."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from hte_jax.hbr.hierarchy import HBR, STEPS_PER_SKILL, execute_skill
from hte_jax.hbr.middle import PRIMARY
from hte_jax.geometry import angle_error
from hte_jax.hbr.skill_grid import TopTask as TopTask  # the top layer's grid, re-exported
from hte_jax.qd.repertoire import Evaluation
from hte_jax.qd.task_spec import EvaluateFn, TaskSpec
from hte_jax.sim.robot import Robot
from hte_jax.sim.env import SimState

GENES = STEPS_PER_SKILL * PRIMARY  # a middle-layer primary descriptor (x, y, yaw step) per second
EXTRAS = {"middle_indices": ((STEPS_PER_SKILL,), "int32"), "arrival_yaw": ((), "float32")}
QD_OFFSET = -math.pi  # the lowest angle error


def top_spec(task: TopTask, evaluate: EvaluateFn | None = None) -> TaskSpec:
    """The top layer as a QD task: 9 genes, the task's x-y grid, the extras `evaluate_top` returns."""
    return TaskSpec("hbr-top", GENES, task.grid(), evaluate, EXTRAS, QD_OFFSET)


def evaluate_top(robot: Robot, start: SimState, task: TopTask, hbr: HBR, key: jax.Array,
                 genotypes: jax.Array) -> Evaluation:
    """Evaluate (B, 9) skills from the unbatched standing state `start`; extras (B, ...) `EXTRAS` (yaw in rad)."""
    del key
    batch = genotypes.shape[0]
    starts = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), start)
    skill = execute_skill(robot, hbr, genotypes, starts)
    descriptors = task.normalise(skill.displacement[:, :2])
    in_range = jnp.all((descriptors >= 0.0) & (descriptors <= 1.0), axis=-1)
    used = jnp.swapaxes(skill.steps.middle_index, 0, 1).reshape(batch, STEPS_PER_SKILL)
    return Evaluation(fitnesses=angle_error(skill.displacement), descriptors=descriptors, valid=skill.valid & in_range,
                      extras={"middle_indices": used, "arrival_yaw": skill.displacement[:, 2]})
