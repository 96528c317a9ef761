"""HTE's secondary-descriptor selection: candidate patterns, error measure, UCB (facts 7.3)."""

import jax.numpy as jnp
import numpy as np

from hte_jax.online.gp import HTE_KERNEL, add_observation, empty_gp, posterior
from hte_jax.online.secondary import (
    CONTACT_EVIDENCE,
    CONTACT_RATIO,
    acquisition,
    allowed_patterns,
    leg_effects,
    leg_miss,
    oracle_pattern,
    predicted_landing_miss,
    predicted_miss,
    relative_error,
    step_targets,
    ucb_beta,
    unusable_legs,
    usable_pattern,
)
from hte_jax.sim.damage import paper_damage_masks

# the 28 patterns the original excludes (facts 7.3)
EXCLUDED = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 12, 14, 16, 17, 18, 20, 24, 28, 32, 33, 34, 35, 36, 40, 48, 49, 56}


def test_allowed_patterns_are_the_original_36():
    allowed = allowed_patterns()
    assert len(allowed) == 36
    assert set(allowed.tolist()) == set(range(64)) - EXCLUDED
    assert {42, 21, 63} <= set(allowed.tolist())  # both tripods and all feet down


def test_oracle_patterns_of_the_paper_damages():
    assert [oracle_pattern(m) for m in paper_damage_masks()] == [31, 47, 55, 59, 61, 62, 45]
    assert oracle_pattern(np.zeros(6, bool)) == 63


def test_error_measure_and_beta_hand_values():
    expected = jnp.asarray([0.9, 0.5, 0.25])
    observed = jnp.asarray([0.7, 0.6, 0.25])
    np.testing.assert_allclose(relative_error(expected, observed), [0.2 / 0.801, 0.1 / 0.001, 0.0], rtol=1e-5)
    np.testing.assert_allclose(ucb_beta(1), 2.6055, atol=1e-3)  # the original's ~2.61 at t = 1
    np.testing.assert_allclose(ucb_beta(100), np.sqrt(np.log(54 * 1e4 * np.pi**2 / 0.6)), rtol=1e-5)


def test_ucb_prefers_patterns_that_worked_and_explores_the_unknown():
    patterns = allowed_patterns()
    bits = ((patterns[:, None] >> np.arange(5, -1, -1)) & 1).astype(np.float32)
    inputs = jnp.asarray(np.concatenate([np.full((36, 3), 0.7, np.float32), bits], axis=1))
    # no data: every candidate scores the same (ties -> the first, as the original)
    mean, var = posterior(HTE_KERNEL, empty_gp(64, 9, 3), inputs)
    scores = np.asarray(acquisition(mean, var, ucb_beta(1)))
    assert np.allclose(scores, scores[0])
    # the all-feet pattern failed badly, the tripod 42 worked: 42 wins over 63
    data = empty_gp(64, 9, 3)
    data = add_observation(data, inputs[list(patterns).index(63)], jnp.asarray([2.0, 2.0, 2.0]))
    data = add_observation(data, inputs[list(patterns).index(42)], jnp.asarray([0.0, 0.0, 0.0]))
    mean, var = posterior(HTE_KERNEL, data, inputs)
    scores = np.asarray(acquisition(mean, var, 0.0))
    assert scores[list(patterns).index(42)] > scores[list(patterns).index(63)]
    assert np.asarray(var)[list(patterns).index(42)] < np.asarray(var).max()


def test_step_targets_and_predicted_miss_hand_values():
    expected = jnp.asarray([0.9, 0.5, 0.25])
    observed = jnp.asarray([0.7, 0.6, 0.25])
    np.testing.assert_allclose(step_targets(expected, observed),
                               [0.2 / 0.801, 0.1 / 0.001, 0.0, 0.2, 0.1, 0.0, -0.2, 0.1, 0.0], rtol=1e-5, atol=1e-7)
    landing = predicted_landing_miss(jnp.asarray([0.7, 0.5, 0.5]), jnp.asarray([[0.8, 0.5, 0.5], [0.6, 0.6, 0.5]]),
                                     jnp.asarray([[-0.1, 0.0, 0.0], [0.0, 0.0, 0.1]]))
    np.testing.assert_allclose(landing, [0.0, np.sqrt(0.03)], atol=1e-6)
    desired = jnp.asarray([0.7, 0.5, 0.5])
    candidates = jnp.asarray([[0.7, 0.5, 0.5], [0.8, 0.5, 0.4]])
    deviation = jnp.asarray([[0.3, 0.4, 0.0], [0.0, 0.0, 0.0]])
    std = jnp.asarray([0.1, 0.2])
    # greedy: candidate 0 is predicted 0.5 off, candidate 1 sqrt(0.02) off
    np.testing.assert_allclose(predicted_miss(desired, candidates, deviation, std, 0.0), [0.5, np.sqrt(0.02)], rtol=1e-6)
    # optimism takes 2 std off each predicted deviation, never below 0
    np.testing.assert_allclose(predicted_miss(desired, candidates, deviation, std, 2.0),
                               [np.hypot(0.1, 0.2), np.sqrt(0.02)], rtol=1e-6)


def test_leg_effects_recover_a_damaged_leg_and_score_candidates():
    """Deviations that grow only when leg 1 is down: the regression gives leg 1 a large weight and
    the others about 0 (NumPy's least squares with the same ridge agrees); a candidate that lifts
    leg 1 then beats a slightly nearer one that puts it down. No data: every weight is 0."""
    assert np.all(np.asarray(leg_effects(empty_gp(8, 9, 9))) == 0.0)
    rng = np.random.default_rng(0)
    gp = empty_gp(40, 9, 9)
    rows = []
    for _ in range(30):
        bits = rng.integers(0, 2, 6).astype(np.float32)
        deviation = 0.03 + 0.12 * bits[1] + rng.normal(0, 0.005)
        x = np.concatenate([rng.uniform(0.3, 0.7, 3), bits]).astype(np.float32)
        y = np.concatenate([np.zeros(3), [deviation, 0.0, 0.0], np.zeros(3)]).astype(np.float32)
        gp = add_observation(gp, jnp.asarray(x), jnp.asarray(y))
        rows.append((bits, deviation))
    effects = np.asarray(leg_effects(gp))
    assert effects[1] > 0.1 and np.all(np.abs(np.delete(effects, 1)) < 0.02)
    design = np.array([[1.0, *b] for b, _ in rows])
    target = np.array([d for _, d in rows])
    reference = np.linalg.solve(design.T @ design + np.diag([1e-6] + [1.0] * 6), design.T @ target)[1:]
    np.testing.assert_allclose(effects, reference, atol=1e-4)
    desired = jnp.asarray([0.6, 0.5, 0.5])
    candidates = jnp.asarray([[0.61, 0.5, 0.5, 1, 1, 1, 1, 1, 1], [0.64, 0.5, 0.5, 1, 0, 1, 1, 1, 1]], jnp.float32)
    miss = np.asarray(leg_miss(desired, candidates, jnp.asarray(effects)))
    np.testing.assert_allclose(miss[1] - 0.04, np.sum(np.maximum(np.delete(effects, 1), 0)), atol=1e-5)
    assert miss[1] < miss[0]


def test_unusable_legs_and_usable_pattern_match_a_numpy_reference():
    rng = np.random.default_rng(3)
    contacts = rng.uniform(0.0, 1.0, (200, 2, 6)).astype(np.float32)
    contacts[:50, 0, 2] = 0.0  # leg 2 never sensed down while expected half a second
    contacts[:50, 1, 2] = 0.5
    contacts[50:60, 1] = 0.1  # too little expected contact to judge
    sensed, expected = contacts[:, 0], contacts[:, 1]
    bad = (expected >= CONTACT_EVIDENCE) & (sensed < CONTACT_RATIO * expected)
    np.testing.assert_array_equal(np.asarray(unusable_legs(jnp.asarray(contacts))), bad)
    reference = np.array([sum(1 << (5 - leg) for leg in range(6) if not row[leg]) if row.any() else -1 for row in bad])
    np.testing.assert_array_equal(np.asarray(usable_pattern(jnp.asarray(contacts))), reference)
    assert bad[:50, 2].all() and not bad[50:60].any()
    # a leg blocked in the air: the pattern of the intact legs, the same as Perfect HTE's oracle
    raised = np.zeros((2, 6), np.float32)
    raised[1] = 0.6
    raised[0] = 0.7
    raised[0, 1] = 0.0
    assert int(usable_pattern(jnp.asarray(raised))) == oracle_pattern(np.array([False, True] + [False] * 4)) == 47
