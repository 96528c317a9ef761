"""RTE's planner: shortest plans with a perfect model in the open, no walls planned into in the maze."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.hbr.store import load_hbr
from hte_jax.online.actions import action_set, displacement_of, empty_model, predict
from hte_jax.online.maze import PAPER_MAZE, GridSpec, Maze
from hte_jax.online.mcts import PlannerConfig, make_world, plan, transition

CONFIG = PlannerConfig(iterations=300, roots=2, candidates=32)


def _radial_actions():
    """80 actions: straight moves of 0.1 .. 0.5 m in 16 directions, no turn."""
    radius, angle = np.meshgrid(np.arange(1, 6) * 0.1, np.arange(16) * np.pi / 8, indexing="ij")
    return np.stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros_like(radius)], -1).reshape(-1, 3)


def test_open_field_reaches_the_goal_in_the_fewest_actions():
    maze = Maze(obstacles=(), bounds=(0.0, 0.0, 5.0, 3.0), start=(0.5, 1.5, 0.0), goal=(3.0, 1.5))
    grid = GridSpec(cell=0.25)
    actions = _radial_actions()
    world = make_world(maze, grid, actions, np.ones(len(actions), bool))
    state = jnp.asarray(maze.start, jnp.float32)
    key = jax.random.PRNGKey(0)
    fewest = int(np.ceil((2.5 - maze.goal_radius) / 0.5))  # 5 moves of at most 0.5 m
    for count in range(1, fewest + 3):
        key, sub = jax.random.split(key)
        result = plan(maze, grid, CONFIG, world, sub, state)
        if count == 1:
            first_path = result
        state, reward, terminal = transition(maze, CONFIG, world, state, result.action)  # perfect model
        assert float(reward) >= 0
        if bool(terminal):
            break
    assert float(reward) == CONFIG.goal_reward
    assert count <= fewest + 1
    assert int(result.visits.sum()) == CONFIG.roots * CONFIG.iterations
    # The first plan's path starts at the start, goes through the chosen action, and every later
    # point is one of the 80 moves away from the previous one.
    path = np.asarray(first_path.path)[: int(first_path.path_length)]
    np.testing.assert_allclose(path[0], maze.start, atol=1e-6)
    np.testing.assert_allclose(path[1, :2], np.asarray(maze.start[:2]) + actions[int(first_path.action), :2], atol=1e-5)
    steps = np.diff(path[:, :2], axis=0)
    moves = actions[:, :2]
    assert len(path) >= 3
    assert all(np.abs(moves - step).sum(axis=1).min() < 1e-4 for step in steps)


@pytest.mark.parametrize("start", [(2.32, 3.27, np.pi), (3.9, 0.9, -np.pi / 2)])
def test_maze_plans_never_hit_a_wall(start):
    hbr, task, _ = load_hbr()
    actions = action_set(hbr.top, task.extent)
    mean, _ = predict(empty_model(actions, 8), actions)
    grid = GridSpec()
    world = make_world(PAPER_MAZE, grid, displacement_of(mean), actions.mask)
    state = jnp.asarray(start, jnp.float32)
    _, reward, _ = transition(PAPER_MAZE, CONFIG, world, jnp.broadcast_to(state, (actions.size, 3)), jnp.arange(actions.size))
    assert (np.asarray(reward) >= 0).any()  # a free action exists
    result = plan(PAPER_MAZE, grid, CONFIG, world, jax.random.PRNGKey(1), state)
    assert float(reward[result.action]) >= 0 and float(result.value) > CONFIG.collision_reward / 2


def test_planner_settings_are_checked():
    with pytest.raises(ConfigError, match="iterations"):
        PlannerConfig(iterations=0)
    with pytest.raises(ConfigError, match="widening"):
        PlannerConfig(widening=1.5)
    assert PlannerConfig(iterations=6000).max_children == 79
