"""Executing actions on the simulated robot in the maze: start placement, walls that stop the robot,
flat actions that are the trained controllers, and each variant's pattern choice (hierarchical
actions run end to end in test_episode)."""

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.flat.store import load_flat, shipped_flat_path
from hte_jax.geometry import planar_pose, relative_pose
from hte_jax.online.arena import maze_robot, place, start_states
from hte_jax.online.execute import (
    ANY_PATTERN_MODE,
    DRIFT_MODE,
    LEGS_MODE,
    MISS_MODE,
    ORACLE_MODE,
    SECONDARY_OUTPUTS,
    RANDOM_MODE,
    UCB_MODE,
    choose_patterns,
    execute_flat,
    flat_skills,
)
from hte_jax.hbr.hierarchy import select_middle
from hte_jax.online.gp import add_observation, empty_gp
from hte_jax.online.variants import ALL_PATTERNS, CANDIDATE_PATTERNS, candidate_elites
from hte_jax.online.secondary import step_targets
from hte_jax.online.maze import PAPER_MAZE, Maze
from hte_jax.sim.robot import load_robot
from hte_jax.sim.rollout import standing_state


def _batched(tree, batch):
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), tree)


def _empty_secondary(batch):
    return _batched(empty_gp(6, 9, 3), batch)


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
    result = execute_flat(maze_robot(walled), skills.genotypes[jnp.asarray([index, index])], standing,
                          jnp.zeros((2, 6), bool), _empty_secondary(2))
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
    recorded = execute_flat(maze_robot(walled), skills.genotypes[jnp.asarray([index, index])], standing,
                            jnp.zeros((2, 6), bool), _empty_secondary(2), record_every=25)
    assert result.qpos is None and recorded.qpos.shape == (2, 16, 25)
    np.testing.assert_array_equal(recorded.poses, result.poses)
    np.testing.assert_array_equal(recorded.state.qpos, result.state.qpos)
    np.testing.assert_array_equal(recorded.qpos[:, 0], standing.qpos)
    np.testing.assert_array_equal(recorded.qpos[:, 4::4, :2], result.poses[:, :3, :2])


def test_each_variant_picks_patterns_its_own_way(shipped_hbr):
    hbr, _ = shipped_hbr
    desired = jnp.asarray([[0.7, 0.5, 0.5]] * 4)  # 0.2 m forward, no turn (normalised)
    index, found = candidate_elites(hbr, desired)
    assert found.any(axis=1).all()
    lowest = int(CANDIDATE_PATTERNS[np.argmax(np.asarray(found[0]))])
    modes = jnp.asarray([ANY_PATTERN_MODE, UCB_MODE, ORACLE_MODE, RANDOM_MODE])
    oracle = jnp.asarray([63, 63, 47, 63])
    gp = _batched(empty_gp(6, 9, SECONDARY_OUTPUTS), 4)
    t = jnp.ones(4, jnp.int32)
    chosen, query = choose_patterns(hbr, modes, oracle, gp, desired, t, jax.random.split(jax.random.PRNGKey(1), 4))
    chosen = np.asarray(chosen)
    np.testing.assert_array_equal(query, desired)  # only DRIFT_MODE aims off the wanted step
    assert chosen[0] == -1 and chosen[2] == 47
    assert chosen[1] == lowest  # an empty GP scores every candidate alike: the first wins, as in the original
    assert chosen[3] in set(CANDIDATE_PATTERNS[np.asarray(found[3])].tolist())
    # Random choices cover many patterns; UCB moves away from a pattern observed to fail badly.
    draws = {int(choose_patterns(hbr, modes[3:], oracle[3:], _batched(empty_gp(6, 9, SECONDARY_OUTPUTS), 1),
                                 desired[3:], t[3:], jax.random.split(jax.random.PRNGKey(k), 1))[0][0]) for k in range(20)}
    assert len(draws) > 5
    bad = hbr.middle.descriptors[index[1, np.argmax(np.asarray(found[1]))]]
    failed = jax.tree.map(lambda x: x[1], gp)
    for _ in range(3):
        failed = add_observation(failed, bad, jnp.asarray([3.0, 3.0, 3.0, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5]))
    again = choose_patterns(hbr, modes[1:2], oracle[1:2], _batched(failed, 1), desired[1:2], t[1:2] + 3,
                            jax.random.split(jax.random.PRNGKey(2), 1))[0]
    assert int(again[0]) != lowest


def test_miss_choice_is_rte_until_a_pattern_is_seen_to_miss(shipped_hbr):
    """An empty GP predicts no deviation: the predicted-miss choice is the nearest elite of any
    pattern (RTE's). Once that elite's pattern is observed to deviate, a pattern whose nearest elite
    is predicted to land closer wins, exactly as a NumPy evaluation of the rule says."""
    hbr, _ = shipped_hbr
    desired = jnp.asarray([[0.7, 0.5, 0.5], [0.45, 0.62, 0.7]])
    modes = jnp.full(2, MISS_MODE, jnp.int32)
    oracle = jnp.full(2, 63, jnp.int32)
    t = jnp.ones(2, jnp.int32)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    empty = _batched(empty_gp(12, 9, SECONDARY_OUTPUTS), 2)
    nearest, _ = select_middle(hbr, desired, jnp.full(2, -1, jnp.int32))
    chosen = np.asarray(choose_patterns(hbr, modes, oracle, empty, desired, t, keys)[0])
    np.testing.assert_array_equal(chosen, np.asarray(hbr.middle_patterns)[np.asarray(nearest)])

    # The nearest elite of robot 0 deviated by 0.3 in x and y, three times.
    first = hbr.middle.descriptors[nearest[0]]
    observed = first[:3] + jnp.asarray([0.3, -0.3, 0.0])
    gp = jax.tree.map(lambda x: x[0], empty)
    for _ in range(3):
        gp = add_observation(gp, first, step_targets(first[:3], observed))
    learnt = _batched(gp, 1)
    again = int(choose_patterns(hbr, modes[:1], oracle[:1], learnt, desired[:1], t[:1], keys[:1])[0][0])
    assert again != int(chosen[0])
    # NumPy reference of the rule over every pattern's nearest elite
    index, found = candidate_elites(hbr, desired[:1], ALL_PATTERNS)
    inputs = hbr.middle.descriptors[index[0]]
    from hte_jax.online.gp import HTE_KERNEL, posterior

    mean, _ = posterior(HTE_KERNEL, gp, inputs)
    miss = np.linalg.norm(np.abs(np.asarray(inputs[:, :3]) - np.asarray(desired[0]))
                          + np.maximum(np.asarray(mean[:, 3:6]), 0.0), axis=-1)
    miss[~np.asarray(found[0])] = np.inf
    assert again == int(ALL_PATTERNS[np.argmin(miss)])


def test_drift_choice_aims_against_a_learnt_drift(shipped_hbr):
    """With no observations DRIFT_MODE is RTE's choice; after RTE's elite was seen to drift by
    +0.15 in x three times, it looks its elite up 0.15 short (or picks one predicted to land nearer),
    and its predicted landing is nearer the wanted step than RTE's."""
    hbr, _ = shipped_hbr
    desired = jnp.asarray([[0.7, 0.5, 0.5]])
    modes = jnp.full(1, DRIFT_MODE, jnp.int32)
    args = (jnp.full(1, 63, jnp.int32),)
    t, keys = jnp.ones(1, jnp.int32), jax.random.split(jax.random.PRNGKey(0), 1)
    empty = _batched(empty_gp(12, 9, SECONDARY_OUTPUTS), 1)
    nearest, _ = select_middle(hbr, desired, jnp.full(1, -1, jnp.int32))
    pattern, query = choose_patterns(hbr, modes, *args, empty, desired, t, keys)
    assert int(pattern[0]) == int(hbr.middle_patterns[nearest[0]])
    np.testing.assert_allclose(query, desired)
    first = hbr.middle.descriptors[nearest[0]]
    gp = jax.tree.map(lambda x: x[0], empty)
    for _ in range(3):
        gp = add_observation(gp, first, step_targets(first[:3], first[:3] + jnp.asarray([0.15, 0.0, 0.0])))
    pattern, query = choose_patterns(hbr, modes, *args, _batched(gp, 1), desired, t, keys)
    index, _ = select_middle(hbr, query, pattern)
    from hte_jax.online.gp import HTE_KERNEL, posterior

    chosen = hbr.middle.descriptors[index[0]]
    mean, _ = posterior(HTE_KERNEL, gp, jnp.stack([first, chosen]))
    landing = np.asarray(jnp.stack([first, chosen])[:, :3] + mean[:, 6:9])
    rte_miss, drift_miss = np.linalg.norm(landing - np.asarray(desired), axis=-1)
    assert drift_miss < rte_miss


def test_legs_choice_is_rte_until_a_leg_is_seen_to_spoil_steps(shipped_hbr):
    """LEGS_MODE with no observations runs RTE's elite; once steps that put one leg down were
    seen to deviate, it runs the elite the NumPy evaluation of `leg_miss` over every pattern's
    nearest elite picks."""
    hbr, _ = shipped_hbr
    desired = jnp.asarray([[0.6, 0.5, 0.5]])
    modes = jnp.full(1, LEGS_MODE, jnp.int32)
    oracle, t = jnp.full(1, 63, jnp.int32), jnp.ones(1, jnp.int32)
    keys = jax.random.split(jax.random.PRNGKey(0), 1)
    empty = _batched(empty_gp(24, 9, SECONDARY_OUTPUTS), 1)
    nearest, _ = select_middle(hbr, desired, jnp.full(1, -1, jnp.int32))
    chosen = int(choose_patterns(hbr, modes, oracle, empty, desired, t, keys)[0][0])
    assert chosen == int(hbr.middle_patterns[nearest[0]])
    index, found = candidate_elites(hbr, desired, ALL_PATTERNS)
    inputs = np.asarray(hbr.middle.descriptors[index[0]])
    filled = np.asarray(found[0])
    leg = int(np.argmax(inputs[filled, 3:].mean(axis=0)))  # the leg most candidates put down
    gp = jax.tree.map(lambda x: x[0], empty)
    for row in inputs[filled][:12]:
        deviation = 0.02 + 0.2 * row[3 + leg]
        gp = add_observation(gp, jnp.asarray(row), jnp.asarray([0, 0, 0, deviation, 0, 0, 0, 0, 0], jnp.float32))
    again = int(choose_patterns(hbr, modes, oracle, _batched(gp, 1), desired, t, keys)[0][0])
    from hte_jax.online.secondary import leg_effects

    effects = np.maximum(np.asarray(leg_effects(gp)), 0.0)
    miss = np.linalg.norm(inputs[:, :3] - np.asarray(desired[0]), axis=-1) + inputs[:, 3:] @ effects
    miss[~filled] = np.inf
    assert again == int(ALL_PATTERNS[np.argmin(miss)])
    rte_column = int(hbr.middle_patterns[nearest[0]])
    if inputs[rte_column, 3 + leg] == 1 and miss.min() < miss[rte_column]:
        assert again != rte_column  # RTE's elite puts the spoilt leg down and something is predicted better
