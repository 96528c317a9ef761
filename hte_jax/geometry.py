"""Planar (SE(2)) pose arithmetic, broadcast over leading dimensions; quaternions are (w, x, y, z)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def wrap_angle(angle: jax.Array) -> jax.Array:
    """Angles wrapped to [-pi, pi)."""
    return (angle + jnp.pi) % (2 * jnp.pi) - jnp.pi


def heading(quat: jax.Array) -> jax.Array:
    """(..., 4) quaternion -> (...,) yaw of the body's x axis projected on the floor (rad). A NumPy quaternion
    gives NumPy: its products and sums NumPy's (rounded as jax's eager ops round them), its arctangent XLA's (NumPy's
    differs in the last bit)."""
    w, x, y, z = quat[..., 0], quat[..., 1], quat[..., 2], quat[..., 3]
    yaw = jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.asarray(yaw) if isinstance(quat, np.ndarray) else yaw


def planar_pose(pos: jax.Array, quat: jax.Array, xp=jnp) -> jax.Array:
    """(..., 3) positions and (..., 4) quaternions -> (..., 3) planar poses (x, y, heading) (jax, or NumPy as
    `heading` computes it)."""
    return xp.concatenate([pos[..., :2], heading(quat)[..., None]], axis=-1)


def relative_pose(start: jax.Array, end: jax.Array) -> jax.Array:
    """Planar pose `end` (..., 3) in the frame of `start` (..., 3): (dx, dy, dyaw), dyaw wrapped."""
    c, s = jnp.cos(start[..., 2]), jnp.sin(start[..., 2])
    dx, dy = end[..., 0] - start[..., 0], end[..., 1] - start[..., 1]
    return jnp.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(end[..., 2] - start[..., 2])], axis=-1)


def compose_pose(base: jax.Array, local: jax.Array) -> jax.Array:
    """The pose `local` (..., 3), given in the frame of `base` (..., 3), in the world frame."""
    c, s = jnp.cos(base[..., 2]), jnp.sin(base[..., 2])
    x = base[..., 0] + c * local[..., 0] - s * local[..., 1]
    y = base[..., 1] + s * local[..., 0] + c * local[..., 1]
    return jnp.stack([x, y, wrap_angle(base[..., 2] + local[..., 2])], axis=-1)


def angle_error(displacement: jax.Array) -> jax.Array:
    """Fitness of a planar displacement (..., 3) = (dx, dy, dyaw) in the start frame (Cully et al. 2015): minus
    |dyaw - the final heading of the circular arc from the origin along +x to (dx, dy)|, in [-pi, 0]."""
    ideal = wrap_angle(2 * jnp.arctan2(displacement[..., 1], displacement[..., 0]))  # twice the chord's angle
    return -jnp.abs(wrap_angle(displacement[..., 2] - ideal))


def medoid_index(points: jax.Array) -> jax.Array:
    """(..., N, D) -> (...,) index of the point with the smallest summed distance to the others (ties: lowest)."""
    diff = points[..., :, None, :] - points[..., None, :, :]
    total = jnp.sqrt((diff * diff).sum(-1)).sum(-1)
    return jnp.argmin(total, axis=-1)
