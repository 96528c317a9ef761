"""HTE's choice of secondary descriptor (contact pattern) by GP-UCB on the error measure (facts 7.3).

Before each 1 s step the robot picks, among the allowed contact patterns, the one whose middle
elite is predicted to deviate least from its stored primary descriptor. A GP (Matern-5/2,
input: the elite's 9-D descriptor, output: the three relative errors of x, y, yaw) learns the
errors on the damaged robot; the score of a candidate is ||exp(-k max(0, mu))||_2 + beta_t var
(k = 4, 4, 3), with the GP-UCB schedule beta_t of the original.

Ours (`usable_pattern`, not the paper's): the robot compares each leg's sensed floor contact with
the contact its executed elites expected; a leg that stays off the floor (blocked in the air) is
judged unusable and the steps take the pattern with every other leg down. `stuck_legs` adds the
joints' own sense: a leg whose joints moved much less than their controllers asked (a leg locked in
any pose, on the floor or in the air) is judged unusable too.

Ours (`predicted_miss`, not the paper's): the GP also learns each executed elite's absolute
deviation |bd' - bd| (normalised units), and every pattern's nearest elite is scored by how far
from the wanted step it is predicted to end: primary mismatch plus predicted deviation. With no
observations the deviation is predicted 0 and the choice is RTE's (the nearest elite of any
pattern); as the damage shows, elites whose pattern it spoils are predicted to miss and avoided.
"""

from __future__ import annotations

import numpy as np
import jax.numpy as jnp
import jax

from hte_jax.hbr.middle import NUM_PATTERNS, PRIMARY
from hte_jax.online.gp import GPData
from hte_jax.sim.robot import NUM_LEGS

ERROR_SCALE = np.array([4.0, 4.0, 3.0], np.float32)  # k for x, y, yaw (paper: k = 4; code: 3 for yaw)
ERROR_CENTRE = 0.5  # c: the normalised descriptor of "no motion"
ERROR_GUARD = 0.001
UCB_DELTA = 0.1
LEG_PRIOR_PRECISION = 1.0  # ridge weight of `leg_effects`: one pseudo-observation of "no effect"
CONTACT_EVIDENCE = 0.3  # seconds of expected floor contact before a leg is judged (`unusable_legs`)
CONTACT_RATIO = 0.1  # a leg sensed down for less than this share of its expected contact is unusable
JOINT_EVIDENCE = 3.0  # rad of commanded joint travel before a leg's tracking is judged (`stuck_legs`)
JOINT_RATIO = 0.55  # a leg whose joints moved less than this share of the commanded travel is stuck


def legs_down(pattern: int) -> list[int]:
    """Legs on the ground in a pattern (leg 0 = most significant bit)."""
    return [leg for leg in range(NUM_LEGS) if pattern >> (NUM_LEGS - 1 - leg) & 1]


def allowed_patterns() -> np.ndarray:
    """The original's 36 candidate patterns, ascending: at least three feet down, and not three
    consecutive legs around the body ring 0-1-2-3-4-5-0 (the robot cannot stand on those)."""
    allowed = []
    for pattern in range(NUM_PATTERNS):
        down = legs_down(pattern)
        consecutive = len(down) == 3 and any(
            set(down) == {i % NUM_LEGS, (i + 1) % NUM_LEGS, (i + 2) % NUM_LEGS} for i in range(NUM_LEGS)
        )
        if len(down) >= 3 and not consecutive:
            allowed.append(pattern)
    return np.asarray(allowed, np.int32)


def oracle_pattern(damage: np.ndarray) -> int:
    """Perfect HTE: the pattern with exactly the intact legs down (63 for the intact robot)."""
    return int(sum(1 << (NUM_LEGS - 1 - leg) for leg in range(NUM_LEGS) if not damage[leg]))


def relative_error(expected: jax.Array, observed: jax.Array) -> jax.Array:
    """(..., 3) normalised primary descriptors -> (..., 3) errors |bd' - bd| / (2 |bd - c| + guard)."""
    return jnp.abs(observed - expected) / (2.0 * jnp.abs(expected - ERROR_CENTRE) + ERROR_GUARD)


def step_targets(expected: jax.Array, observed: jax.Array) -> jax.Array:
    """(..., 3) stored and observed primary descriptors -> (..., 9) the secondary GP's targets:
    the paper's relative errors, the absolute deviations |bd' - bd|, the signed deviations bd' - bd."""
    return jnp.concatenate([relative_error(expected, observed), jnp.abs(observed - expected), observed - expected],
                           axis=-1)


def predicted_landing_miss(desired: jax.Array, candidates: jax.Array, drift: jax.Array) -> jax.Array:
    """How far from the wanted step (..., 3) each candidate (..., C, 3) lands if it drifts by the
    predicted signed deviation `drift` (..., C, 3): || candidate + drift - desired ||_2, (..., C)."""
    return jnp.linalg.norm(candidates + drift - desired[..., None, :], axis=-1)


def predicted_miss(
    desired: jax.Array, candidates: jax.Array, deviation: jax.Array, std: jax.Array, optimism: float
) -> jax.Array:
    """How far from the wanted step each candidate elite is predicted to end (normalised units).

    desired: (..., 3) wanted primary step. candidates: (..., C, 3) the candidates' stored primary
    descriptors. deviation: (..., C, 3) predicted |bd' - bd|; std: (..., C) its posterior standard
    deviation, subtracted `optimism` times (a lower confidence bound: untried elites get tried).
    Returns (..., C): || |candidate - desired| + max(0, deviation - optimism std) ||_2.
    """
    mismatch = jnp.abs(candidates - desired[..., None, :])
    hopeful = jnp.maximum(deviation - optimism * std[..., None], 0.0)
    return jnp.linalg.norm(mismatch + hopeful, axis=-1)


def leg_effects(data: GPData, precision: float = LEG_PRIOR_PRECISION) -> jax.Array:
    """(6,) what each leg's use adds to a step's deviation, learnt from the secondary GP's data.

    Ridge regression (an intercept plus one weight per leg, the weights shrunk towards 0 by
    `precision`) of each observed step's absolute deviation ||bd' - bd||_2 on its executed elite's
    contact bits (`data.inputs[:, 3:9]`; deviations are `data.targets[:, 3:6]`, see `step_targets`).
    A damaged leg shows as a large weight; the weights are 0 before any observation.
    """
    weight = data.mask.astype(jnp.float32)
    bits = data.inputs[:, PRIMARY:]
    deviation = jnp.linalg.norm(data.targets[:, 3:6], axis=-1)
    design = jnp.concatenate([jnp.ones_like(bits[:, :1]), bits], axis=-1)  # (N, 7)
    ridge = jnp.diag(jnp.asarray([1e-6] + [precision] * NUM_LEGS, jnp.float32))
    with jax.default_matmul_precision("highest"):
        gram = design.T @ (weight[:, None] * design) + ridge
        coef = jnp.linalg.solve(gram, design.T @ (weight * deviation))
    return coef[1:]


def leg_miss(desired: jax.Array, candidates: jax.Array, effects: jax.Array) -> jax.Array:
    """How far from the wanted step (..., 3) each candidate elite (..., C, 9) is predicted to end:
    its primary mismatch ||candidate - desired||_2 plus the learnt effect (..., 6) of every leg it
    puts down (negative effects count as 0: using a leg never makes a step more accurate). (..., C)."""
    mismatch = jnp.linalg.norm(candidates[..., :PRIMARY] - desired[..., None, :], axis=-1)
    return mismatch + jnp.sum(candidates[..., PRIMARY:] * jnp.maximum(effects, 0.0)[..., None, :], axis=-1)


def unusable_legs(contacts: jax.Array, evidence: float = CONTACT_EVIDENCE, ratio: float = CONTACT_RATIO) -> jax.Array:
    """(..., 2, 6) seconds each leg was sensed on the floor and expected on it -> (..., 6) bool, the
    legs that touched the floor for less than `ratio` of the contact the executed elites expected,
    once they expected at least `evidence` seconds (a leg blocked in the air senses none)."""
    sensed, expected = contacts[..., 0, :], contacts[..., 1, :]
    return (expected >= evidence) & (sensed < ratio * expected)


def stuck_legs(motion: jax.Array, evidence: float = JOINT_EVIDENCE, ratio: float = JOINT_RATIO) -> jax.Array:
    """(..., 2, 6) radians each leg's joints moved and were commanded to move -> (..., 6) bool, the
    legs that moved less than `ratio` of the commanded travel once at least `evidence` rad were
    commanded (a locked leg's joints hold their pose whatever they are asked)."""
    moved, commanded = motion[..., 0, :], motion[..., 1, :]
    return (commanded >= evidence) & (moved < ratio * commanded)


def usable_pattern(contacts: jax.Array, motion: jax.Array | None = None) -> jax.Array:
    """(..., 2, 6) sensed and expected contact, and optionally (..., 2, 6) moved and commanded joint
    travel -> (...,) int32: the pattern with every leg down but the unusable ones (`unusable_legs`,
    and `stuck_legs` when motion is given), or -1 (any pattern) while every leg seems usable."""
    bad = unusable_legs(contacts)
    if motion is not None:
        bad = bad | stuck_legs(motion)
    weights = jnp.asarray([1 << (NUM_LEGS - 1 - leg) for leg in range(NUM_LEGS)], jnp.int32)
    pattern = jnp.sum(jnp.where(bad, 0, weights), axis=-1)
    return jnp.where(bad.any(axis=-1), pattern, -1).astype(jnp.int32)


def ucb_beta(t: jax.Array, candidates: int = 36) -> jax.Array:
    """GP-UCB exploration weight at step t >= 1: sqrt(log(1.5 |C| t^2 pi^2 / (6 delta)))."""
    t = jnp.asarray(t, jnp.float32)
    return jnp.sqrt(jnp.log(1.5 * candidates * t**2 * jnp.pi**2 / (6.0 * UCB_DELTA)))


def acquisition(mean: jax.Array, variance: jax.Array, beta: jax.Array) -> jax.Array:
    """(C, 3) predicted errors and (C,) variance -> (C,) UCB scores (higher is better)."""
    score = jnp.exp(-jnp.asarray(ERROR_SCALE) * jnp.maximum(mean, 0.0))
    return jnp.linalg.norm(score, axis=-1) + beta * variance
