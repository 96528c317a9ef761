"""The maze in MJX: a robot model with the maze's walls (met by a bumper of the planner's robot radius),
and damaged robots standing at the start (`docs/design.md`, The maze in MJX).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.geometry import heading
from hte_jax.online.maze import Maze
from hte_jax.sim.damage import Damage, damage_legs
from hte_jax.sim.robot import Robot, RobotConfig, load_robot
from hte_jax.sim.env import SimState
from hte_jax.sim.rollout import standing_state


def maze_config(maze: Maze, base: RobotConfig = RobotConfig()) -> RobotConfig:
    """`base` with the maze's boxes as walls and a bumper of the planner's robot radius."""
    return dataclasses.replace(base, walls=maze.obstacles, wall_contact="bumper", bumper_radius=maze.robot_radius,
                               body_floor_contact=True)


def maze_robot(maze: Maze, base: RobotConfig = RobotConfig()) -> Robot:
    return load_robot(maze_config(maze, base))


def _cos_sin(angle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(B, 1) cosines and sines of angles (B,) by XLA (NumPy's differ in the last bit)."""
    return np.asarray(jnp.cos(angle))[:, None], np.asarray(jnp.sin(angle))[:, None]


def _yaw_quaternion(yaw: np.ndarray) -> np.ndarray:
    c, s = _cos_sin(yaw / 2)
    return np.concatenate([c, np.zeros_like(c), np.zeros_like(c), s], axis=-1)


def _quaternion_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def place(state: SimState, pose: np.ndarray) -> SimState:
    """Move robots `state` (B, ...) to planar poses `pose` (B, 3) (x, y, heading), turning the quaternion,
    world-frame linear velocity and its warm start about the vertical axis (the rest is unchanged). On the host:
    NumPy's float32 arithmetic rounds as jax's eager ops do; XLA gives the arctangent, cosines and sines (three
    small programs, not one per operation)."""
    qpos, qvel, warm = (np.asarray(x) for x in (state.qpos, state.qvel, state.qacc_warmstart))
    pose = np.asarray(pose, np.float32)
    turn = pose[:, 2] - heading(qpos[:, 3:7])
    c, s = _cos_sin(turn)

    def rotate(v):
        return np.concatenate([c * v[:, :1] - s * v[:, 1:2], s * v[:, :1] + c * v[:, 1:2], v[:, 2:]], axis=-1)

    quat = _quaternion_product(_yaw_quaternion(turn), qpos[:, 3:7])
    qpos = np.concatenate([pose[:, :2], qpos[:, 2:3], quat, qpos[:, 7:]], axis=-1)
    qvel = np.concatenate([rotate(qvel[:, :3]), qvel[:, 3:]], axis=-1)
    warm = np.concatenate([rotate(warm[:, :3]), warm[:, 3:]], axis=-1)
    return jax.device_put(SimState(qpos=qpos, qvel=qvel, qacc_warmstart=warm))


def start_states(maze: Maze, damages: jax.Array | Damage, base: RobotConfig = RobotConfig()) -> SimState:
    """Robots with damages (a (B, 6) bool leg mask under `base.damage_model`, or a `Damage` (B, ...)), settled
    standing (away from walls) and placed at the maze's start."""
    damages = damages if isinstance(damages, Damage) else np.asarray(damages, bool)
    plain = load_robot(dataclasses.replace(base, walls=()))
    settled = standing_state(plain, damages)
    pose = np.broadcast_to(np.asarray(maze.start, np.float32), (np.shape(damage_legs(damages))[0], 3))
    return place(settled, pose)
