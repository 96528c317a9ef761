"""APROL (Kaushik et al. 2020) in the maze: K prior repertoires, one RTE GP each, and the choice of the
executed skill by log L(k, a) + log P(k) (`docs/design.md`, APROL, with the fixes against the original).

    log L(k, a) = sum over x, y of [-1/2 log(2 pi var) - (mu - goal)^2 / (2 var)],
    P(k) = (m_k + u_k) / sum_j (m_j + u_j),   u_k = c sqrt(2 ln N / n_k),   N = sum_j n_j,

mu, var: repertoire k's GP posterior at skill a; m_k: its mean closeness; n_k: its trial count.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import struct

from hte_jax.online.skills import outcome

EXPLORATION = 0.01  # c of the UCB term
INITIAL_SCORE = 0.6  # m_k before any trial
CLOSENESS_RATE = 5.0
VARIANCE_FLOOR = 1e-10


@struct.dataclass
class MapBelief:
    """APROL's belief about K repertoires (one episode; batched with a leading B). trials: (K,) int32 n_k,
    trials plus one. score: (K,) float32 m_k, mean closeness of predictions to what the robot did.
    current: () int32 the repertoire the planner uses next (the one chosen last)."""

    trials: jax.Array
    score: jax.Array
    current: jax.Array


def initial_belief(num_maps: int, start: jax.Array | int = 0) -> MapBelief:
    return MapBelief(trials=jnp.ones(num_maps, jnp.int32), score=jnp.full(num_maps, INITIAL_SCORE, jnp.float32),
                     current=jnp.asarray(start, jnp.int32))


def map_probability(belief: MapBelief, exploration: float = EXPLORATION) -> jax.Array:
    """(K,) P(k): mean closeness plus a UCB bonus, normalised."""
    trials = belief.trials.astype(jnp.float32)
    bonus = exploration * jnp.sqrt(2.0 * jnp.log(trials.sum()) / trials)
    weight = belief.score + bonus
    return weight / weight.sum()


def entry_scores(belief: MapBelief, mean: jax.Array, variance: jax.Array, mask: jax.Array, goal: jax.Array) -> jax.Array:
    """(K, A) log score of every skill: log-likelihood of reaching `goal` (2,) (m) plus log P(k). mean:
    (K, A, >=2) GP posterior mean (dx, dy first, m). variance: (K, A) (m^2). mask: (K, A) bool real skills."""
    var = jnp.maximum(variance, VARIANCE_FLOOR)[..., None]
    log_likelihood = jnp.sum(-0.5 * jnp.log(2.0 * math.pi * var) - (mean[..., :2] - goal) ** 2 / (2.0 * var), axis=-1)
    score = log_likelihood + jnp.log(map_probability(belief))[:, None]
    return jnp.where(mask, score, -jnp.inf)


def select_entry(belief: MapBelief, mean: jax.Array, variance: jax.Array, mask: jax.Array, goal: jax.Array):
    """The (repertoire, skill) with the best score (ties: the lowest flat index). Returns two () int32."""
    score = entry_scores(belief, mean, variance, mask, goal)
    flat = jnp.argmax(score.reshape(-1))
    return (flat // score.shape[1]).astype(jnp.int32), (flat % score.shape[1]).astype(jnp.int32)


def closeness(predicted: jax.Array, displacement: jax.Array) -> jax.Array:
    """exp(-5 |predicted - observed|) with predicted (4,) (dx, dy, cos, sin) and observed (dx, dy, dyaw)."""
    return jnp.exp(-CLOSENESS_RATE * jnp.linalg.norm(predicted - outcome(displacement)))


def update_belief(belief: MapBelief, chosen: jax.Array, close: jax.Array) -> MapBelief:
    """Repertoire `chosen` was tried and its prediction scored `close`: count it, average it in."""
    trials = belief.trials.at[chosen].add(1)
    n = trials[chosen].astype(jnp.float32)
    # The initial score counts as the first of n values (the original's running mean).
    score = belief.score.at[chosen].set(((n - 1.0) * belief.score[chosen] + close) / n)
    return MapBelief(trials=trials, score=score, current=jnp.asarray(chosen, jnp.int32))
