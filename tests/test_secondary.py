"""HTE's secondary-descriptor selection (candidate patterns, error measure, UCB; docs/original_code.md
§7.3) and the leg sensing of ours."""

import jax.numpy as jnp
import numpy as np

from hte_jax.online.gp import HTE_KERNEL, add_observation, empty_gp, posterior
from hte_jax.online.secondary import acquisition, allowed_patterns, oracle_pattern, relative_error, ucb_beta
from hte_jax.online.sensing import CONTACT_EVIDENCE, CONTACT_RATIO, unusable_legs, usable_pattern
from hte_jax.sim.damage import paper_damage_masks

# the 28 patterns the original excludes (docs/original_code.md §7.3)
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
