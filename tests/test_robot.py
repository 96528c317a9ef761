"""The MJCF model against the original robot's facts, and config validation."""

import math

import mujoco
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.control_step import STEPS_PER_SECOND
from hte_jax.sim.robot import FOOT_RADIUS, FOOT_REACH, WALL_BIT, RobotConfig, load_robot, mj_model


@pytest.fixture(scope="module")
def model():
    return mj_model(RobotConfig())


def test_sizes_and_mass(model):
    assert (model.nq, model.nv, model.nu) == (25, 24, 18)
    assert model.body_mass.sum() == pytest.approx(0.6791 + 6 * (0.0199 + 0.1872 + 0.0911), rel=1e-6)
    assert model.opt.timestep == pytest.approx(0.01)
    assert STEPS_PER_SECOND * RobotConfig().control_dt == pytest.approx(1.0)  # the control step's one definition


def test_hip_placements_and_axes(model):
    hips = {0: (0.093, -0.053, -0.7864), 1: (0.0, -0.075, -1.5708), 3: (-0.093, 0.053, 2.3516)}
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    base = data.xpos[model.body("base_link").id]
    for leg, (x, y, yaw) in hips.items():
        body = model.body(f"leg_{leg}_1").id
        np.testing.assert_allclose(data.xpos[body] - base, [x, y, 0.0], atol=1e-9)
        heading = data.xmat[body].reshape(3, 3)[:, 0]  # hip frame x points outwards
        assert math.atan2(heading[1], heading[0]) == pytest.approx(yaw, abs=1e-6)
    for leg in range(6):
        np.testing.assert_allclose(model.joint(f"body_leg_{leg}").axis, [0, 0, 1])
        np.testing.assert_allclose(model.joint(f"leg_{leg}_1_2").axis, [0, 1, 0])
        np.testing.assert_allclose(model.joint(f"leg_{leg}_2_3").axis, [0, -1, 0])
    hinge = model.jnt_type == mujoco.mjtJoint.mjJNT_HINGE
    np.testing.assert_allclose(model.jnt_range[hinge], np.tile([-np.pi / 2, np.pi / 2], (18, 1)), atol=1e-6)


def test_neutral_pose_geometry(model):
    # At q = 0 the foot bottoms are 0.136 m below the base and FOOT_REACH (0.176 m) from the hip.
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    base_z = data.xpos[model.body("base_link").id][2]
    for leg in range(6):
        foot = data.geom_xpos[model.geom(f"foot_{leg}").id]
        hip = data.xpos[model.body(f"leg_{leg}_1").id]
        assert base_z - (foot[2] - FOOT_RADIUS) == pytest.approx(0.136, abs=1e-4)
        assert np.linalg.norm((foot - hip)[:2]) == pytest.approx(FOOT_REACH, abs=1e-4) == pytest.approx(0.176)


def test_only_feet_touch_the_floor(model):
    floor = model.geom("floor")
    touching = [
        model.geom(g).name
        for g in range(model.ngeom)
        if g != floor.id
        and (model.geom_contype[g] & floor.conaffinity[0] or floor.contype[0] & model.geom_conaffinity[g])
    ]
    assert sorted(touching) == [f"foot_{i}" for i in range(6)]
    assert all(model.geom(f"foot_{i}").size[0] == 0.025 for i in range(6))


def test_servo_actuators(model):
    assert np.all(model.actuator_gainprm[:, 0] == 1.0)  # kv
    assert np.all(model.actuator_biasprm[:, 2] == -1.0)
    np.testing.assert_allclose(model.actuator_forcerange, np.tile([-4.0, 4.0], (18, 1)))
    np.testing.assert_allclose(model.actuator_ctrlrange, np.tile([-5.0, 5.0], (18, 1)))
    assert list(model.actuator_trnid[:, 0]) == list(range(1, 19))  # leg-major joint order


def _contacts_with_wall(config):
    model = mj_model(config)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    wall = model.geom("wall_0").id
    pairs = {tuple(sorted((c.geom1, c.geom2))) for c in data.contact[: data.ncon]}
    return {model.geom(g1 if g2 == wall else g2).name for g1, g2 in pairs if wall in (g1, g2)}


def test_wall_contact_modes():
    post = ((-0.05, -0.05, 0.05, 0.05),)  # a post straight through the body, clear of the feet
    assert "base_link" in _contacts_with_wall(RobotConfig(walls=post, wall_contact="links"))
    assert _contacts_with_wall(RobotConfig(walls=post, wall_contact="feet")) == set()
    assert _contacts_with_wall(RobotConfig(walls=post, wall_contact="bumper")) == {"bumper"}
    # The bumper reaches 0.25 m from the body's centre: a box 0.2 m away touches it, one 0.3 m away does not.
    near = ((0.2, -0.5, 0.4, 0.5),)
    far = ((0.3, -0.5, 0.5, 0.5),)
    assert _contacts_with_wall(RobotConfig(walls=near)) == {"bumper"}
    assert _contacts_with_wall(RobotConfig(walls=far)) == set()
    # The bumper is massless and meets nothing but walls.
    plain, bumped = mj_model(RobotConfig()), mj_model(RobotConfig(walls=far))
    assert bumped.body_mass.sum() == pytest.approx(plain.body_mass.sum())
    bumper = bumped.geom("bumper")
    assert bumper.contype[0] == WALL_BIT and bumper.conaffinity[0] == 0
    assert bumped.geom("wall_0").conaffinity[0] == WALL_BIT


def test_config_changes_compile_options():
    model = mj_model(RobotConfig(timestep=0.005, solver_iterations=7, joint_limits=False, armature=0.02))
    assert model.opt.timestep == pytest.approx(0.005)
    assert model.opt.iterations == 7
    assert not model.jnt_limited[1:].any()
    assert np.all(model.dof_armature[6:] == 0.02)
    assert RobotConfig(timestep=0.005).substeps == 2


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"timestep": 0.003}, "whole multiple"),
        ({"timestep": -0.01}, "timestep"),
        ({"solver_iterations": 0}, "solver_iterations"),
        ({"servo_gain": float("nan")}, "servo_gain"),
        ({"armature": -1.0}, "armature"),
        ({"walls": ((1.0, 0.0, 0.5, 1.0),)}, "wall"),
        ({"wall_contact": "legs"}, "wall_contact"),
        ({"bumper_radius": 0.0}, "bumper_radius"),
    ],
)
def test_bad_config_is_a_clear_error(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        RobotConfig(**kwargs)


def test_load_robot_info():
    robot = load_robot()
    assert robot.info.joint_qpos == tuple(range(7, 25))
    assert len(robot.info.foot_geoms) == 6


def test_importing_the_physics_prints_nothing():
    """MJX's "Failed to import warp" notice (warp-lang is optional and unused) never reaches the user."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", "import hte_jax.sim.rollout, hte_jax.sim.robot"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "warp" not in proc.stdout + proc.stderr and proc.stdout == "", proc.stdout
