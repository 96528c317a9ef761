"""Controller signals and joint targets against the NumPy reference (acceptance 1)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.sim import controller
from tests import reference_controller as ref


def test_signal_matches_reference_on_random_parameters():
    rng = np.random.default_rng(0)
    params = rng.uniform(size=(200, 3)).astype(np.float32)
    ours = np.asarray(jax.vmap(controller.signal_table)(*jnp.asarray(params).T))
    for (a, p, d), got in zip(params.astype(np.float64), ours):
        np.testing.assert_allclose(got, ref.signal(a, p, d), atol=2e-6)


@pytest.mark.parametrize(
    "a,p,d",
    [(1.0, 0.0, 0.5), (0.5, 0.25, 0.25), (1.0, 0.99, 1.0), (0.7, 1.0, 0.0), (1.0, 0.29, 0.29), (0.3, 0.07, 0.71)],
)
def test_signal_matches_reference_on_boundary_parameters(a, p, d):
    got = np.asarray(controller.signal_table(jnp.float32(a), jnp.float32(p), jnp.float32(d)))
    np.testing.assert_allclose(got, ref.signal(a, p, d), atol=2e-6)


def test_signal_shape_facts():
    # duty 0.5, no phase: the first half is high; smoothing keeps values within +-a and
    # the centre of each half at exactly +-a (more than 10 samples from an edge).
    s = np.asarray(controller.signal_table(jnp.float32(0.8), jnp.float32(0.0), jnp.float32(0.5)))
    assert s.shape == (100,)
    assert np.all(np.abs(s) <= 0.8 + 1e-6)
    np.testing.assert_allclose(s[25], 0.8, atol=1e-6)
    np.testing.assert_allclose(s[75], -0.8, atol=1e-6)
    # phase 0.1 shifts the table left by 10 samples
    shifted = np.asarray(controller.signal_table(jnp.float32(0.8), jnp.float32(0.1), jnp.float32(0.5)))
    np.testing.assert_allclose(shifted, np.roll(s, -10), atol=1e-7)


def test_target_table_matches_reference():
    rng = np.random.default_rng(1)
    for params in rng.uniform(size=(5, 36)).astype(np.float32):
        got = np.asarray(controller.target_table(jnp.asarray(params)))
        assert got.shape == (100, 18)
        np.testing.assert_allclose(got, ref.joint_targets(params.astype(np.float64)), atol=2e-6)


def test_commanded_travel_matches_reference():
    rng = np.random.default_rng(2)
    params = rng.uniform(size=(4, 36)).astype(np.float32)
    got = np.asarray(controller.commanded_travel(jnp.asarray(params)))
    for row, p in zip(got, params):
        table = ref.joint_targets(p.astype(np.float64))  # (100, 18)
        per_joint = np.abs(np.diff(np.vstack([table, table[:1]]), axis=0)).sum(axis=0)
        np.testing.assert_allclose(row, per_joint.reshape(6, 3).sum(-1), rtol=1e-5, atol=1e-5)
    assert np.asarray(controller.commanded_travel(jnp.zeros(36))).tolist() == [0.0] * 6


def test_zero_parameters_give_the_neutral_pose():
    assert np.all(np.asarray(controller.target_table(jnp.zeros(36))) == 0.0)


def test_target_ranges():
    table = np.asarray(controller.target_table(jnp.ones(36) * jnp.asarray([1, 0, 0.5, 1, 0.5, 0.5] * 6)))
    assert np.abs(table[:, 0::3]).max() == pytest.approx(np.pi / 8, rel=1e-6)
    assert np.abs(table[:, 1::3]).max() == pytest.approx(np.pi / 4, rel=1e-6)
    np.testing.assert_array_equal(table[:, 1::3], table[:, 2::3])  # tibia kept vertical


def test_leg_primitive_embeds_one_leg():
    leg_params = jnp.arange(1, 7, dtype=jnp.float32) / 10
    full = np.asarray(controller.leg_primitive(leg_params, jnp.int32(4))).reshape(6, 6)
    np.testing.assert_allclose(full[4], np.asarray(leg_params))
    assert np.all(np.delete(full, 4, axis=0) == 0)
    # the other legs stay at the neutral pose
    table = np.asarray(controller.target_table(jnp.asarray(full.reshape(36))))
    assert np.all(np.delete(table.reshape(100, 6, 3), 4, axis=1) == 0)


def test_servo_command_gain_and_clip():
    q = jnp.zeros(18)
    small = jnp.full(18, 0.01)
    np.testing.assert_allclose(controller.servo_command(small, q, 5.0), 0.01 / (np.pi * 0.01), rtol=1e-6)
    big = jnp.full(18, -1.0)
    np.testing.assert_allclose(controller.servo_command(big, q, 5.0), -5.0)
