"""APROL's choice of repertoire and skill: the score formula, the belief update (trial counts grow),
and a toy two-repertoire case where the robot behaves like the second repertoire."""

import math

import jax.numpy as jnp
import numpy as np

from hte_jax.online.gp import add_observation, empty_gp
from hte_jax.online.skills import OUTCOME_DIM, ActionSet, displacement_of, outcome, predict
from hte_jax.online.aprol import (
    EXPLORATION,
    INITIAL_SCORE,
    closeness,
    entry_scores,
    initial_belief,
    map_probability,
    select_entry,
    update_belief,
)


def test_scores_match_the_formula():
    rng = np.random.default_rng(0)
    mean = rng.normal(size=(3, 5, 4)).astype(np.float32)
    variance = rng.uniform(0.001, 0.01, size=(3, 5)).astype(np.float32)
    mask = np.ones((3, 5), bool)
    mask[2, 3:] = False
    goal = np.array([0.2, -0.1], np.float32)
    belief = initial_belief(3).replace(trials=jnp.asarray([2, 1, 4]), score=jnp.asarray([0.5, 0.6, 0.2]))
    n = np.array([2.0, 1.0, 4.0])
    weight = np.array([0.5, 0.6, 0.2]) + EXPLORATION * np.sqrt(2 * np.log(n.sum()) / n)
    prior = weight / weight.sum()
    np.testing.assert_allclose(np.asarray(map_probability(belief)), prior, rtol=1e-5)
    loglik = np.sum(-0.5 * np.log(2 * np.pi * variance[..., None]) - (mean[..., :2] - goal) ** 2 / (2 * variance[..., None]), -1)
    expected = np.where(mask, loglik + np.log(prior)[:, None], -np.inf)
    np.testing.assert_allclose(np.asarray(entry_scores(belief, mean, variance, mask, goal)), expected, rtol=1e-4)
    k, a = select_entry(belief, mean, variance, mask, goal)
    assert (int(k), int(a)) == np.unravel_index(np.argmax(expected), expected.shape)


def test_belief_update_counts_every_trial():
    belief = initial_belief(2, start=0)
    assert belief.trials.tolist() == [1, 1] and np.allclose(belief.score, INITIAL_SCORE)
    belief = update_belief(belief, jnp.int32(1), jnp.float32(1.0))
    belief = update_belief(belief, jnp.int32(1), jnp.float32(0.0))
    assert belief.trials.tolist() == [1, 3] and int(belief.current) == 1
    np.testing.assert_allclose(float(belief.score[1]), (INITIAL_SCORE + 1.0 + 0.0) / 3, rtol=1e-6)
    # closeness compares metres with metres: a perfect prediction scores 1, 0.1 m off scores exp(-0.5)
    predicted = jnp.asarray([0.3, 0.0, 1.0, 0.0])
    assert math.isclose(float(closeness(predicted, jnp.asarray([0.3, 0.0, 0.0]))), 1.0, rel_tol=1e-6)
    assert math.isclose(float(closeness(predicted, jnp.asarray([0.3, 0.1, 0.0]))), math.exp(-0.5), rel_tol=1e-5)


def _toy_maps():
    """Two repertoires of 8 skills: map 0 predicts 0.3 m moves in 8 directions, map 1 predicts the
    opposite direction for the same descriptors (as if trained on another damage)."""
    angle = np.arange(8) * np.pi / 4
    inputs = np.stack([0.5 + 0.4 * np.cos(angle), 0.5 + 0.4 * np.sin(angle)], -1).astype(np.float32)
    moves = [np.stack([0.3 * np.cos(angle + shift), 0.3 * np.sin(angle + shift), np.ones(8), np.zeros(8)], -1)
             for shift in (0.0, np.pi)]
    return [ActionSet(slots=jnp.arange(8, dtype=jnp.int32), inputs=jnp.asarray(inputs), prior=jnp.asarray(m, jnp.float32),
                      mask=jnp.ones(8, bool)) for m in moves]


def test_toy_case_picks_the_repertoire_that_matches_the_observations():
    maps = _toy_maps()
    models = [empty_gp(16, m.inputs.shape[1], OUTCOME_DIM) for m in maps]
    belief = initial_belief(2, start=0)

    def robot(k, a):
        """The damaged robot: map 1's skills do what map 1 predicts; map 0's skills do not move."""
        return np.asarray(maps[1].prior[a, :2]) if k == 1 else np.zeros(2)

    goals = [np.array([0.3, 0.0]), np.array([0.0, 0.3]), np.array([-0.3, 0.0]), np.array([0.0, -0.3])] * 2
    chosen = []
    for goal in goals:
        stats = [predict(model, m) for model, m in zip(models, maps)]
        mean = jnp.stack([s[0] for s in stats])
        variance = jnp.stack([s[1] for s in stats])
        k, a = select_entry(belief, mean, variance, jnp.ones((2, 8), bool), jnp.asarray(goal, jnp.float32))
        k, a = int(k), int(a)
        chosen.append(k)
        moved = jnp.asarray([*robot(k, a), 0.0], jnp.float32)
        models[k] = add_observation(models[k], maps[k].inputs[a], outcome(moved), maps[k].prior[a])
        belief = update_belief(belief, jnp.int32(k), closeness(maps[k].prior[a], moved))
    # Map 0 is tried first (equal beliefs, lowest index), fails, and map 1 is used from then on.
    assert chosen[0] == 0 and all(k == 1 for k in chosen[1:]), chosen
    probability = np.asarray(map_probability(belief))
    assert probability[1] > 0.6 and int(belief.trials.sum()) == 2 + len(goals)
    # Map 0's GP learnt that its skill does not move: its prediction for that skill is now near 0.
    mean0, _ = predict(models[0], maps[0])
    assert float(jnp.abs(displacement_of(mean0)[0, :2]).max()) < 0.05
