"""The maze of the paper's experiment and the planner's 2-D geometry (`docs/design.md`, Maze): boxes
(x1, y1, x2, y2), a disc-shaped robot, and the grid distance field that guides the planner's expansion.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.errors import ConfigError, check_fields, number
from hte_jax.numerics import quotient

Box = tuple[float, float, float, float]

PAPER_BOXES: tuple[Box, ...] = ((-0.20, 3.06, 0.75, 4.00), (2.20, -0.30, 2.70, 0.625), (1.73, 1.84, 2.73, 2.34),
                                 (2.73, 1.84, 3.23, 2.84), (3.15, 1.84, 4.50, 4.04))
PAPER_WALLS: tuple[Box, ...] = ((-0.2, -0.31, 4.5, -0.3), (-0.21, -0.3, -0.2, 4.0), (4.5, -0.3, 4.51, 4.0),
                                (-0.2, 4.0, 4.5, 4.01))


@dataclasses.dataclass(frozen=True)
class Maze:
    """A navigation task (static, hashable). obstacles: boxes (x1, y1, x2, y2) in metres. bounds: (x_min,
    y_min, x_max, y_max) of the planner's map (leaving it fails). start: (x, y, yaw). goal: (x, y), reached
    within goal_radius. robot_radius: the planner's disc."""

    obstacles: tuple[Box, ...] = PAPER_BOXES + PAPER_WALLS
    bounds: Box = (0.0, 0.0, 4.5, 4.0)
    start: tuple[float, float, float] = (2.32, 3.27, float(np.pi))
    goal: tuple[float, float] = (3.79, 0.424)
    goal_radius: float = number(0.25, 0.0, open_low=True)
    robot_radius: float = number(0.25, 0.0)

    def __post_init__(self):
        for box in (*self.obstacles, self.bounds):
            if len(box) != 4 or not (box[0] < box[2] and box[1] < box[3]):
                raise ConfigError(f"box {box!r} must be (x1, y1, x2, y2) with x1 < x2 and y1 < y2")
        check_fields(self)

    @property
    def boxes(self) -> np.ndarray:
        return np.asarray(self.obstacles, np.float32).reshape(-1, 4)


PAPER_MAZE = Maze()
MAZE_FIELDS = tuple(field.name for field in dataclasses.fields(Maze))


def maze_to_dict(maze: Maze) -> dict:
    """The JSON layout of a maze (boxes as lists)."""
    return dataclasses.asdict(maze)


def maze_from_dict(data: dict) -> Maze:
    """The maze of `maze_to_dict`'s layout; missing fields take the paper maze's values."""
    unknown = sorted(set(data) - set(MAZE_FIELDS))
    if unknown:
        raise ConfigError(f"unknown maze field(s) {', '.join(unknown)}; the fields are {', '.join(MAZE_FIELDS)}")
    try:
        fields = {key: tuple(tuple(float(v) for v in box) for box in value) if key == "obstacles"
                  else tuple(float(v) for v in value) if key in ("bounds", "start", "goal") else value
                  for key, value in data.items()}
        maze = Maze(**fields)
    except (TypeError, ValueError) as error:
        raise ConfigError(f"bad maze: {error}") from None
    if len(maze.start) != 3 or len(maze.goal) != 2:
        raise ConfigError(f"maze start must be (x, y, yaw) and goal (x, y), got {maze.start} and {maze.goal}")
    return maze


def shipped_mazes() -> dict[str, Path]:
    """The mazes shipped in assets/mazes/, by name."""
    from hte_jax.sim.robot import assets_dir

    return {path.stem: path for path in sorted((assets_dir() / "mazes").glob("*.json"))}


def load_maze(spec: str) -> Maze:
    """The maze `spec` names: "" (the paper's), "random:K" (the generated maze of seed K, `maze_gen.random_maze`),
    a shipped maze's name or a JSON file."""
    if not spec:
        return PAPER_MAZE
    from hte_jax.online.maze_gen import RANDOM, parse_random, random_maze  # maze_gen builds on this module

    if spec.startswith(RANDOM):
        return random_maze(parse_random(spec))
    shipped = shipped_mazes()
    path = shipped.get(spec, Path(spec))
    if not path.is_file():
        raise ConfigError(f"maze {spec!r}: no such file, and no shipped maze of that name ({', '.join(shipped)})")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ConfigError(f"maze {spec!r}: cannot read {path}: {error}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"maze {spec!r}: {path} must hold a JSON object of maze fields")
    try:
        maze = maze_from_dict(data)
    except ConfigError as error:
        raise ConfigError(f"maze {spec!r}: {error}") from None
    if not in_bounds(maze, np.array([maze.start[:2], maze.goal])).all():  # the episodes' own rule
        raise ConfigError(f"maze {spec!r}: start and goal must lie within its bounds {maze.bounds}")
    return maze


def point_box_distance(points: jax.Array, boxes: np.ndarray, xp=jnp) -> jax.Array:
    """(..., 2) points, (K, 4) boxes -> (..., K) Euclidean distance to each box (0 inside). Jax (xp=jnp) or
    NumPy (float32 points: the same values)."""
    p = points[..., None, :]
    low, high = xp.asarray(boxes[:, :2]), xp.asarray(boxes[:, 2:])
    gap = xp.maximum(xp.maximum(low - p, p - high), 0.0)
    return xp.sqrt(xp.sum(gap * gap, axis=-1))


def _point_segment_distance(points: jax.Array, a: jax.Array, b: jax.Array, xp=jnp) -> jax.Array:
    """points (..., M, 2) to segments a, b (..., 2) -> (..., M)."""
    ab, ap = (b - a)[..., None, :], points - a[..., None, :]
    t = xp.clip(quotient(xp.sum(ap * ab, -1), xp.maximum(xp.sum(ab * ab, -1), 1e-12), xp), 0.0, 1.0)
    d = ap - t[..., None] * ab
    return xp.sqrt(xp.sum(d * d, axis=-1))


def _segment_crosses_box(a: jax.Array, b: jax.Array, boxes: np.ndarray, xp=jnp) -> jax.Array:
    """Slab test: does segment a-b (..., 2) meet each box? -> (..., K)."""
    low, high = xp.asarray(boxes[:, :2]), xp.asarray(boxes[:, 2:])
    a, d = a[..., None, :], (b - a)[..., None, :]
    safe = xp.where(xp.abs(d) < 1e-12, 1e-12, d)
    t1, t2 = quotient(low - a, safe, xp), quotient(high - a, safe, xp)
    inside = (a >= low) & (a <= high)  # for axis-parallel segments
    t_near = xp.where(xp.abs(d) < 1e-12, xp.where(inside, -xp.inf, xp.inf), xp.minimum(t1, t2))
    t_far = xp.where(xp.abs(d) < 1e-12, xp.where(inside, xp.inf, -xp.inf), xp.maximum(t1, t2))
    enter, leave = xp.max(t_near, axis=-1), xp.min(t_far, axis=-1)
    return (enter <= leave) & (leave >= 0.0) & (enter <= 1.0)


def segment_box_distance(a: jax.Array, b: jax.Array, boxes: np.ndarray, xp=jnp) -> jax.Array:
    """(..., 2) segment ends, (K, 4) boxes -> (..., K) distance (0 if they meet; else at an end or a corner).
    Jax (xp=jnp) or NumPy (float32 ends: the same values)."""
    ends = xp.minimum(point_box_distance(a, boxes, xp), point_box_distance(b, boxes, xp))
    corners = xp.stack([boxes[:, [0, 1]], boxes[:, [0, 3]], boxes[:, [2, 1]], boxes[:, [2, 3]]], axis=1)  # (K, 4, 2)
    flat = xp.asarray(corners.reshape(-1, 2))
    batch = a.shape[:-1]
    to_corners = _point_segment_distance(xp.broadcast_to(flat, (*batch, *flat.shape)), a, b, xp)
    to_corners = to_corners.reshape(*batch, boxes.shape[0], 4).min(axis=-1)
    return xp.where(_segment_crosses_box(a, b, boxes, xp), 0.0, xp.minimum(ends, to_corners))


def point_collides(maze: Maze, points: jax.Array, radius: float | None = None, xp=jnp) -> jax.Array:
    """(..., 2) -> (...,) the disc overlaps an obstacle (jax or NumPy)."""
    radius = maze.robot_radius if radius is None else radius
    return xp.any(point_box_distance(points, maze.boxes, xp) < radius, axis=-1)


def move_collides(maze: Maze, start: jax.Array, end: jax.Array, radius: float | None = None, xp=jnp) -> jax.Array:
    """(..., 2), (..., 2) -> (...,) the disc swept from start to end overlaps an obstacle (jax or NumPy)."""
    radius = maze.robot_radius if radius is None else radius
    return xp.any(segment_box_distance(start, end, maze.boxes, xp) < radius, axis=-1)


def in_bounds(maze: Maze, points: jax.Array) -> jax.Array:
    x0, y0, x1, y1 = maze.bounds
    return (points[..., 0] >= x0) & (points[..., 0] < x1) & (points[..., 1] >= y0) & (points[..., 1] < y1)


def reached_goal(maze: Maze, points: jax.Array) -> jax.Array:
    return jnp.linalg.norm(points - jnp.asarray(maze.goal), axis=-1) < maze.goal_radius


# Offsets tried when the robot stands where the planner's disc overlaps an obstacle (`docs/original_code.md` §9).
_ESCAPES = np.array(sorted(((dx, dy) for dx in (-0.5, 0.0, 0.5) for dy in (-0.5, 0.0, 0.5)),
                           key=lambda o: (o[0] ** 2 + o[1] ** 2, o)), np.float32)


def planning_start(maze: Maze, points: jax.Array) -> jax.Array:
    """(..., 2) measured positions -> (..., 2) the planner's start: the nearest free on-map point among the
    position and its +-0.5 m offsets (the original's rule), else the position itself."""
    offsets = jnp.asarray(_ESCAPES)  # (9, 2), (0, 0) first
    tries = points[..., None, :] + offsets
    free = ~point_collides(maze, tries) & in_bounds(maze, tries)
    first = jnp.argmax(free, axis=-1)
    chosen = jnp.take_along_axis(tries, first[..., None, None], axis=-2)[..., 0, :]
    return jnp.where(free.any(axis=-1)[..., None], chosen, points)


@dataclasses.dataclass(frozen=True)
class GridSpec:
    """A planning grid over the maze bounds: node (i, j) at (x_min + i cell, y_min + j cell)."""

    cell: float = 0.5
    radius_factor: float = 1.3  # steps blocked for a disc of radius_factor * robot_radius (the A*'s inflation)

    def shape(self, maze: Maze) -> tuple[int, int]:
        x0, y0, x1, y1 = maze.bounds
        return int(np.floor((x1 - x0) / self.cell + 1e-9)), int(np.floor((y1 - y0) / self.cell + 1e-9))

    def nodes(self, maze: Maze) -> np.ndarray:
        nx, ny = self.shape(maze)
        i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
        return np.stack([maze.bounds[0] + i * self.cell, maze.bounds[1] + j * self.cell], -1).astype(np.float32)

    def node_of(self, maze: Maze, points: jax.Array, xp=jnp) -> jax.Array:
        """(..., 2) float32 points -> (..., 2) int32 indices of their nearest nodes (jax or NumPy)."""
        nx, ny = self.shape(maze)
        ij = xp.round((points - xp.asarray(maze.bounds[:2], xp.float32)) / self.cell).astype(xp.int32)
        return xp.clip(ij, 0, xp.asarray([nx - 1, ny - 1], xp.int32))


NEIGHBOURS = np.array([(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0)], np.int32)


def edge_free(maze: Maze, grid: GridSpec) -> np.ndarray:
    """(nx, ny, 8) bool: the step from each node to each neighbour stays free and on the grid (NumPy)."""
    nodes = grid.nodes(maze)
    nx, ny = nodes.shape[:2]
    radius = grid.radius_factor * maze.robot_radius
    targets = (nodes[:, :, None, :] + NEIGHBOURS[None, None] * grid.cell).astype(np.float32)
    ij = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij"), -1)[:, :, None, :] + NEIGHBOURS
    on_grid = (ij[..., 0] >= 0) & (ij[..., 0] < nx) & (ij[..., 1] >= 0) & (ij[..., 1] < ny)
    start = np.broadcast_to(nodes[:, :, None, :], targets.shape)
    return on_grid & ~move_collides(maze, start, targets, radius, xp=np)


def distance_field(maze: Maze, grid: GridSpec = GridSpec()) -> jax.Array:
    """(nx, ny) int32 fewest grid steps from each node to the goal's node (-1 if unreachable)."""
    free = edge_free(maze, grid)
    nx, ny = free.shape[:2]
    padded_index = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij"), -1)[:, :, None, :] + NEIGHBOURS
    neighbour = np.clip(padded_index, 0, np.array([nx - 1, ny - 1])).astype(np.int32)
    goal = grid.node_of(maze, np.asarray(maze.goal, np.float32), xp=np)
    return _grid_steps(free, neighbour, goal)


@jax.jit
def _grid_steps(free: jax.Array, neighbour: jax.Array, goal: jax.Array) -> jax.Array:
    """Bellman-Ford relaxation of unit steps over the free edges (nx, ny, 8), neighbour indices (nx, ny, 8, 2),
    from the goal node (2,); compiled once per grid shape."""
    nx, ny = free.shape[:2]
    unreached = nx * ny + 1
    dist = jnp.full((nx, ny), unreached, jnp.int32).at[goal[0], goal[1]].set(0)
    ni, nj = neighbour[..., 0], neighbour[..., 1]

    def relax(_, d):
        through = jnp.where(free, d[ni, nj] + 1, unreached)  # step i->neighbour is free both ways
        return jnp.minimum(d, through.min(axis=-1))

    dist = jax.lax.fori_loop(0, nx * ny, relax, dist)
    return jnp.where(dist >= unreached, -1, dist)
