"""Episodes on a robot driven through an executor: native MuJoCo does what the MJX robot does, an
invalid robot is detected and ends HBR and flat episodes with its reason (the episode that reaches
the goal is docs/extending.md's example 4, run by test_extending)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.flat.store import load_flat, shipped_flat_path
from hte_jax.hbr.hierarchy import select_middle
from hte_jax.geometry import compose_pose, planar_pose
from hte_jax.hbr.store import load_hbr
from hte_jax.online.arena import maze_robot
from hte_jax.online.action import ONLINE_LIMITS, SECONDS_PER_ACTION
from hte_jax.online.episode import AdaptationConfig
from hte_jax.online.external import MujocoExecutor, Seconds, run_episode
from hte_jax.online.skills import flat_skills, hbr_skills
from hte_jax.online.maze import PAPER_MAZE
from hte_jax.online.mcts import PlannerConfig
from hte_jax.online.secondary import oracle_pattern
from hte_jax.sim.damage import parse_damage
from hte_jax.sim.robot import NUM_LEGS, RobotConfig
from hte_jax.sim.env import InvalidReason
from hte_jax.sim.rollout import RolloutSpec, rollout

LEG1 = parse_damage("leg1")
# docs/extending.md example 4's settings: with its skills, the programs compiled here are the
# example's (the session's persistent compilation cache holds them once).
CONFIG = AdaptationConfig(max_actions=35, planner=PlannerConfig(iterations=200, roots=2))


@pytest.fixture(scope="module")
def hbr():
    """The shipped HBR and its top task."""
    return load_hbr()[:2]


@pytest.fixture(scope="module")
def native():
    """The leg-1-damaged robot in native MuJoCo, settled at the maze's start."""
    return MujocoExecutor.in_maze(PAPER_MAZE, LEG1)


@pytest.mark.slow
def test_native_mujoco_walks_as_the_mjx_robot_does(hbr, native):
    """The same middle elite (the damage's own pattern, 0.2 m forward) for 3 s and the neutral second,
    from the same state: poses within 1 cm and 1 degree after every second, contacts within 0.05."""
    hbr, _ = hbr
    pattern = jnp.asarray([oracle_pattern(LEG1)], jnp.int32)
    index, found = select_middle(hbr, jnp.asarray([[0.7, 0.5, 0.5]]), pattern)
    assert bool(found[0])
    params = np.asarray(hbr.middle_params[index[0]])
    segments = np.stack([params] * 3 + [np.zeros_like(params)])  # (4, 36), an action's seconds
    start = native.state()
    batched = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32)[None], start)
    spec = RolloutSpec(num_steps=400, pose_steps=(100, 200, 300, 400), limits=ONLINE_LIMITS, record_joints=True)
    simulated = rollout(maze_robot(PAPER_MAZE), jnp.asarray(segments)[None], jnp.asarray(LEG1)[None], batched, spec)
    assert bool(simulated.valid[0])
    want_poses = np.asarray(planar_pose(simulated.base_pos[0], simulated.base_quat[0]))  # (4, 3)
    want_contacts = np.asarray(simulated.foot_contacts[0]).reshape(4, 100, NUM_LEGS).mean(axis=1)
    angles = np.concatenate([np.asarray(simulated.joint_pos[0]), np.asarray(simulated.final_state.qpos[0, 7:])[None]])
    want_travel = np.abs(np.diff(angles, axis=0)).reshape(4, 100, NUM_LEGS, 3).sum(axis=(1, 3))  # (4, 6)

    before = native.pose()
    seconds = native.run(segments)
    assert seconds.invalid_reason == 0 and seconds.poses.shape == (4, 3) and seconds.contacts.shape == (4, NUM_LEGS)
    assert np.linalg.norm(seconds.poses[2, :2] - before[:2]) > 0.3  # it walked: the comparison means something
    np.testing.assert_allclose(seconds.poses[:, :2], want_poses[:, :2], atol=0.01)
    np.testing.assert_allclose(np.rad2deg(seconds.poses[:, 2] - want_poses[:, 2]), 0.0, atol=1.0)
    np.testing.assert_allclose(seconds.contacts, want_contacts, atol=0.05)
    np.testing.assert_allclose(seconds.leg_travel, want_travel, atol=0.05)
    assert (seconds.leg_travel[:3, 1] < 0.1 * seconds.leg_travel[:3, 0]).all()  # leg 1's joints hold their pose
    assert (seconds.contacts[:3, 1] == 0).all() and (seconds.contacts[:3, [0, 2, 3, 4, 5]] > 0.2).all()  # leg 1 is up
    np.testing.assert_array_equal(native.pose(), seconds.poses[-1])
    native._set(start.qpos, start.qvel, start.qacc_warmstart)  # the next test starts from the start again


def test_native_mujoco_stops_a_flipped_robot_where_it_was(native):
    """Upside down, the first step is invalid (flipped): the robot is put back and the seconds after
    repeat its pose with no contact."""
    start = native.state()
    upside_down = start.qpos.copy()
    upside_down[2], upside_down[3:7] = 0.3, [0.0, 1.0, 0.0, 0.0]  # turned by pi about x
    native._set(upside_down, np.zeros_like(start.qvel), np.zeros_like(start.qvel))
    pose = native.pose()
    seconds = native.run(np.full((2, 36), 0.5, np.float32))
    assert seconds.invalid_reason & InvalidReason.FLIPPED
    np.testing.assert_array_equal(seconds.poses, [pose, pose])
    assert (seconds.contacts == 0).all()
    np.testing.assert_array_equal(native.state().qpos, upside_down)
    native._set(start.qpos, start.qvel, start.qacc_warmstart)


class FlippingRobot:
    """A fake robot: each second it steps 0.1 m straight ahead, except its `flip_at`-th second (from 1),
    in which it flips and stops. It keeps every command it was sent."""

    def __init__(self, flip_at: int):
        self.at = np.asarray(PAPER_MAZE.start, np.float32)
        self.flip_at, self.elapsed, self.commands = flip_at, 0, []

    def pose(self):
        return self.at.copy()

    def run(self, params):
        self.commands.append(np.asarray(params))
        poses, reason = [], 0
        for _ in params:
            if not reason:
                self.elapsed += 1
                if self.elapsed == self.flip_at:
                    reason = int(InvalidReason.FLIPPED)
                else:
                    self.at = np.asarray(compose_pose(self.at, jnp.asarray([0.1, 0.0, 0.0])), np.float32)
            poses.append(self.at.copy())
        return Seconds(poses=np.stack(poses), contacts=np.zeros((len(params), NUM_LEGS), np.float32),
                       invalid_reason=reason)


def _check_flipped(episode, robot, actions):
    """The episode ended broken (flipped) after `actions` actions; its records are the robot's reports."""
    assert episode.sim is None
    assert int(episode.taken[0]) == actions and bool(episode.broken[0]) and not bool(episode.reached[0])
    assert int(episode.reason[0]) == InvalidReason.FLIPPED
    assert bool(episode.done[0])
    track = np.asarray(episode.trajectory[0])
    walked = robot.flip_at - 1  # seconds the robot stepped forward before it flipped
    np.testing.assert_allclose(np.linalg.norm(track[-1, :2] - track[0, :2]), 0.1 * walked, atol=1e-5)
    np.testing.assert_allclose(np.asarray(episode.pose[0]), robot.pose())
    observed = np.asarray(episode.history.observed[0, actions - 1])
    start = SECONDS_PER_ACTION * (actions - 1)
    np.testing.assert_allclose(observed[0], np.linalg.norm(track[-1, :2] - track[start, :2]), atol=1e-5)


@pytest.mark.slow
def test_a_robot_that_flips_ends_an_hbr_episode(hbr):
    """Flipping in the second step of the second action: that action's third step and neutral second
    are never sent, and the episode ends broken with the robot's reason."""
    hbr, task = hbr
    skills = hbr_skills(hbr, task)
    robot = FlippingRobot(flip_at=SECONDS_PER_ACTION + 2)
    episode = run_episode(PAPER_MAZE, CONFIG, skills, robot, "hte", jax.random.PRNGKey(1), LEG1)
    assert [c.shape for c in robot.commands] == [(1, 36)] * (SECONDS_PER_ACTION + 2)
    neutral = robot.commands[3]
    assert (neutral == 0).all()
    for command in robot.commands[:3] + robot.commands[4:]:  # each step ran one of the HBR's middle elites
        assert np.isclose(np.asarray(hbr.middle_params), command).all(axis=1).any()
    _check_flipped(episode, robot, actions=2)
    patterns = np.asarray(episode.history.patterns[0])
    assert (patterns[0] >= 0).all() and (patterns[1, :2] >= 0).all() and patterns[1, 2] == -1  # step 3 never ran


@pytest.mark.slow
def test_a_robot_that_flips_ends_a_flat_episode():
    """A flat skill goes to the robot as one command of 4 seconds (the controller 3 times, then the
    neutral one); flipping in its second second ends the episode."""
    flat, _ = load_flat(shipped_flat_path("2d"))
    skills = flat_skills(flat[0], flat.task.extent)
    robot = FlippingRobot(flip_at=2)
    episode = run_episode(PAPER_MAZE, CONFIG, skills, robot, "2d-rte", jax.random.PRNGKey(2))
    assert len(robot.commands) == 1 and robot.commands[0].shape == (4, 36)
    controller = np.asarray(skills.genotypes[int(episode.history.action[0, 0])])
    np.testing.assert_array_equal(robot.commands[0], np.stack([controller] * 3 + [np.zeros(36)]))
    _check_flipped(episode, robot, actions=1)


def test_run_episode_refuses_a_variant_its_repertoire_cannot_run():
    flat, _ = load_flat(shipped_flat_path("2d"))
    robot = FlippingRobot(flip_at=1)
    with pytest.raises(ConfigError, match="needs an HBR"):
        run_episode(PAPER_MAZE, CONFIG, flat_skills(flat[0], flat.task.extent), robot, "hte")
    assert robot.commands == []


def test_native_mujoco_runs_the_tilt_reflex_as_the_rollout_does():
    """With `RobotConfig.reflex_tilt`, a robot started 15 degrees tilted holds the neutral pose for the
    rest of that second, then walks the next: the same as the robot without the reflex sent the
    all-zero controller for that second (the rollout's own test: test_rollout)."""
    def tilted(executor):
        start = executor.state()
        qpos = start.qpos.copy()
        half = np.deg2rad(15.0) / 2
        qpos[2] += 0.05
        qpos[3:7] = [np.cos(half), np.sin(half), 0.0, 0.0]
        executor._set(qpos, np.zeros_like(start.qvel), np.zeros_like(start.qvel))
        return executor

    base = RobotConfig()
    walk = np.stack([np.full(36, 0.5, np.float32)] * 2)  # (2, 36): two seconds of one gait
    reflexive = tilted(MujocoExecutor.in_maze(PAPER_MAZE, np.zeros(NUM_LEGS, bool),
                                              dataclasses.replace(base, reflex_tilt=0.1)))
    plain = tilted(MujocoExecutor.in_maze(PAPER_MAZE, np.zeros(NUM_LEGS, bool), base))
    np.testing.assert_array_equal(reflexive.state().qpos, plain.state().qpos)
    fired = reflexive.run(walk)
    reference = plain.run(walk * np.array([[0.0], [1.0]], np.float32))
    assert fired.invalid_reason == 0
    np.testing.assert_array_equal(fired.poses, reference.poses)
    np.testing.assert_array_equal(reflexive.state().qpos, plain.state().qpos)
    assert np.abs(fired.leg_travel[1]).sum() > np.abs(fired.leg_travel[0]).sum()  # the gait came back
    free = tilted(MujocoExecutor.in_maze(PAPER_MAZE, np.zeros(NUM_LEGS, bool), base))
    free.run(walk)
    assert np.abs(free.state().qpos - reflexive.state().qpos).max() > 0.01  # the reflex changed the walk
    # reflex_release: the gait resumes within the first second, once the robot is back upright
    releasing = tilted(MujocoExecutor.in_maze(PAPER_MAZE, np.zeros(NUM_LEGS, bool),
                                              dataclasses.replace(base, reflex_tilt=0.1, reflex_release=0.05)))
    resumed = releasing.run(walk)
    assert resumed.invalid_reason == 0
    assert resumed.leg_travel[0].sum() > 2 * fired.leg_travel[0].sum()
