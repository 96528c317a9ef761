"""Videos of recorded maze episodes (`online.recording.Replay`) replayed from above or tracked, with trail and text."""

from __future__ import annotations

import mujoco
import numpy as np

from hte_jax.errors import ConfigError, require_choice, require_int
from hte_jax.online.arena import maze_config
from hte_jax.hbr.hierarchy import STEPS_PER_SKILL
from hte_jax.online.action import SECONDS_PER_ACTION
from hte_jax.online.recording import Replay
from hte_jax.sim.robot import RobotConfig
from hte_jax.viz.camera import CAMERAS, Camera
from hte_jax.viz.render import damaged, label, open_renderer, render_frames, render_spec

GOAL_RGBA = (0.1, 0.75, 0.25, 0.7)
TRAIL_RGBA = (0.1, 0.3, 0.95, 1.0)
TRAIL_WIDTH = 0.015  # m
PANEL_RGB = (245, 245, 245)
PANEL_WIDTH = 96  # pixels, at least, of the text panel beside a top view
MARGIN = 0.1  # m of floor shown around the maze


def maze_region(replay: Replay) -> tuple[float, float, float, float]:
    """(x1, y1, x2, y2) the top view shows: the maze's bounds and walls, plus a margin."""
    boxes = np.asarray([*replay.maze.obstacles, replay.maze.bounds], np.float64)
    return (*(boxes[:, :2].min(axis=0) - MARGIN), *(boxes[:, 2:].max(axis=0) + MARGIN))


def episode_model(replay: Replay, view_extent: float | None = None) -> mujoco.MjModel:
    """The maze robot's render model with the goal disc; orthographic showing `view_extent` (m) high, or None."""
    maze = replay.maze
    config = maze_config(maze, RobotConfig())  # the render draws recorded states: no damage model acts
    damage = replay.robot_damage
    spec = render_spec(config, damage, checks=2.0)
    spec.worldbody.add_geom(name="goal", type=mujoco.mjtGeom.mjGEOM_CYLINDER, pos=[*maze.goal, 0.002],
                            size=[maze.goal_radius, 0.002, 0.0], contype=0, conaffinity=0, rgba=list(GOAL_RGBA))
    if view_extent is not None:
        spec.visual.global_.orthographic = True
        spec.visual.global_.fovy = view_extent
    return damaged(spec.compile(), config, damage)


def frame_states(replay: Replay, stride: int) -> np.ndarray:
    """Indices of the recorded states shown: every `stride`-th, and the last."""
    require_int("stride", stride)
    last = replay.qpos.shape[0] - 1
    states = np.arange(0, last + 1, stride)
    return states if states[-1] == last else np.append(states, last)


def frame_text(replay: Replay, state: int) -> str:
    """The panel's lines for recorded state `state`."""
    info = replay.info
    per_second = replay.states_per_action // SECONDS_PER_ACTION
    lines = [info["variant"], f"damage: {info['damage']}"]
    seconds = f"{state * replay.every / 100:.0f} s"
    if state == replay.qpos.shape[0] - 1:
        outcome = "reached the goal" if info["reached"] else "flipped over" if info["broken"] else "goal not reached"
        return "\n".join([*lines, outcome, f"in {replay.actions} actions", seconds])
    action, within = divmod(state, replay.states_per_action)
    second = within // per_second
    lines += [f"action {action + 1} / {info['max_actions']}", f"skill {int(replay.action[action])}"]
    if second == STEPS_PER_SKILL:
        lines += ["neutral pose", ""]
    elif info.get("hierarchical", True):
        pattern = int(replay.patterns[action, second])
        lines += [f"step {second + 1}: pattern", "any" if pattern < 0 else f"{pattern} = {pattern:06b}"]
    else:
        lines += [f"second {second + 1}", ""]
    return "\n".join([*lines, seconds])


def _two_lines(lines: list[str]) -> str:
    return "  ".join(lines[:3]) + "\n" + "  ".join(line for line in lines[3:] if line)


def _trail(replay: Replay, states: np.ndarray):
    """decorate(t, scene) drawing the base's path up to frame t (its pose after every second, then now)."""
    per_second = replay.states_per_action // SECONDS_PER_ACTION
    seconds = replay.trajectory[:, :2].astype(np.float64)
    base = replay.qpos[:, :2].astype(np.float64)

    def decorate(t: int, scene: mujoco.MjvScene) -> None:
        state = int(states[t])
        points = np.concatenate([seconds[: state // per_second + 1], base[state][None]])
        for a, b in zip(points[:-1], points[1:]):
            if scene.ngeom >= scene.maxgeom:
                return
            if np.array_equal(a, b):
                continue
            geom = scene.geoms[scene.ngeom]
            mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, np.zeros(3), np.zeros(3), np.eye(3).ravel(),
                                np.asarray(TRAIL_RGBA, np.float32))
            mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, TRAIL_WIDTH, np.append(a, 0.01), np.append(b, 0.01))
            scene.ngeom += 1

    return decorate


def render_episode(replay: Replay, width: int, height: int, camera: str = "top", stride: int = 1, hold: int = 0,
                   progress=None) -> np.ndarray:
    """Frames (T, height, width, 3) uint8 of every `stride`-th state (and the last, `hold` more times)."""
    require_choice("camera", camera, CAMERAS)
    require_int("width", width)
    require_int("height", height)
    require_int("hold", hold, 0)
    states = frame_states(replay, stride)
    if camera == "top":
        x1, y1, x2, y2 = maze_region(replay)
        panel = max(width - round(height * (x2 - x1) / (y2 - y1)), PANEL_WIDTH) if width >= 3 * PANEL_WIDTH else 0
        view = Camera("top", distance=10.0, centre=((x1 + x2) / 2, (y1 + y2) / 2))
        model = episode_model(replay, max(y2 - y1, (x2 - x1) * height / (width - panel)))
    else:
        panel, view, model = 0, Camera("track", distance=1.5), episode_model(replay)
    if width - panel < 1:
        raise ConfigError(f"width {width} leaves no room for the maze")
    renderer = open_renderer(model, width - panel, height)
    try:
        frames = render_frames(model, replay.qpos[states], renderer, view, progress, decorate=_trail(replay, states))
    finally:
        renderer.close()
    texts = [frame_text(replay, int(state)) for state in states]
    if panel:
        canvas = np.empty((len(frames), height, width, 3), np.uint8)
        canvas[:, :, :panel] = PANEL_RGB
        canvas[:, :, panel:] = frames
        frames = label(canvas, texts)
    else:  # over the frame: two lines across its top
        frames = label(frames, [_two_lines(text.split("\n")) for text in texts], background=PANEL_RGB)
    return np.concatenate([frames, np.repeat(frames[-1:], hold, axis=0)])
