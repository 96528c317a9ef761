"""Damage masks, names and the blocked-in-the-air pose."""

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.sim import damage
from hte_jax.sim.robot import RobotConfig, mj_model


def test_paper_conditions():
    masks = damage.paper_damage_masks()
    assert masks.shape == (7, 6)
    np.testing.assert_array_equal(masks[:6], np.eye(6, dtype=bool))
    np.testing.assert_array_equal(masks[6], [False, True, False, False, True, False])


@pytest.mark.parametrize("name,legs", [("none", []), ("leg3", [3]), ("legs1+4", [1, 4]), (6, [1, 4]), (-1, []), (0, [0])])
def test_parse_damage(name, legs):
    np.testing.assert_array_equal(np.flatnonzero(damage.parse_damage(name)), legs)


@pytest.mark.parametrize("bad", ["leg6", "legs5+2", "legs2+2", "", 7, -2])
def test_unknown_damage_is_a_clear_error(bad):
    with pytest.raises(ConfigError, match="unknown damage"):
        damage.parse_damage(bad)


def test_bad_leg_index():
    with pytest.raises(ConfigError, match="leg index"):
        damage.damage_mask([6])


def test_held_targets_override_only_damaged_legs():
    targets = jnp.arange(18, dtype=jnp.float32) / 100
    mask = jnp.asarray([False, True, False, False, True, False])
    out = np.asarray(damage.held_targets(targets, damage.make_damage(mask))).reshape(6, 3)
    np.testing.assert_allclose(out[[1, 4]], np.tile(damage.DAMAGED_POSE, (2, 1)), rtol=1e-6)
    np.testing.assert_allclose(out[[0, 2, 3, 5]], np.asarray(targets).reshape(6, 3)[[0, 2, 3, 5]])


def test_damaged_pose_lifts_the_foot_well_above_the_hip():
    model = mj_model(RobotConfig())
    data = mujoco.MjData(model)
    for leg in range(6):
        data.qpos[:] = model.qpos0
        data.qpos[7 + 3 * leg : 10 + 3 * leg] = damage.DAMAGED_POSE
        mujoco.mj_kinematics(model, data)
        hip = data.xpos[model.body(f"leg_{leg}_1").id]
        foot = data.geom_xpos[model.geom(f"foot_{leg}").id]
        assert foot[2] - hip[2] > 0.18  # 0.081 femur + 0.111 tibia, straight up
        # the pose is inside the joint limits
        lo, hi = model.jnt_range[model.joint(f"leg_{leg}_1_2").id]
        assert lo - 1e-6 <= damage.DAMAGED_POSE[1] <= hi + 1e-6


def test_damage_models_choose_the_damaged_pose():
    assert damage.damaged_pose("raised") == damage.DAMAGED_POSE
    assert damage.damaged_pose("locked") == (0.0, 0.0, 0.0)
    targets = jnp.full(18, 0.3, jnp.float32)
    mask = jnp.asarray([False, False, True, False, False, False])
    out = np.asarray(damage.held_targets(targets, damage.make_damage(mask, "locked"))).reshape(6, 3)
    np.testing.assert_allclose(out[2], 0.0)
    np.testing.assert_allclose(np.delete(out, 2, axis=0), 0.3)
    for model in ("removed", "shortened", "weak"):  # the leg follows the gait's targets
        assert damage.damaged_pose(model) is None
        held = damage.held_targets(targets, damage.make_damage(mask, model, xp=np), np)
        np.testing.assert_array_equal(held, np.asarray(targets))
    with pytest.raises(ConfigError, match="unknown damage model"):
        damage.damaged_pose("floppy")
    with pytest.raises(ConfigError, match="damage_model"):
        RobotConfig(damage_model="floppy")


def test_locked_leg_starts_in_the_standing_pose():
    """With the locked model, a damaged leg starts (and is held) where an intact leg stands: its
    foot as low as the others' (native kinematics of the initial state, no MJX rollout)."""
    from hte_jax.sim.robot import load_robot
    from hte_jax.sim.rollout import initial_state

    mask = jnp.asarray([False, False, True, False, False, False])
    config = RobotConfig(damage_model="locked")
    state = initial_state(load_robot(config), mask)
    np.testing.assert_allclose(np.asarray(state.qpos[13:16]), 0.0)
    model = mj_model(config)
    data = mujoco.MjData(model)
    data.qpos[:] = np.asarray(state.qpos)
    mujoco.mj_kinematics(model, data)
    feet = np.array([data.geom_xpos[model.geom(f"foot_{leg}").id][2] for leg in range(6)])
    np.testing.assert_allclose(feet, feet[0], atol=1e-6)
