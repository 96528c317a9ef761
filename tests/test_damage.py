"""Damage masks, names, the command lines' spelling of a damage (`parse_damages`) and the blocked-in-the-air pose."""

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


@pytest.mark.parametrize("name,legs", [("none", []), ("leg3", [3]), ("legs1+4", [1, 4]), (6, [1, 4]), (-1, []), (0, [0]),
                                       ("legs0+2+4", [0, 2, 4])])
def test_parse_damage(name, legs):
    np.testing.assert_array_equal(np.flatnonzero(damage.parse_damage(name)), legs)


@pytest.mark.parametrize("bad", ["leg6", "legs5+2", "legs2+2", "legs1+3+2", "legs0+6+2", "legs", "", 7, -2])
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


# spelling -> [(canonical label, legs, model, fraction, friction)] under the run's damage model "raised"
SPELLINGS = {
    "leg0:removed": [("leg0:removed", [0], "removed", 1.0, 1.0)],
    " leg2 : shortened = 0.50 : friction=0.6 ": [("leg2:shortened=0.5:friction=0.6", [2], "shortened", 0.5, 0.6)],
    "leg2:friction=0.6:shortened=0.5": [("leg2:shortened=0.5:friction=0.6", [2], "shortened", 0.5, 0.6)],
    "none:friction=0.5": [("none:friction=0.5", [], "raised", 1.0, 0.5)],
    "6,-1,leg1:raised,3:friction=1": [("legs1+4", [1, 4], "raised", 1.0, 1.0), ("none", [], "raised", 1.0, 1.0),
                                      ("leg1", [1], "raised", 1.0, 1.0), ("leg3", [3], "raised", 1.0, 1.0)],
    "legs0+2+5:weak=0.25": [("legs0+2+5:weak=0.25", [0, 2, 5], "weak", 0.25, 1.0)],
    "leg4:locked:friction=2": [("leg4:locked:friction=2", [4], "locked", 1.0, 2.0)],
}


@pytest.mark.parametrize("text", SPELLINGS)
def test_a_spelled_damage_parses_to_its_damage_and_canonical_label(text):
    parsed = damage.parse_damages(text)
    assert [(label, np.flatnonzero(d.legs).tolist(), list(damage.DAMAGE_PARTS)[int(d.model)], float(d.fraction),
             float(d.friction)) for label, d in parsed.items()] == [
        (label, legs, model, pytest.approx(fraction), pytest.approx(friction))
        for label, legs, model, fraction, friction in SPELLINGS[text]]
    for label, one in parsed.items():  # a label reads back to its damage, bit for bit
        (again, read), = damage.parse_damages(label).items()
        assert again == label and damage.damage_label(read, "raised") == label
        for field in ("legs", "model", "fraction", "friction"):
            assert getattr(read, field).dtype == getattr(one, field).dtype
            np.testing.assert_array_equal(getattr(read, field), getattr(one, field))


def test_all_is_the_papers_seven_under_the_runs_model_or_the_items():
    assert list(damage.parse_damages("all")) == list(damage.PAPER_DAMAGES)
    locked = damage.parse_damages("all", "locked")
    assert list(locked) == list(damage.PAPER_DAMAGES)  # the run's model is not named in the labels
    assert {int(d.model) for d in locked.values()} == {list(damage.DAMAGE_PARTS).index("locked")}
    assert list(damage.parse_damages("leg1:raised,leg1", "locked")) == ["leg1:raised", "leg1"]
    spelled = damage.parse_damages("all:shortened=0.5:friction=0.8,none")
    assert list(spelled) == [f"{name}:shortened=0.5:friction=0.8" for name in damage.PAPER_DAMAGES] + ["none"]
    np.testing.assert_array_equal(np.stack([d.legs for d in spelled.values()])[:7], damage.paper_damage_masks())


def test_suite_is_the_held_out_conditions_beside_the_papers_seven():
    suite = damage.parse_damages("suite", "removed")
    assert list(suite) == list(damage.DAMAGE_SUITE) and not set(suite) & set(damage.PAPER_DAMAGES)
    parts = list(damage.DAMAGE_PARTS)
    pairs = [suite[name] for name in ("legs0+3", "legs2+5", "legs0+5", "legs1+2")]
    assert [np.flatnonzero(d.legs).tolist() for d in pairs] == [[0, 3], [2, 5], [0, 5], [1, 2]]
    assert {int(d.model) for d in pairs} == {parts.index("removed")}  # the run's damage model
    short, weak = suite["leg0:shortened=0.5"], suite["leg1:weak=0.5"]
    assert (int(short.model), float(short.fraction)) == (parts.index("shortened"), 0.5)
    assert (int(weak.model), float(weak.fraction), np.flatnonzero(weak.legs).tolist()) == (parts.index("weak"), 0.5, [1])
    slippery = suite["none:friction=0.5"]
    assert not slippery.legs.any() and float(slippery.friction) == 0.5
    assert list(damage.parse_damages("all,suite")) == [*damage.PAPER_DAMAGES, *damage.DAMAGE_SUITE]


@pytest.mark.parametrize("text, fragment", [
    ("leg2:shortened=0", "fraction must be in (0, 1], got 0"),
    ("leg2:weak=1.5", "fraction must be in (0, 1], got 1.5"),
    ("leg2:shortened=half", "fraction must be a number"),
    ("leg2:shortened", "needs a fraction in (0, 1]"),
    ("leg0:removed=0.5", "damage model 'removed' takes no fraction"),
    ("leg0:floppy", "unknown damage model 'floppy'"),
    ("leg7:removed", "unknown damage 'leg7'"),
    ("9", "unknown damage index 9"),
    ("leg0:friction=0", "friction scale must be > 0, got 0"),
    ("leg0:friction=-0.5", "friction scale must be > 0"),
    ("leg0:friction=nan", "friction must be a number"),
    ("leg0:friction", "as friction=<scale>"),
    ("leg0:friction=0.5:friction=0.6", "give friction once"),
    ("leg0:removed:locked", "names two damage models"),
    ("leg0::removed", "empty part"),
    ("none:removed", "none damages no leg"),
    ("leg1,leg1:raised", "names the damage 'leg1' twice"),
    (" , ", "give 'all' or at least one damage"),
])
def test_a_bad_spelling_is_a_one_line_config_error(text, fragment):
    with pytest.raises(ConfigError) as error:
        damage.parse_damages(text)
    assert fragment in str(error.value) and "\n" not in str(error.value)


def test_a_damage_that_says_no_more_than_its_legs_is_given_as_the_mask():
    """`mask_if_plain`: the rollout keeps a mask's program where the mask says the same."""
    plain = damage.stack_damages(damage.parse_damages("leg1,none,legs1+4", "locked").values())
    mask = damage.mask_if_plain(plain, "locked")
    assert isinstance(mask, np.ndarray) and mask.dtype == bool
    np.testing.assert_array_equal(mask, damage.damage_masks(["leg1", "none", "legs1+4"]))
    assert not damage.edits_model(mask, "locked") and damage.edits_model(plain, "locked")
    for text in ("leg1,leg2:removed", "leg1,none:friction=0.9", "leg1:raised"):
        mixed = damage.stack_damages(damage.parse_damages(text, "locked").values())
        assert damage.mask_if_plain(mixed, "locked") is mixed
    np.testing.assert_array_equal(damage.damage_legs(mixed), mixed.legs)
