"""Actions on the simulated robots in the maze: start placement, walls that stop the robot, flat
actions that are the trained controllers (hierarchical actions run end to end in test_episode and,
on a robot driven from the host, in test_executor)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.flat.store import load_flat, shipped_flat_path
from hte_jax.geometry import planar_pose, relative_pose
from hte_jax.online.arena import maze_robot, place, start_states
from hte_jax.online.action import SimulatedRobots, flat_action
from hte_jax.online.skills import flat_skills
from hte_jax.online.maze import PAPER_MAZE, Maze
from hte_jax.sim.robot import load_robot
from hte_jax.sim.env import SimState
from hte_jax.sim.rollout import standing_state

# Bit for bit: a flat action against its trained controller run directly.
pytestmark = [pytest.mark.exact_numerics, pytest.mark.slow]


def _batched(tree, batch):
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), tree)


def test_robots_start_standing_at_the_maze_start():
    damages = np.array([[False] * 6, [False] * 6, [False, True, False, False, False, False], [False, True] + [False] * 4])
    start = start_states(PAPER_MAZE, damages)  # the batch of test_episode's run: its compile is shared
    pose = np.asarray(planar_pose(start.qpos[:, :3], start.qpos[:, 3:7]))
    np.testing.assert_allclose(pose[:, :2], np.tile(PAPER_MAZE.start[:2], (4, 1)), atol=1e-6)
    np.testing.assert_allclose(np.cos(pose[:, 2]), -1.0, atol=1e-6)  # facing -x
    standing = standing_state(load_robot(), jnp.asarray(damages))
    np.testing.assert_allclose(start.qpos[:, 2], standing.qpos[:, 2], atol=1e-6)  # same height
    np.testing.assert_allclose(start.qpos[:, 7:], standing.qpos[:, 7:], atol=1e-6)  # same joints
    # turning a moving robot turns its world-frame velocity with it
    moving = standing.replace(qvel=standing.qvel.at[:, 0].set(1.0))
    turned = place(moving, jnp.asarray([[0.0, 0.0, np.pi / 2]] * 4))
    np.testing.assert_allclose(turned.qvel[:, :2], [[0.0, 1.0]] * 4, atol=1e-3)  # the settled heading is ~0


def test_place_on_the_host_agrees_with_eager_jax():
    """`place` (NumPy's arithmetic around XLA's arctangent, cosines and sines) gives, bit for bit, what its formulas
    give as eager jax operations."""
    rng = np.random.default_rng(7)
    quat = rng.normal(size=(64, 4))
    qpos = np.concatenate([rng.uniform(-1, 1, (64, 3)), quat / np.linalg.norm(quat, axis=-1, keepdims=True),
                           rng.uniform(-1, 1, (64, 18))], axis=-1).astype(np.float32)
    qvel, warm = rng.normal(size=(2, 64, 24)).astype(np.float32)
    pose = rng.uniform(-3, 3, (64, 3)).astype(np.float32)
    placed = place(SimState(qpos=qpos, qvel=qvel, qacc_warmstart=warm), pose)

    q, p = jnp.asarray(qpos), jnp.asarray(pose)
    w, x, y, z = q[:, 3], q[:, 4], q[:, 5], q[:, 6]
    turn = p[:, 2] - jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    c, s = jnp.cos(turn)[:, None], jnp.sin(turn)[:, None]
    aw, ax, ay, az = jnp.cos(turn / 2), jnp.zeros_like(turn), jnp.zeros_like(turn), jnp.sin(turn / 2)
    quat = jnp.stack([aw * w - ax * x - ay * y - az * z, aw * x + ax * w + ay * z - az * y,
                      aw * y - ax * z + ay * w + az * x, aw * z + ax * y - ay * x + az * w], axis=-1)

    def rotate(v):
        v = jnp.asarray(v)
        return jnp.concatenate([c * v[:, :1] - s * v[:, 1:2], s * v[:, :1] + c * v[:, 1:2], v[:, 2:]], axis=-1)

    expected = (jnp.concatenate([p[:, :2], q[:, 2:3], quat, q[:, 7:]], axis=-1), rotate(qvel), rotate(warm))
    for got, want in zip((placed.qpos, placed.qvel, placed.qacc_warmstart), expected):
        assert np.asarray(got).tobytes() == np.asarray(want).tobytes()


def _forward_controller():
    """The shipped Flat-2D elite that walks furthest straight ahead, and its stored displacement."""
    flat, _ = load_flat(shipped_flat_path("2d"))
    rep = flat[0]
    xy = np.asarray(rep.descriptors) * 3.0 - 1.5
    score = np.where(np.asarray(rep.filled) & (np.abs(xy[:, 1]) < 0.1), xy[:, 0], -np.inf)
    best = int(np.argmax(score))
    return rep, best, xy[best]


def test_flat_action_is_the_trained_controller_and_walls_stop_it():
    rep, best, stored = _forward_controller()
    assert stored[0] > 0.6
    skills = flat_skills(rep, 1.5)
    index = int(np.flatnonzero(np.asarray(skills.actions.slots) == best)[0])
    # A wall 0.45 m ahead of robot 0; robot 1 faces away from it, into open space.
    wall_x = 0.45
    walled = Maze(obstacles=((wall_x, -1.0, wall_x + 0.2, 1.0),), bounds=(-5.0, -5.0, 5.0, 5.0), start=(0.0, 0.0, 0.0))
    standing = place(_batched(standing_state(load_robot()), 2), jnp.asarray([[0.0, 0.0, 0.0], [0.0, 0.0, np.pi]]))
    controllers = skills.genotypes[jnp.asarray([index, index])]
    result = flat_action(SimulatedRobots(maze_robot(walled), jnp.zeros((2, 6), bool)), standing, controllers)
    assert bool(result.valid.all())
    # In the open, the 3 s part reproduces the stored descriptor (in the robot's start frame).
    start_pose = jnp.asarray([0.0, 0.0, np.pi])
    after_skill = np.asarray(relative_pose(start_pose, result.poses[1, 2]))
    np.testing.assert_allclose(after_skill[:2], stored, atol=0.03)
    settle = relative_pose(result.poses[:, 2], result.poses[:, 3])
    assert float(jnp.linalg.norm(settle[1, :2])) < 0.1  # the neutral second only settles the robot
    np.testing.assert_allclose(np.asarray(result.displacement[1]), np.asarray(relative_pose(start_pose, result.poses[1, 3])),
                               atol=1e-5)
    # Towards the wall, the robot's bumper (radius 0.25) stops it short of the wall.
    x_reached = float(np.max(np.asarray(result.poses[0, :, 0])))
    assert x_reached < wall_x - walled.robot_radius + 0.03
    assert abs(float(result.poses[1, 2, 0])) > wall_x  # unblocked, it walks further than that
    # Recording the states every 25 control steps changes nothing; every 4th state starts a second.
    recorded = flat_action(SimulatedRobots(maze_robot(walled), jnp.zeros((2, 6), bool), record_every=25), standing,
                           controllers)
    assert result.qpos is None and recorded.qpos.shape == (2, 16, 25)
    np.testing.assert_array_equal(recorded.poses, result.poses)
    np.testing.assert_array_equal(recorded.state.qpos, result.state.qpos)
    np.testing.assert_array_equal(recorded.qpos[:, 0], standing.qpos)
    np.testing.assert_array_equal(recorded.qpos[:, 4::4, :2], result.poses[:, :3, :2])
