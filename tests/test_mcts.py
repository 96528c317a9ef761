"""RTE's planner: shortest plans with a perfect model in the open, no walls planned into in the maze;
its steps (select, expand, evaluate, back-up) against NumPy references on hand-built trees."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.hbr.store import load_hbr
from hte_jax.online.gp import empty_gp
from hte_jax.online.skills import OUTCOME_DIM, action_set, displacement_of, predict
from hte_jax.online.maze import PAPER_MAZE, GridSpec, Maze, distance_field
from hte_jax.online.mcts import (
    Path,
    PlannerConfig,
    backup,
    empty_tree,
    evaluate,
    expand,
    expansion_action,
    geodesic_cost,
    plan,
    search,
    select,
    transition,
    uct_child,
    world_of,
)

CONFIG = PlannerConfig(iterations=300, roots=2, candidates=32)
OPEN = Maze(obstacles=(), bounds=(0.0, 0.0, 5.0, 3.0), start=(0.5, 1.5, 0.0), goal=(3.0, 1.5))
OPEN_GRID = GridSpec(cell=0.25)



def make_world(maze, grid, displacement, mask):
    """A planner's world over the maze's distance field (what `episode.plan_step` builds)."""
    return world_of(displacement, mask, distance_field(maze, grid))

def _radial_actions():
    """80 actions: straight moves of 0.1 .. 0.5 m in 16 directions, no turn."""
    radius, angle = np.meshgrid(np.arange(1, 6) * 0.1, np.arange(16) * np.pi / 8, indexing="ij")
    return np.stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros_like(radius)], -1).reshape(-1, 3)


@pytest.mark.slow
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


@pytest.mark.slow
@pytest.mark.parametrize("start", [(2.32, 3.27, np.pi), (3.9, 0.9, -np.pi / 2)])
def test_maze_plans_never_hit_a_wall(start):
    hbr, task, _ = load_hbr()
    actions = action_set(hbr.top, task.extent)
    mean, _ = predict(empty_gp(8, actions.inputs.shape[1], OUTCOME_DIM), actions)
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


# The search's steps, one at a time, on small hand-built trees.
SMALL = PlannerConfig(iterations=7, roots=1, exploration=1.0, depth=4, candidates=8)  # M = 8 nodes, K = 4


def _tree(config, parent, **fields):
    """A tree whose node i has parent parent[i] (parent[0] = -1, the root), children in node order;
    `fields` override (M,) or (M, 3) rows of the first len(parent) nodes (state, reward, visits, ...)."""
    tree = empty_tree(config, jnp.zeros(3, jnp.float32))
    n = len(parent)
    children = np.full(tree.children.shape, -1, np.int32)
    depth = np.zeros(tree.depth.shape, np.int32)
    for node in range(1, n):
        row = parent[node]
        children[row, (children[row] >= 0).sum()] = node
        depth[node] = depth[row] + 1
    tree = tree.replace(parent=tree.parent.at[:n].set(jnp.asarray(parent, jnp.int32)),
                        children=jnp.asarray(children), num_children=jnp.asarray((children >= 0).sum(1), jnp.int32),
                        depth=jnp.asarray(depth), size=jnp.int32(n))
    return tree.replace(**{name: getattr(tree, name).at[:n].set(jnp.asarray(value, getattr(tree, name).dtype))
                           for name, value in fields.items()})


def _path(config, nodes):
    capacity = config.iterations + 1
    return Path(nodes=jnp.asarray(list(nodes) + [capacity] * (config.depth + 1 - len(nodes)), jnp.int32),
                length=jnp.int32(len(nodes)))


def _numpy_select(config, tree):
    """Reference descent: UCT children until a leaf or a node that should widen."""
    t = jax.tree.map(np.asarray, tree)
    node, path = 0, [0]
    while not (t.terminal[node] or t.depth[node] >= config.depth):
        count = t.num_children[node]
        widen = count == 0 or np.float32(t.visits[node]) ** np.float32(config.widening) > count
        if widen and count < config.max_children:
            break
        kids = t.children[node, :count]
        n = np.maximum(t.visits[kids], 1).astype(np.float32)
        score = t.value[kids] / n + 2 * config.exploration * np.sqrt(np.log(np.float32(t.visits[node]) + 1) / n)
        node = int(kids[np.argmax(score)])
        path.append(node)
    return path


def test_backup_adds_discounted_returns_up_the_path():
    #      0
    #    /   \
    #   1     2      path 0 -> 2 -> 3; node 1 is off the path
    #         |
    #         3
    rewards, visits, values = [0.0, 5.0, -2.0, 7.0], [6, 2, 3, 1], [0.0, 4.0, -1.5, 2.0]
    tree = _tree(SMALL, [-1, 0, 0, 2], reward=rewards, visits=visits, value=values)
    leaf_value = 3.25
    out = backup(SMALL, tree, _path(SMALL, [0, 2, 3]), jnp.float32(leaf_value))
    g3 = rewards[3] + SMALL.gamma * leaf_value
    g2 = rewards[2] + SMALL.gamma * g3
    expected_values = np.array(values + [0.0] * 4, np.float32)
    expected_values[2] += g2
    expected_values[3] += g3
    np.testing.assert_allclose(np.asarray(out.value), expected_values, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(out.visits), np.array([7, 2, 4, 2, 0, 0, 0, 0]))
    # A path holding the root only counts one more root visit and leaves every value alone.
    alone = backup(SMALL, tree, _path(SMALL, [0]), jnp.float32(leaf_value))
    np.testing.assert_array_equal(np.asarray(alone.visits), np.asarray(tree.visits).copy() + np.eye(8, dtype=int)[0])
    np.testing.assert_array_equal(np.asarray(alone.value), np.asarray(tree.value))


def test_select_descends_by_uct_as_numpy_does():
    #        0                 Means: node 2 has the best one, node 3 the fewest visits; below node 2,
    #     /  |  \              node 5 (terminal) the better mean, node 4 the fewer visits. Which ones
    #    1   2   3             UCT takes depends on c. No node on the way should widen (9^0.5 = 3
    #       / \                children at the root, 4^0.5 = 2 at node 2).
    #      4   5
    parent = [-1, 0, 0, 0, 2, 2]
    visits = [9, 2, 4, 1, 1, 3]
    values = [0.0, -4.0, 10.0, 0.5, 3.5, 12.3]
    tree = _tree(SMALL, parent, visits=visits, value=values, terminal=[False] * 5 + [True])
    chosen = {}
    for c in (0.1, 1.0, 10.0):
        config = dataclasses.replace(SMALL, exploration=c)
        path = select(config, tree)
        expected = _numpy_select(config, tree)
        assert np.asarray(path.nodes)[: int(path.length)].tolist() == expected
        assert (np.asarray(path.nodes)[int(path.length):] == config.iterations + 1).all()
        assert int(path.last) == expected[-1]
        assert int(uct_child(config, tree, 0)) == expected[1]
        chosen[c] = expected
    assert chosen[0.1] == [0, 2, 5] and chosen[1.0] == [0, 2, 4] and chosen[10.0] == [0, 3]


def test_select_agrees_with_numpy_on_grown_trees():
    world = make_world(OPEN, OPEN_GRID, _radial_actions(), np.ones(80, bool))
    for widening, c in ((0.3, 100.0), (0.4, 2.0)):
        config = PlannerConfig(iterations=150, roots=1, widening=widening, exploration=c, depth=6, candidates=8)
        tree = jax.jit(search, static_argnums=(0, 1, 2))(OPEN, OPEN_GRID, config, world, jax.random.PRNGKey(3),
                                                         jnp.asarray(OPEN.start, jnp.float32))
        path = select(config, tree)
        expected = _numpy_select(config, tree)
        assert len(expected) >= 3  # the descent goes below the root's children
        assert np.asarray(path.nodes)[: int(path.length)].tolist() == expected


@pytest.mark.slow
def test_expand_follows_progressive_widening():
    world = make_world(OPEN, OPEN_GRID, _radial_actions(), np.ones(80, bool))
    key = jax.random.PRNGKey(4)
    start = jnp.asarray(OPEN.start, jnp.float32)
    state = jnp.broadcast_to(start, (8, 3))

    def step(tree):
        path = select(SMALL, tree)
        return tree, path, *expand(OPEN, OPEN_GRID, SMALL, world, key, tree, path)

    # Root with one child, visited once: 1^0.5 > 1 fails, so the search goes down and widens the child.
    tree, path, grown, longer = step(_tree(SMALL, [-1, 0], visits=[1, 1], state=state[:2]))
    assert np.asarray(longer.nodes)[:3].tolist() == [0, 1, 2] and int(longer.length) == 3
    assert int(grown.size) == 3 and int(grown.parent[2]) == 1 and int(grown.depth[2]) == 2
    assert np.asarray(grown.num_children)[:3].tolist() == [1, 1, 0] and int(grown.children[1, 0]) == 2
    action = expansion_action(OPEN, OPEN_GRID, SMALL, world, key, start)
    nxt, reward, terminal = transition(OPEN, SMALL, world, start, action)
    assert int(grown.action[2]) == int(action)
    np.testing.assert_array_equal(np.asarray(grown.state[2]), np.asarray(nxt))
    assert float(grown.reward[2]) == float(reward) and bool(grown.terminal[2]) == bool(terminal)
    # Visited twice: 2^0.5 > 1, so the root gets its second child.
    _, path, grown, longer = step(_tree(SMALL, [-1, 0], visits=[2, 1], state=state[:2]))
    assert int(path.length) == 1 and np.asarray(longer.nodes)[:2].tolist() == [0, 2]
    assert np.asarray(grown.children[0, :3]).tolist() == [1, 2, -1] and int(grown.num_children[0]) == 2
    # A full root (K = 4 children) never widens, however often it is visited.
    full = [-1, 0, 0, 0, 0]
    _, path, grown, _ = step(_tree(SMALL, full, visits=[100, 1, 1, 1, 1], state=state[:5]))
    assert int(path.length) == 2 and int(grown.num_children[0]) == SMALL.max_children == 4
    # A terminal node or one at the depth limit gets no child: tree and path stay as they were.
    for fields in ({"terminal": [False, True]}, {"depth": [0, SMALL.depth]}):
        tree, path, grown, longer = step(_tree(SMALL, [-1, 0], visits=[1, 1], state=state[:2], **fields))
        assert int(path.length) == 2
        jax.tree.map(np.testing.assert_array_equal, (grown, longer), (tree, path))


def test_search_never_widens_faster_than_visits_allow():
    world = make_world(OPEN, OPEN_GRID, _radial_actions(), np.ones(80, bool))
    config = PlannerConfig(iterations=200, roots=1, depth=6, candidates=8)
    tree = jax.jit(search, static_argnums=(0, 1, 2))(OPEN, OPEN_GRID, config, world, jax.random.PRNGKey(5),
                                                     jnp.asarray(OPEN.start, jnp.float32))
    count, visits = np.asarray(tree.num_children), np.asarray(tree.visits)
    # A node's c-th child came on a visit v with v^a > c - 1 (or c = 1), and v < the visits it has now.
    allowed = (count <= 1) | (count - 1 < np.asarray(jnp.maximum(tree.visits - 1, 0).astype(jnp.float32) ** config.widening))
    assert allowed.all() and (count <= config.max_children).all()
    assert int(tree.size) == config.iterations + 1 and count.sum() == config.iterations  # one new node a simulation
    assert int(visits[0]) == config.iterations and count[0] >= 2


@pytest.mark.slow
def test_expansion_takes_the_free_action_nearest_the_goal():
    # A thin wall ahead, and besides the 80 moves one 1.2 m jump that would cross it and end nearest
    # the goal. With many more draws than actions, the choice is the best of all actions by the
    # distance field among those that do not collide.
    maze = dataclasses.replace(OPEN, obstacles=((1.0, 0.8, 1.05, 2.2),))
    actions = np.concatenate([_radial_actions(), [[1.2, 0.0, 0.0]]])
    world = make_world(maze, OPEN_GRID, actions, np.ones(81, bool))
    config = dataclasses.replace(SMALL, candidates=2000)
    start = jnp.asarray(maze.start, jnp.float32)
    ends, reward, _ = transition(maze, config, world, jnp.broadcast_to(start, (81, 3)), jnp.arange(81))
    cost = np.asarray(geodesic_cost(maze, OPEN_GRID, world.field, ends[:, :2]))
    assert np.argmin(cost) == 80 and float(reward[80]) < 0  # the jump is the unmasked favourite, and collides
    best = int(np.argmin(np.where(np.asarray(reward) < 0, np.inf, cost)))
    assert int(expansion_action(maze, OPEN_GRID, config, world, jax.random.PRNGKey(6), start)) == best


@pytest.mark.slow
def test_evaluate_is_the_discounted_rollout_return_within_the_depth_limit():
    # One usable action, 0.5 m straight ahead: from x = 0.6 the fifth step (k = 4) ends 0.1 m from the goal.
    world = make_world(OPEN, OPEN_GRID, np.array([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]]), np.array([True, False]))
    back = make_world(OPEN, OPEN_GRID, np.array([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]]), np.array([False, True]))
    config = dataclasses.replace(SMALL, depth=20)
    state = jnp.asarray([[0.0, 0.0, 0.0], [0.6, 1.5, 0.0]], jnp.float32)
    key = jax.random.PRNGKey(7)

    def value(world, depth, terminal=False):
        tree = _tree(config, [-1, 0], state=state, depth=[0, depth], terminal=[False, terminal])
        return float(evaluate(OPEN, config, world, key, tree, jnp.int32(1)))

    goal = config.gamma ** 4 * config.goal_reward
    assert value(world, 1) == pytest.approx(goal, rel=1e-6)
    assert value(world, config.depth - 5) == pytest.approx(goal, rel=1e-6)  # steps k = 0 .. 4 still count
    assert value(world, config.depth - 4) == 0.0  # the goal lies past the depth limit
    assert value(world, 1, terminal=True) == 0.0
    # Backwards: 0.1 m, then out of the map on step k = 1.
    assert value(back, 1) == pytest.approx(config.gamma * config.collision_reward, rel=1e-6)
