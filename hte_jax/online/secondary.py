"""HTE's secondary descriptor: the paper's error measure and GP-UCB score of contact patterns
(`docs/design.md`, Secondary descriptor).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.hbr.middle import NUM_PATTERNS, pattern_code
from hte_jax.sim.robot import NUM_LEGS

ERROR_SCALE = np.array([4.0, 4.0, 3.0], np.float32)  # k for x, y, yaw (paper: k = 4; code: 3 for yaw)
ERROR_CENTRE = 0.5  # c: the normalised descriptor of "no motion"
ERROR_GUARD = 0.001
UCB_DELTA = 0.1
ERROR_DIM = 3  # the relative errors of x, y, yaw: the secondary GP's outputs


def legs_down(pattern: int) -> list[int]:
    """Legs on the ground in a pattern (leg 0 = most significant bit)."""
    return [leg for leg in range(NUM_LEGS) if pattern >> (NUM_LEGS - 1 - leg) & 1]


def allowed_patterns() -> np.ndarray:
    """The original's 36 candidates, ascending: >= 3 feet down, not three consecutive legs of the ring 0-...-5-0."""
    allowed = []
    for pattern in range(NUM_PATTERNS):
        down = legs_down(pattern)
        consecutive = len(down) == 3 and any(set(down) == {i % NUM_LEGS, (i + 1) % NUM_LEGS, (i + 2) % NUM_LEGS}
                                             for i in range(NUM_LEGS))
        if len(down) >= 3 and not consecutive:
            allowed.append(pattern)
    return np.asarray(allowed, np.int32)


def oracle_pattern(damage: np.ndarray) -> int:
    """Perfect HTE: the pattern with exactly the intact legs down (63 for the intact robot)."""
    return int(pattern_code((~np.asarray(damage, bool)).astype(np.float32), xp=np))


def oracle_patterns(damages: jax.Array) -> jax.Array:
    """(..., 6) bool damaged legs -> (...,) int32 `oracle_pattern` of each (jax: also inside a jit)."""
    return pattern_code((~jnp.asarray(damages, bool)).astype(jnp.float32))


def relative_error(expected: jax.Array, observed: jax.Array) -> jax.Array:
    """(..., 3) normalised primary descriptors -> (..., 3) errors |bd' - bd| / (2 |bd - c| + guard)."""
    return jnp.abs(observed - expected) / (2.0 * jnp.abs(expected - ERROR_CENTRE) + ERROR_GUARD)


def ucb_beta(t: jax.Array, candidates: int = 36) -> jax.Array:
    """GP-UCB exploration weight at step t >= 1: sqrt(log(1.5 |C| t^2 pi^2 / (6 delta)))."""
    t = jnp.asarray(t, jnp.float32)
    return jnp.sqrt(jnp.log(1.5 * candidates * t**2 * jnp.pi**2 / (6.0 * UCB_DELTA)))


def acquisition(mean: jax.Array, variance: jax.Array, beta: jax.Array) -> jax.Array:
    """(C, 3) predicted errors and (C,) variance -> (C,) UCB scores (higher is better)."""
    score = jnp.exp(-jnp.asarray(ERROR_SCALE) * jnp.maximum(mean, 0.0))
    return jnp.linalg.norm(score, axis=-1) + beta * variance
