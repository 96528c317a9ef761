"""Generated mazes: a pure function of the seed, solvable by the planner's own distance field, spelled
"random:K" wherever a maze is named; the held-out suite."""

import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.online import maze_gen
from hte_jax.online.maze import (PAPER_MAZE, PAPER_WALLS, GridSpec, Maze, distance_field, in_bounds, load_maze,
                                 move_collides, planning_start, point_collides)
from hte_jax.online.maze_gen import HELD_OUT_MAZES, RANDOM, random_maze, solvable

SEED_0 = Maze(obstacles=((1.81, 0.04, 2.88, 0.92), (3.6, -0.3, 4.06, 2.15), (3.39, 2.48, 4.5, 3.26),
                         (0.83, 1.9, 2.53, 2.9), (2.39, 0.59, 2.97, 2.55)) + PAPER_WALLS,
              start=(0.94, 0.58, float(np.pi)), goal=(2.59, 3.47))


def test_a_seed_gives_one_maze_and_seeds_differ():
    """The same maze on every machine and every call (seed 0 written out: a change of NumPy's streams or of the
    rule shows here); the suite's mazes differ from each other and from the paper's."""
    random_maze.cache_clear()
    assert random_maze(0) == SEED_0
    random_maze.cache_clear()
    assert random_maze(0) == SEED_0 == load_maze("random:0")
    mazes = [load_maze(spec) for spec in HELD_OUT_MAZES]
    assert len(set(mazes)) == len(mazes) and PAPER_MAZE not in mazes
    assert len({maze.start for maze in mazes}) == len(mazes) and len({maze.goal for maze in mazes}) == len(mazes)


def test_held_out_suite_is_solvable_in_the_paper_size_class():
    """Seeds 0..7; each maze has the paper maze's bounds, outer walls and five interior boxes within them, a start
    disc free (the planner starts there) and a goal the straight line cannot reach, joined by the planner's own
    distance field with a detour."""
    assert HELD_OUT_MAZES == tuple(f"random:{k}" for k in range(8))
    grid = GridSpec()  # the planner's (AdaptationConfig.grid)
    room = np.array([-0.2, -0.3, 4.5, 4.0])  # inside PAPER_WALLS
    for spec in HELD_OUT_MAZES:
        maze = load_maze(spec)
        assert maze.bounds == PAPER_MAZE.bounds and maze.obstacles[-len(PAPER_WALLS):] == PAPER_WALLS
        interior = np.array(maze.obstacles[: -len(PAPER_WALLS)])
        assert len(interior) == maze_gen.INTERIOR
        assert (interior[:, :2] >= room[:2]).all() and (interior[:, 2:] <= room[2:]).all()
        start, goal = jnp.asarray(maze.start[:2]), jnp.asarray(maze.goal)
        assert not bool(point_collides(maze, start)) and not bool(point_collides(maze, goal))
        assert bool(in_bounds(maze, jnp.stack([start, goal])).all())
        np.testing.assert_array_equal(planning_start(maze, start), start)
        assert bool(move_collides(maze, start, goal)) and float(jnp.linalg.norm(goal - start)) >= maze_gen.SEPARATION
        field = np.asarray(distance_field(maze, grid))
        (si, sj), (gi, gj) = np.asarray(grid.node_of(maze, start)), np.asarray(grid.node_of(maze, goal))
        assert field[si, sj] >= max(abs(si - gi), abs(sj - gj)) + maze_gen.DETOUR, spec
        assert solvable(maze)


def test_unsolvable_draws_are_rejected_and_a_seed_without_a_maze_is_an_error(monkeypatch):
    """`solvable` refuses a goal walled off from the start and a start inside a box; a seed whose draws all fail
    is a ConfigError."""
    walled = dataclasses.replace(SEED_0, obstacles=SEED_0.obstacles + ((-0.2, 2.0, 4.5, 2.3),))  # across the room
    assert solvable(SEED_0) and not solvable(walled)
    assert not solvable(dataclasses.replace(SEED_0, start=(2.0, 0.5, 0.0)))  # inside the first box
    random_maze.cache_clear()
    monkeypatch.setattr(maze_gen, "ATTEMPTS", 3)
    monkeypatch.setattr(maze_gen, "solvable", lambda maze: False)
    with pytest.raises(ConfigError, match="random:123: no solvable maze in 3 draws"):
        random_maze(123)


@pytest.mark.parametrize("spec", ["random:-1", "random:x", "random:", "random: 3", "random:1.5", "random:+2"])
def test_bad_seed_spellings_are_one_line_errors(spec):
    with pytest.raises(ConfigError, match="random:K needs a seed K, an integer >= 0") as error:
        load_maze(spec)
    assert "\n" not in str(error.value) and repr(spec) in str(error.value)


def test_the_spelling_through_the_config_and_the_commands(tmp_path, capsys):
    """EvalConfig keeps the spelling (config.json, so a resumed run draws the same maze) and runs its maze;
    maze_eval prints it and refuses a bad seed with exit 2; maze_gen writes the maze as a maze file."""
    from experiments.maze_eval import main as maze_main
    from hte_jax.online.evaluation import EvalConfig

    config = EvalConfig(maze="random:3")
    assert config.maze_task == random_maze(3) and config.to_dict()["maze"] == "random:3"
    assert maze_main(["--maze", "random:3", "--show-config"]) == 0
    assert json.loads(capsys.readouterr().out)["maze"] == "random:3"
    assert maze_main(["--maze", "random:x", "--show-config"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: maze 'random:x': random:K needs a seed") and err.count("\n") == 1
    path = tmp_path / "three.json"
    assert maze_gen.main(["3", "--out", str(path)]) == 0
    assert load_maze(str(path)) == random_maze(3)
    assert maze_gen.main(["3"]) == 0 and json.loads(capsys.readouterr().out) == json.loads(path.read_text())
    assert maze_gen.main(["-1"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_a_generated_maze_draws():
    """`plots.draw_maze` draws every box, the bounds and the goal of a generated maze."""
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Rectangle

    from hte_jax.online.plots import draw_maze

    maze = load_maze(RANDOM + "5")
    fig, ax = plt.subplots()
    draw_maze(ax, maze)
    rectangles = [p for p in ax.patches if isinstance(p, Rectangle)]
    assert len(rectangles) == len(maze.obstacles) + 1 and sum(isinstance(p, Circle) for p in ax.patches) == 1
    plt.close(fig)
