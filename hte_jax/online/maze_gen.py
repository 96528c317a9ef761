"""Generated mazes of the paper maze's size class (`docs/design.md`, Maze): `random_maze(seed)`, spelled
"random:K" wherever a maze is named (`maze.load_maze`), and the held-out suite `HELD_OUT_MAZES`.

    python -m hte_jax.online.maze_gen 3 --out maze.json   # the maze of "random:3" as JSON (stdout without --out)
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import re
import sys
from pathlib import Path

import numpy as np

from hte_jax.errors import ConfigError
from hte_jax.online.maze import (PAPER_MAZE, PAPER_WALLS, GridSpec, Maze, distance_field, maze_to_dict,
                                 move_collides, point_collides)

RANDOM = "random:"  # the spelling's prefix: "random:K", K a seed >= 0
HELD_OUT_MAZES = tuple(f"{RANDOM}{k}" for k in range(8))  # the first eight seeds; no setting is tuned on them

ROOM = (PAPER_WALLS[1][2], PAPER_WALLS[0][3], PAPER_WALLS[2][0], PAPER_WALLS[3][1])  # inside the outer walls
INTERIOR = 5  # interior boxes, as many as the paper maze's
LONG_SIDE, SHORT_SIDE = (0.8, 2.4), (0.3, 1.0)  # m
ATTACHED = 0.5  # chance that a box juts out of an outer wall (perpendicular to it) instead of standing free
CLEARANCE = 0.2  # m of floor beyond the robot's disc around the start and the goal
SEPARATION = 2.5  # m, the least straight-line distance from the start to the goal
DETOUR = 2  # grid steps the planner's path to the goal takes at least beyond an open room's
POINT_TRIES = 64  # candidate points per start or goal draw
ATTEMPTS = 500  # mazes drawn per seed before giving up


def parse_random(spec: str) -> int:
    """The seed K of a maze spelled "random:K" (ConfigError unless K is a non-negative integer)."""
    text = spec.removeprefix(RANDOM)
    if not re.fullmatch(r"[0-9]+", text):
        raise ConfigError(f"maze {spec!r}: {RANDOM}K needs a seed K, an integer >= 0")
    return int(text)


@functools.lru_cache(maxsize=256)
def start_steps(maze: Maze, grid: GridSpec = GridSpec()) -> int:
    """The planner's distance field on `grid` (its default: the planner's) at the start's node: grid steps to
    the goal's node, -1 if unreachable (kept per maze and grid: `solvable` and `detour` both ask)."""
    node = grid.node_of(maze, np.asarray(maze.start[:2], np.float32), xp=np)
    return int(np.asarray(distance_field(maze, grid))[node[0], node[1]])


def solvable(maze: Maze, grid: GridSpec = GridSpec()) -> bool:
    """The robot's disc stands free at the start and at the goal, and the planner's distance field leads from
    the start's node to the goal's, at least one step."""
    ends = np.asarray([maze.start[:2], maze.goal], np.float32)
    return not bool(point_collides(maze, ends, xp=np).any()) and start_steps(maze, grid) > 0


def detour(maze: Maze, grid: GridSpec = GridSpec()) -> int:
    """Grid steps of the planner's path from the start's node to the goal's beyond those of an open room (the
    larger of the two index differences)."""
    start, goal = (grid.node_of(maze, np.asarray(p, np.float32), xp=np) for p in (maze.start[:2], maze.goal))
    return start_steps(maze, grid) - int(np.abs(start - goal).max())


def _box(rng: np.random.Generator) -> tuple[float, ...]:
    """An interior box: jutting out of a random outer wall or standing free inside the bounds."""
    x0, y0, x1, y1 = PAPER_MAZE.bounds
    long, short = rng.uniform(*LONG_SIDE), rng.uniform(*SHORT_SIDE)
    if rng.uniform() < ATTACHED:
        side = rng.integers(4)  # left, bottom, right, top
        if side in (0, 2):  # horizontal, from the left or the right wall
            y = rng.uniform(y0, y1 - short)
            box = (ROOM[0], y, x0 + long, y + short) if side == 0 else (x1 - long, y, ROOM[2], y + short)
        else:  # vertical, from the bottom or the top wall
            x = rng.uniform(x0, x1 - short)
            box = (x, ROOM[1], x + short, y0 + long) if side == 1 else (x, y1 - long, x + short, ROOM[3])
    else:
        w, h = (long, short) if rng.uniform() < 0.5 else (short, long)
        x, y = rng.uniform(x0, x1 - w), rng.uniform(y0, y1 - h)
        box = (x, y, x + w, y + h)
    return tuple(round(float(v), 2) for v in box)


def _free_point(rng: np.random.Generator, maze: Maze, away_from=None) -> tuple[float, float] | None:
    """The first of POINT_TRIES uniform points (cm) with CLEARANCE around the robot's disc (and SEPARATION from
    `away_from`), or None."""
    margin = maze.robot_radius + CLEARANCE
    x0, y0, x1, y1 = maze.bounds
    points = np.round(rng.uniform((x0 + margin, y0 + margin), (x1 - margin, y1 - margin), (POINT_TRIES, 2)), 2)
    ok = ~point_collides(maze, points.astype(np.float32), margin, xp=np)
    if away_from is not None:
        ok &= np.linalg.norm(points - np.asarray(away_from), axis=-1) >= SEPARATION
    return tuple(float(v) for v in points[np.argmax(ok)]) if ok.any() else None


def _draw(rng: np.random.Generator) -> Maze | None:
    """One candidate maze of the paper's bounds, walls, radii and INTERIOR boxes, with a free start (yaw a
    multiple of 45 degrees) and a goal SEPARATION away whose straight line the robot's disc cannot follow; None
    when the draw finds no such start and goal."""
    maze = dataclasses.replace(PAPER_MAZE, obstacles=tuple(_box(rng) for _ in range(INTERIOR)) + PAPER_WALLS)
    start = _free_point(rng, maze)
    goal = None if start is None else _free_point(rng, maze, start)
    if goal is None:
        return None
    yaw = float(rng.integers(8) * np.pi / 4)
    maze = dataclasses.replace(maze, start=(*start, yaw), goal=goal)
    blocked = move_collides(maze, np.asarray(start, np.float32), np.asarray(goal, np.float32), xp=np)
    return maze if bool(blocked) else None


@functools.lru_cache(maxsize=64)
def random_maze(seed: int) -> Maze:
    """The maze of `seed`: the first of the candidate mazes drawn in turn from `np.random.default_rng(seed)` that
    is `solvable` with a `detour` of DETOUR steps at least (ATTEMPTS draws at most; ConfigError past them)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"maze seed must be an integer >= 0, got {seed!r}")
    rng = np.random.default_rng(seed)
    for _ in range(ATTEMPTS):
        maze = _draw(rng)
        if maze is not None and solvable(maze) and detour(maze) >= DETOUR:
            return maze
    raise ConfigError(f"maze {RANDOM}{seed}: no solvable maze in {ATTEMPTS} draws; choose another seed")


def main(argv=None) -> int:
    """Print or write the maze of "random:K" as JSON (the layout of assets/mazes/), one box a line."""
    p = argparse.ArgumentParser(description="Write the generated maze of a seed as JSON (a maze file of load_maze).")
    p.add_argument("seed", help="K of random:K, an integer >= 0")
    p.add_argument("--out", default=None, help="JSON file to write (default: stdout)")
    args = p.parse_args(argv)
    try:
        data = maze_to_dict(random_maze(parse_random(RANDOM + args.seed)))
    except ConfigError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    boxes = ",\n  ".join(json.dumps(box) for box in data.pop("obstacles"))
    fields = "".join(f",\n {json.dumps(key)}: {json.dumps(value)}" for key, value in data.items())
    text = f'{{\n "obstacles": [\n  {boxes}]{fields}\n}}\n'
    if args.out is None:
        print(text, end="")
    else:
        Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
