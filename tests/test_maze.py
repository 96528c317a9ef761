"""Maze geometry for the planner: exact disc-vs-box checks and the BFS distance field."""

from collections import deque

import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.online.maze import (
    NEIGHBOURS,
    PAPER_MAZE,
    GridSpec,
    Maze,
    distance_field,
    edge_free,
    in_bounds,
    move_collides,
    point_box_distance,
    point_collides,
    reached_goal,
    segment_box_distance,
)


def test_start_and_goal_are_free_and_boxes_block():
    start, goal = jnp.asarray(PAPER_MAZE.start[:2]), jnp.asarray(PAPER_MAZE.goal)
    assert not bool(point_collides(PAPER_MAZE, start)) and not bool(point_collides(PAPER_MAZE, goal))
    assert bool(point_collides(PAPER_MAZE, jnp.asarray([2.45, 0.2])))  # inside box 2
    assert bool(point_collides(PAPER_MAZE, jnp.asarray([2.45, 0.8])))  # 0.175 m above box 2
    assert not bool(point_collides(PAPER_MAZE, jnp.asarray([2.45, 0.9])))  # 0.275 m above it
    assert bool(reached_goal(PAPER_MAZE, goal + 0.1)) and not bool(reached_goal(PAPER_MAZE, goal + 0.2))
    assert bool(in_bounds(PAPER_MAZE, start)) and not bool(in_bounds(PAPER_MAZE, jnp.asarray([-0.1, 1.0])))
    # straight from the start to the goal crosses the central boxes
    assert bool(move_collides(PAPER_MAZE, start, goal))
    with pytest.raises(ConfigError, match="must be \\(x1, y1, x2, y2\\)"):
        Maze(obstacles=((1.0, 0.0, 0.0, 1.0),))


def test_swept_disc_distance_matches_dense_sampling():
    rng = np.random.default_rng(0)
    boxes = PAPER_MAZE.boxes
    a = rng.uniform([-0.5, -0.5], [5.0, 4.5], (400, 2)).astype(np.float32)
    b = (a + rng.normal(0, 0.6, (400, 2))).astype(np.float32)
    exact = np.asarray(segment_box_distance(jnp.asarray(a), jnp.asarray(b), boxes))
    t = np.linspace(0, 1, 2001)[:, None, None]
    samples = a[None] + t * (b - a)[None]  # (T, 400, 2)
    sampled = np.asarray(point_box_distance(jnp.asarray(samples), boxes)).min(axis=0)
    step = np.linalg.norm(b - a, axis=-1)[:, None] / 2000
    assert (exact <= sampled + 1e-5).all()
    assert (sampled - exact <= step / 2 + 1e-5).all()
    # a segment passing 0.2 m beside a box corner: free for radius 0.15, blocked for radius 0.25
    maze = Maze(obstacles=((0.0, 0.0, 1.0, 1.0),))
    c = 2.0 + 0.2 * np.sqrt(2.0)  # the line x + y = c passes 0.2 m from the corner (1, 1)
    p0, p1 = jnp.asarray([c, 0.0]), jnp.asarray([0.0, c])
    assert not bool(move_collides(maze, p0, p1, 0.15)) and bool(move_collides(maze, p0, p1, 0.25))


def _same_bits(host, device):
    device = np.asarray(device)
    assert host.dtype == device.dtype and host.shape == device.shape and host.tobytes() == device.tobytes()


@pytest.mark.exact_numerics
@pytest.mark.parametrize("obstacles", [PAPER_MAZE.obstacles, ((1.0, 0.8, 1.05, 2.2),)])
def test_host_geometry_agrees_with_jax_bit_for_bit(obstacles):
    """NumPy (xp=np: `edge_free` and the maze generator on the host) gives jax's values to the last bit, with one
    box or several (XLA divides by a broadcast value as a product with its inverse: `numerics.quotient`)."""
    maze = Maze(obstacles=obstacles)
    rng = np.random.default_rng(3)
    a = rng.uniform(-0.5, 4.5, (3000, 2)).astype(np.float32)
    b = rng.uniform(-0.5, 4.5, (3000, 2)).astype(np.float32)
    b[::3, 0], b[1::3, 1], b[2::7] = a[::3, 0], a[1::3, 1], a[2::7]  # axis-parallel and zero-length segments
    _same_bits(segment_box_distance(a, b, maze.boxes, np),
               segment_box_distance(jnp.asarray(a), jnp.asarray(b), maze.boxes))
    _same_bits(point_box_distance(a, maze.boxes, np), point_box_distance(jnp.asarray(a), maze.boxes))
    _same_bits(move_collides(maze, a, b, 0.3, np), move_collides(maze, jnp.asarray(a), jnp.asarray(b), 0.3))
    _same_bits(point_collides(maze, a, xp=np), point_collides(maze, jnp.asarray(a)))
    _same_bits(GridSpec().node_of(maze, a, np), GridSpec().node_of(maze, jnp.asarray(a)))
    grid = GridSpec(cell=0.25)
    nodes = grid.nodes(maze)
    targets = (nodes[:, :, None, :] + NEIGHBOURS[None, None] * grid.cell).astype(np.float32)
    start = np.broadcast_to(nodes[:, :, None, :], targets.shape)  # `edge_free`'s steps
    radius = grid.radius_factor * maze.robot_radius
    _same_bits(move_collides(maze, start, targets, radius, np),
               move_collides(maze, jnp.asarray(start), jnp.asarray(targets), radius))


def _numpy_bfs(free, goal):
    nx, ny = free.shape[:2]
    dist = -np.ones((nx, ny), int)
    dist[goal] = 0
    queue = deque([goal])
    while queue:
        i, j = queue.popleft()
        for k, (di, dj) in enumerate(NEIGHBOURS):
            a, b = i + di, j + dj
            # a step a->(i, j) must be free from the neighbour's side
            back = [idx for idx, (ei, ej) in enumerate(NEIGHBOURS) if (ei, ej) == (-di, -dj)][0]
            if 0 <= a < nx and 0 <= b < ny and dist[a, b] < 0 and free[a, b, back]:
                dist[a, b] = dist[i, j] + 1
                queue.append((a, b))
    return dist


@pytest.mark.parametrize("cell", [0.5, 0.25])
def test_distance_field_matches_numpy_bfs(cell):
    grid = GridSpec(cell=cell)
    free = edge_free(PAPER_MAZE, grid)
    goal = tuple(np.asarray(grid.node_of(PAPER_MAZE, jnp.asarray(PAPER_MAZE.goal))))
    want = _numpy_bfs(free, goal)
    got = np.asarray(distance_field(PAPER_MAZE, grid))
    np.testing.assert_array_equal(got, want)
    start = tuple(np.asarray(grid.node_of(PAPER_MAZE, jnp.asarray(PAPER_MAZE.start[:2]))))
    assert got[start] > 0  # the start reaches the goal around the boxes
    assert (got >= -1).all() and (got == -1).any()  # nodes inside boxes are unreachable


def test_shipped_mazes_load_by_name_or_file_and_bad_files_are_refused(tmp_path, capsys):
    """`load_maze`: "" and "paper" are the paper's maze; every shipped maze has free start and goal
    joined by the distance field; a JSON file round-trips; bad files fail with one line naming them."""
    import json

    from experiments.maze_eval import main as maze_main
    from hte_jax.online.maze import load_maze, maze_to_dict, shipped_mazes

    assert load_maze("") == PAPER_MAZE == load_maze("paper")
    assert {"paper", "two_rooms"} <= set(shipped_mazes())
    for name in shipped_mazes():
        maze = load_maze(name)
        start, goal = jnp.asarray(maze.start[:2]), jnp.asarray(maze.goal)
        assert not bool(point_collides(maze, start)) and not bool(point_collides(maze, goal))
        node = GridSpec().node_of(maze, start)
        assert int(distance_field(maze)[node[0], node[1]]) > 0  # reachable, and not already there
    two = load_maze("two_rooms")
    assert two != PAPER_MAZE and bool(move_collides(two, jnp.asarray(two.start[:2]), jnp.asarray(two.goal)))
    path = tmp_path / "mine.json"
    path.write_text(json.dumps(maze_to_dict(two)))
    assert load_maze(str(path)) == two
    bad = {"nowhere": "no such file, and no shipped maze", "{": "cannot read", "[1]": "must hold a JSON object",
           '{"doors": 1}': "unknown maze field", '{"start": [9.0, 1.0, 0.0]}': "must lie within its bounds",
           '{"goal": [1.0]}': "goal \\(x, y\\)", '{"obstacles": [[1, 1, 0, 0]]}': "must be \\(x1, y1, x2, y2\\)"}
    for text, message in bad.items():
        spec = text
        if text != "nowhere":
            spec = str(tmp_path / "bad.json")
            (tmp_path / "bad.json").write_text(text)
        with pytest.raises(ConfigError, match=message):
            load_maze(spec)
    # the CLI: the maze is a setting (config.json), checked before anything runs
    assert maze_main(["--maze", "two_rooms", "--show-config"]) == 0
    assert json.loads(capsys.readouterr().out)["maze"] == "two_rooms"
    assert maze_main(["--maze", "nowhere", "--show-config"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: maze 'nowhere': no such file") and err.count("\n") == 1
