"""Each damage model tested for what it means, end to end in the simulation (hte_jax.sim.damage): a removed leg
weighs nothing and its foot never bears the robot, a shortened leg stands its hip lower, a weak leg cannot hold
the load an intact one holds, a slippery floor lets the feet slide further under the same gait; raised and locked
give the leg-mask path's bits; one compiled program serves a batch that mixes damages."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.sim import damage as dmg
from hte_jax.sim.env import InvalidReason
from hte_jax.sim.robot import NUM_LEGS, mj_model
from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state

LEG = 0


def _mask(*legs):
    return dmg.damage_mask(legs)


def _stack(*damages: dmg.Damage) -> dmg.Damage:
    return jax.tree.map(lambda *x: jnp.stack(x), *damages)


# One batch, one compiled program (and one for its standing start): every scenario below is a row.
ALL = np.ones(NUM_LEGS, bool)
RIGHT = _mask(0, 1, 2)
SCENARIOS = {  # name: (damage, walks)
    "all removed": (dmg.make_damage(ALL, "removed"), False),
    "all locked": (dmg.make_damage(ALL, "locked"), False),
    "leg removed, walking": (dmg.make_damage(_mask(LEG), "removed"), True),
    "intact": (dmg.make_damage(_mask(), "weak"), False),
    "right side shortened": (dmg.make_damage(RIGHT, "shortened", fraction=0.5), False),
    "all weak": (dmg.make_damage(ALL, "weak", fraction=0.05), False),
    "intact, walking": (dmg.make_damage(_mask()), True),
    "slippery, walking": (dmg.make_damage(_mask(), friction=0.05), True),
}
ROW = {name: i for i, name in enumerate(SCENARIOS)}
SPEC = RolloutSpec(num_steps=200, pose_steps=(0, 100, 200), record_feet=True)


@pytest.fixture(scope="module")
def scenarios(robot):
    damages = _stack(*(damage for damage, _ in SCENARIOS.values()))
    gait = jax.random.uniform(jax.random.key(3), (36,))
    params = jnp.stack([gait if walks else jnp.zeros(36) for _, walks in SCENARIOS.values()])
    start = standing_state(robot, damages)
    return start, rollout(robot, params, damages, start, SPEC), damages, params


def test_removed_leg_takes_its_mass_and_torque(robot):
    native = mj_model(robot.config)
    removed = dmg.edited_model(robot.model, dmg.make_damage(_mask(LEG), "removed"), robot.info)
    leg_mass = native.body_mass[list(robot.info.leg_bodies[LEG])].sum()
    assert float(removed.body_mass.sum()) == pytest.approx(native.body_mass.sum() - leg_mass, rel=1e-6)
    assert (np.asarray(removed.actuator_forcerange)[list(robot.info.leg_actuators[LEG])] == 0).all()


@pytest.mark.slow
def test_removed_legs_touch_nothing(scenarios):
    _, result, _, _ = scenarios
    # No foot left to stand on: every leg removed, the robot falls through the floor; every leg locked, it stands.
    fell = int(result.invalid_reason[ROW["all removed"]])
    assert fell & (InvalidReason.HEIGHT | InvalidReason.BODY_ON_FLOOR), fell
    assert bool(result.valid[ROW["all locked"]])
    walking = ROW["leg removed, walking"]
    assert bool(result.valid[walking])
    contacts = np.asarray(result.foot_contacts[walking])
    assert not contacts[:, LEG].any() and contacts[:, [1, 2, 3, 4, 5]].any(axis=0).all()


def _hip_heights(qpos: np.ndarray) -> np.ndarray:
    model = mj_model()
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    return np.asarray([data.xpos[model.body(f"leg_{leg}_1").id, 2] for leg in range(NUM_LEGS)])


@pytest.mark.slow
def test_shortened_legs_stand_their_hips_lower(scenarios):
    start, _, _, _ = scenarios
    intact = _hip_heights(np.asarray(start.qpos[ROW["intact"]], np.float64))
    short = _hip_heights(np.asarray(start.qpos[ROW["right side shortened"]], np.float64))
    right, left = RIGHT, ~RIGHT
    assert np.ptp(intact) < 5e-3  # level
    # Tibiae at half their 0.11 m below the knee: the right side's hips stand lower than the left side's (by
    # 1.4 cm, measured: the body tilts onto the short side and the left legs' servos give under the load).
    assert short[right].max() < short[left].min() - 0.01, short


@pytest.mark.slow
def test_weak_legs_cannot_hold_the_load_intact_ones_hold(scenarios):
    start, result, _, _ = scenarios
    heights = np.asarray(result.base_pos[:, -1, 2])
    intact, weak = ROW["intact"], ROW["all weak"]
    assert abs(heights[intact] - float(start.qpos[intact, 2])) < 2e-3  # intact servos hold the standing pose
    assert heights[weak] < heights[intact] - 5e-3 or not bool(result.valid[weak])  # 0.2 N m servos let it sink


@pytest.mark.slow
def test_slippery_floor_lets_the_feet_slide_further_under_the_same_gait(scenarios):
    _, result, _, _ = scenarios
    rows = [ROW["intact, walking"], ROW["slippery, walking"]]
    feet, down = np.asarray(result.foot_pos)[rows], np.asarray(result.foot_contacts)[rows]
    planted = down[:, 1:] & down[:, :-1]  # (2, T - 1, 6) a foot down on two steps running
    slip = (np.linalg.norm(np.diff(feet[..., :2], axis=1), axis=-1) * planted).sum(axis=(1, 2))
    assert slip[1] > 2 * slip[0], slip


@pytest.mark.slow
def test_one_program_serves_every_mix_of_damages(robot, scenarios):
    start, _, damages, params = scenarios
    compiled = rollout._cache_size()
    shuffled = jax.tree.map(lambda x: x[::-1], damages)
    result = rollout(robot, params, shuffled, start, SPEC)
    assert rollout._cache_size() == compiled and result.valid.shape == (len(SCENARIOS),)


def test_bad_damage_values_are_one_line_errors():
    with pytest.raises(ConfigError, match="fraction must be in"):
        dmg.make_damage(_mask(0), "shortened", fraction=0.0)
    with pytest.raises(ConfigError, match="fraction must be in"):
        dmg.make_damage(_mask(0), "weak", fraction=1.5)
    with pytest.raises(ConfigError, match="takes no fraction"):
        dmg.make_damage(_mask(0), "removed", fraction=0.5)
    with pytest.raises(ConfigError, match="unknown damage model"):
        dmg.make_damage(_mask(0), "melted")
    with pytest.raises(ConfigError, match="friction scale must be"):
        dmg.make_damage(_mask(0), friction=0.0)
    with pytest.raises(ConfigError, match="leg index"):
        dmg.damage_mask([6])
