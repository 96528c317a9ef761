"""RTE's planner: Monte-Carlo tree search over the repertoire's actions, jitted and batched (`docs/design.md`,
Planner). A simulation is `select`, `expand`, `evaluate` and `backup` on one fixed-size tree, written for
vmap (an expansion that does not happen writes out of range); `plan` merges `roots` trees at the root.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from flax import struct

from hte_jax.errors import check_fields, integer, number
from hte_jax.geometry import compose_pose
from hte_jax.online.maze import GridSpec, Maze, in_bounds, move_collides, point_collides, reached_goal


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    """MCTS settings, the original's but iterations x roots (6000 x 32 there): UCT c `exploration`, progressive
    widening exponent a, discount gamma, `depth` the longest path, `candidates` ranked at each expansion."""

    iterations: int = integer(1000)
    roots: int = integer(4)
    exploration: float = number(100.0, 0.0)
    widening: float = number(0.5, 0.0, 1.0, open_low=True)
    gamma: float = number(0.9, 0.0, 1.0)
    depth: int = integer(20)
    candidates: int = integer(100)
    collision_reward: float = -1000.0
    goal_reward: float = 100.0

    def __post_init__(self):
        check_fields(self)

    @property
    def max_children(self) -> int:
        return int(math.ceil((self.iterations + 1) ** self.widening)) + 1


@struct.dataclass
class Tree:
    """One search tree of M = iterations + 1 nodes (0: the root), K = max children: state (M, 3); parent and action
    (M,) int32 (-1 at the root); reward (M,) of entering; terminal (M,) bool; depth and visits (M,) int32; value
    (M,) summed discounted returns from entering; children (M, K) int32 (-1 empty); num_children (M,); size ()."""

    state: jax.Array
    parent: jax.Array
    action: jax.Array
    reward: jax.Array
    terminal: jax.Array
    depth: jax.Array
    visits: jax.Array
    value: jax.Array
    children: jax.Array
    num_children: jax.Array
    size: jax.Array


@struct.dataclass
class World:
    """What a plan needs besides the state. displacement: (A, 3) predicted (dx, dy, dyaw) of each action in
    the robot's frame. mask: (A,) bool usable actions. field: (nx, ny) int32 grid steps to the goal (-1
    unreachable). usable: (A,) int32 action indices, the usable ones first. count: () int32 usable actions."""

    displacement: jax.Array
    mask: jax.Array
    field: jax.Array
    usable: jax.Array
    count: jax.Array


@struct.dataclass
class Path:
    """The nodes one simulation went through. nodes: (D + 1,) int32 the node at each depth (D = config.depth);
    from `length` on M = iterations + 1, past every tree array (scatters through them are dropped).
    length: () int32 nodes on the path (at least 1: the root)."""

    nodes: jax.Array
    length: jax.Array

    @property
    def last(self) -> jax.Array:
        """() int32 the deepest node of the path."""
        return self.nodes[self.length - 1]

    def extended(self, node: jax.Array, grow: jax.Array) -> Path:
        """The path with `node` appended where `grow` (() bool), else unchanged (a dropped write)."""
        index = jnp.where(grow, self.length, self.nodes.shape[0])
        return Path(nodes=self.nodes.at[index].set(node, mode="drop"), length=self.length + grow.astype(jnp.int32))


def empty_tree(config: PlannerConfig, state: jax.Array) -> Tree:
    """A tree holding only its root, at `state` (3,)."""
    m, k = config.iterations + 1, config.max_children
    return Tree(state=jnp.zeros((m, 3), jnp.float32).at[0].set(state), parent=jnp.full((m,), -1, jnp.int32),
                action=jnp.full((m,), -1, jnp.int32), reward=jnp.zeros((m,), jnp.float32),
                terminal=jnp.zeros((m,), bool), depth=jnp.zeros((m,), jnp.int32), visits=jnp.zeros((m,), jnp.int32),
                value=jnp.zeros((m,), jnp.float32), children=jnp.full((m, k), -1, jnp.int32),
                num_children=jnp.zeros((m,), jnp.int32), size=jnp.int32(1))

def transition(maze: Maze, config: PlannerConfig, world: World, state: jax.Array, action: jax.Array):
    """(..., 3) state, (...,) action -> next state, reward, terminal."""
    nxt = compose_pose(state, world.displacement[action])
    end = nxt[..., :2]
    bad = ~in_bounds(maze, end) | point_collides(maze, end) | move_collides(maze, state[..., :2], end)
    goal = reached_goal(maze, end) & ~bad
    reward = jnp.where(bad, config.collision_reward, jnp.where(goal, config.goal_reward, 0.0))
    return nxt, reward, bad | goal


def geodesic_cost(maze: Maze, grid: GridSpec, field: jax.Array, points: jax.Array) -> jax.Array:
    """(..., 2) -> (...,) estimated path length to the goal through the grid (inf if unreachable)."""
    node = grid.node_of(maze, points)
    steps = field[node[..., 0], node[..., 1]]
    node_xy = jnp.asarray(maze.bounds[:2]) + node * grid.cell
    cost = steps * grid.cell + jnp.linalg.norm(points - node_xy, axis=-1)
    near = jnp.linalg.norm(points - jnp.asarray(maze.goal), axis=-1)
    cost = jnp.where(steps == 0, near, cost)
    return jnp.where((steps < 0) | ~in_bounds(maze, points), jnp.inf, cost)


def _sample_actions(key, world: World, num: int) -> jax.Array:
    """`num` uniform draws among the usable actions (O(num), whatever the number of actions)."""
    return world.usable[jax.random.randint(key, (num,), 0, jnp.maximum(world.count, 1))]


def evaluate(maze: Maze, config: PlannerConfig, world: World, key: jax.Array, tree: Tree, leaf: jax.Array) -> jax.Array:
    """() float32 the leaf's estimated return: a uniform random rollout's from its state and depth (0 if
    terminal), until a terminal transition or the depth limit; only the pose composition is sequential."""
    state, alive, depth = tree.state[leaf], ~tree.terminal[leaf], tree.depth[leaf]
    steps = config.depth
    actions = _sample_actions(key, world, steps)

    def move(pose, action):
        return compose_pose(pose, world.displacement[action]), pose

    _, before = jax.lax.scan(move, state, actions, unroll=True)  # (S, 3) the pose before each step
    _, reward, terminal = transition(maze, config, world, before, actions)
    k = jnp.arange(steps)
    earlier_terminal = jnp.cumsum(terminal) - terminal  # terminal transitions before step k
    go = alive & (depth + k < config.depth) & (earlier_terminal == 0)
    return jnp.sum(jnp.where(go, config.gamma ** k.astype(jnp.float32) * reward, 0.0))


def is_leaf(config: PlannerConfig, tree: Tree, node: jax.Array) -> jax.Array:
    """() bool: the node ends every simulation reaching it (terminal, or at the depth limit)."""
    return tree.terminal[node] | (tree.depth[node] >= config.depth)


def should_widen(config: PlannerConfig, tree: Tree, node: jax.Array) -> jax.Array:
    """() bool progressive widening: a new child when it has none or visits^a > children, room permitting."""
    count = tree.num_children[node]
    widen = (count == 0) | (tree.visits[node].astype(jnp.float32) ** config.widening > count)
    return widen & (count < config.max_children)


def uct_child(config: PlannerConfig, tree: Tree, node: jax.Array) -> jax.Array:
    """() int32 the child of `node` (which has one) maximising Q/N + 2c sqrt(ln(N_node + 1) / N)."""
    kids = tree.children[node]
    valid = kids >= 0
    safe = jnp.where(valid, kids, 0)
    n, parent = jnp.maximum(tree.visits[safe], 1).astype(jnp.float32), tree.visits[node].astype(jnp.float32)
    score = tree.value[safe] / n + 2.0 * config.exploration * jnp.sqrt(jnp.log(parent + 1.0) / n)
    return safe[jnp.argmax(jnp.where(valid, score, -jnp.inf))]


def select(config: PlannerConfig, tree: Tree) -> Path:
    """Descend from the root by `uct_child` until a leaf or a node that should widen (the path's `last`).
    A loop of `config.depth` steps that stand still once stopped: a fixed trip count, so that on a GPU the
    descent never waits for the host to test whether it is done (a node at the depth limit is a leaf)."""
    capacity, depth_limit = config.iterations + 1, config.depth

    def descend(_, carry):
        node, stopped, nodes, length = carry
        stop = stopped | is_leaf(config, tree, node) | should_widen(config, tree, node)
        node_next = jnp.where(stop, node, uct_child(config, tree, node))
        nodes = nodes.at[jnp.where(stop, depth_limit + 1, length)].set(node_next, mode="drop")
        return node_next, stop, nodes, length + (~stop).astype(jnp.int32)

    nodes = jnp.full((depth_limit + 1,), capacity, jnp.int32).at[0].set(0)
    _, _, nodes, length = jax.lax.fori_loop(0, depth_limit, descend, (jnp.int32(0), False, nodes, jnp.int32(1)))
    return Path(nodes=nodes, length=length)


def expansion_action(maze: Maze, grid: GridSpec, config: PlannerConfig, world: World, key: jax.Array,
                     state: jax.Array) -> jax.Array:
    """() int32 the best of `config.candidates` uniform usable actions from `state` (3,): the one ending
    nearest the goal by `geodesic_cost`; colliding ones are never preferred."""
    candidates = _sample_actions(key, world, config.candidates)
    ends, reward, _ = transition(maze, config, world, jnp.broadcast_to(state, (config.candidates, 3)), candidates)
    cost = jnp.where(reward < 0, jnp.inf, geodesic_cost(maze, grid, world.field, ends[:, :2]))
    return candidates[jnp.argmin(cost)]


def expand(maze: Maze, grid: GridSpec, config: PlannerConfig, world: World, key: jax.Array, tree: Tree,
           path: Path) -> tuple[Tree, Path]:
    """Give the path's last node (unless a leaf) a child, node `tree.size`, and append it to the path."""
    capacity, node = config.iterations + 1, path.last
    grow = ~is_leaf(config, tree, node)
    action = expansion_action(maze, grid, config, world, key, tree.state[node])
    nxt, reward, terminal = transition(maze, config, world, tree.state[node], action)
    new = jnp.where(grow, tree.size, capacity)
    child = dict(state=nxt, parent=node, action=action, reward=reward, terminal=terminal, depth=tree.depth[node] + 1)
    tree = tree.replace(
        **{name: getattr(tree, name).at[new].set(value, mode="drop") for name, value in child.items()},
        children=tree.children.at[jnp.where(grow, node, capacity), tree.num_children[node]].set(new, mode="drop"),
        num_children=tree.num_children.at[node].add(grow.astype(jnp.int32)), size=tree.size + grow.astype(jnp.int32))
    return tree, path.extended(new, grow)


def backup(config: PlannerConfig, tree: Tree, path: Path, value: jax.Array) -> Tree:
    """One more visit at every node of the path, and to each below the root its discounted return
    g_k = reward_k + gamma g_(k+1), with g after the last node = `value` (() float32)."""
    capacity, depth_limit = config.iterations + 1, config.depth
    on_path = jnp.arange(depth_limit + 1) < path.length
    below_root = on_path & (jnp.arange(depth_limit + 1) > 0)
    rewards = jnp.where(below_root, tree.reward[jnp.where(on_path, path.nodes, 0)], 0.0)

    def back(g, k):
        g = jnp.where(below_root[k], rewards[k] + config.gamma * g, g)
        return g, g

    returns = jax.lax.scan(back, value, jnp.arange(depth_limit, -1, -1), unroll=True)[1][::-1]
    target = jnp.where(below_root, path.nodes, capacity)
    return tree.replace(visits=tree.visits.at[target].add(1, mode="drop").at[0].add(1),
                        value=tree.value.at[target].add(returns, mode="drop"))


def simulate(maze: Maze, grid: GridSpec, config: PlannerConfig, world: World, key_expand: jax.Array,
             key_rollout: jax.Array, tree: Tree) -> Tree:
    """One simulation: `select` a path, `expand` its last node, `evaluate` the new leaf, `backup` the return."""
    path = select(config, tree)
    tree, path = expand(maze, grid, config, world, key_expand, tree, path)
    value = evaluate(maze, config, world, key_rollout, tree, path.last)
    return backup(config, tree, path, value)


def search(maze: Maze, grid: GridSpec, config: PlannerConfig, world: World, key: jax.Array, state: jax.Array) -> Tree:
    """Grow one tree from `state` (3,) by config.iterations simulations (`simulate`)."""

    def body(_, carry):
        tree, key = carry
        key, key_expand, key_rollout = jax.random.split(key, 3)
        return simulate(maze, grid, config, world, key_expand, key_rollout, tree), key

    return jax.lax.fori_loop(0, config.iterations, body, (empty_tree(config, state), key))[0]

@struct.dataclass
class PlanResult:
    """One decision: action () int32 of the best mean value over the merged roots, value (), visits (A,) int32,
    path (D + 1, 3) the start, the action's end and the most-visited branch below it, path_length () int32."""

    action: jax.Array
    value: jax.Array
    visits: jax.Array
    path: jax.Array
    path_length: jax.Array


def _principal_path(tree: Tree, first: jax.Array, depth: int) -> tuple[jax.Array, jax.Array]:
    """States from the root through node `first` and then its most-visited descendants."""

    def follow(carry, _):
        node, length = carry
        kids = tree.children[node]
        valid = kids >= 0
        safe = jnp.where(valid, kids, 0)
        child = safe[jnp.argmax(jnp.where(valid, tree.visits[safe], -1))]
        go = valid.any()
        node = jnp.where(go, child, node)
        return (node, length + go), tree.state[node]

    (_, length), rest = jax.lax.scan(follow, (first, jnp.int32(2)), None, length=depth - 1)
    path = jnp.concatenate([tree.state[:1], tree.state[first][None], rest], axis=0)
    return path, length


@functools.partial(jax.jit, static_argnames=("maze", "grid", "config"))
def plan(maze: Maze, grid: GridSpec, config: PlannerConfig, world: World, key: jax.Array, state: jax.Array) -> PlanResult:
    """Plan from `state` (3,): `config.roots` trees merged at the root (see the module docstring)."""
    trees = jax.vmap(lambda k: search(maze, grid, config, world, k, state))(jax.random.split(key, config.roots))
    root_children = trees.children[:, 0]  # (R, K)
    valid = root_children >= 0
    safe = jnp.where(valid, root_children, 0)
    actions = jnp.take_along_axis(trees.action, safe, axis=1)
    visits = jnp.where(valid, jnp.take_along_axis(trees.visits, safe, axis=1), 0)
    values = jnp.where(valid, jnp.take_along_axis(trees.value, safe, axis=1), 0.0)
    num_actions = world.mask.shape[0]
    target = jnp.where(valid, actions, num_actions)
    merged_visits = jax.ops.segment_sum(visits.reshape(-1), target.reshape(-1), num_segments=num_actions + 1)[:-1]
    merged_values = jax.ops.segment_sum(values.reshape(-1), target.reshape(-1), num_segments=num_actions + 1)[:-1]
    mean = jnp.where(merged_visits > 0, merged_values / jnp.maximum(merged_visits, 1), -jnp.inf)
    best = jnp.argmax(mean).astype(jnp.int32)
    # The planned path: in the tree that visited the chosen action most, follow its node down.
    on_best = jnp.where(valid & (actions == best), visits, -1)  # (R, K)
    tree_index = jnp.argmax(on_best.max(axis=1))
    first = safe[tree_index, jnp.argmax(on_best[tree_index])]
    tree = jax.tree.map(lambda x: x[tree_index], trees)
    path, length = _principal_path(tree, first, config.depth)
    return PlanResult(action=best, value=mean[best], visits=merged_visits, path=path, path_length=length)


def world_of(displacement: jax.Array, mask: jax.Array, field: jax.Array) -> World:
    """A World from predicted displacements (A, 3), usable actions (A,) and a distance field (jittable)."""
    mask = jnp.asarray(mask, bool)
    return World(displacement=jnp.asarray(displacement, jnp.float32), mask=mask, field=field,
                 usable=jnp.argsort(~mask, stable=True).astype(jnp.int32), count=mask.sum().astype(jnp.int32))
