"""How fast can a motion representation move at each turn rate? A dedicated frontier search.

The HBR's middle layer is limited by the fastest 1 s motions it stores at each turn rate (its
speed-versus-turn frontier, `analysis.speed_by_turn`). To tell whether a limit comes from the
representation (six leg primitives looked up by bottom descriptor) or from the middle layer's
search, this runs the same MAP-Elites over a different container: a 1-D grid over |yaw|
(`bins` cells over [0, max_turn]) whose fitness is the speed. Any map from genotypes in [0, 1]
to 36-parameter controllers can be searched, e.g. the HBR's middle genotype or the flat
controller itself, with the middle layer's evaluation (chained samples, medoid sample).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from hte_jax.hbr.middle import MiddleTask, evaluate_controllers
from hte_jax.qd.grid import Grid
from hte_jax.qd.loop import MapElites, MapElitesConfig
from hte_jax.qd.repertoire import Evaluation
from hte_jax.sim.robot import Robot
from hte_jax.sim.rollout import SimState

# genotypes (B, G) in [0, 1] -> controllers (B, 36)
ToControllers = Callable[[jax.Array], jax.Array]


def frontier_evaluation(robot: Robot, start: SimState, task: MiddleTask, to_controllers: ToControllers):
    """evaluate(key, genotypes) -> Evaluation: descriptor |yaw| / max_turn (B, 1), fitness speed (m/s).

    Validity is the middle layer's (finite upright rollout, |x|, |y| <= max_step, |yaw| <= max_turn).
    """

    def evaluate(key: jax.Array, genotypes: jax.Array) -> Evaluation:
        del key
        motion = evaluate_controllers(robot, start, task, to_controllers(genotypes))
        step = task.denormalise(motion.descriptors[:, :3])
        return Evaluation(
            fitnesses=jnp.hypot(step[:, 0], step[:, 1]),
            descriptors=jnp.abs(step[:, 2:3]) / task.max_turn,
            valid=motion.valid,
            extras={},
        )

    return evaluate


def frontier_search(
    robot: Robot,
    start: SimState,
    task: MiddleTask,
    to_controllers: ToControllers,
    genotype_dim: int,
    *,
    batch_size: int,
    mutation_rate: float,
    bins: int = 20,
) -> MapElites:
    """A MAP-Elites whose grid cell b holds the fastest motion found with |yaw| in bin b."""
    return MapElites(
        container=Grid((bins,), (0.0,), (1.0,)),
        evaluate=frontier_evaluation(robot, start, task, to_controllers),
        genotype_dim=genotype_dim,
        config=MapElitesConfig(batch_size=batch_size, init_size=batch_size, mutation_rate=mutation_rate, eta_m=10.0),
    )
