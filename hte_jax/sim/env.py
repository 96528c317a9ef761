"""The hexapod environment's step, one pure function for every path that simulates the robot: the controller's
joint targets -> tilt reflex -> damage -> servo (`control`) -> MJX physics -> validity (`step`). `control` runs
under jax or NumPy (`xp`): the rollout (`hte_jax.sim.rollout`, a `lax.scan` of `step`) and the host-driven
robots (`hte_jax.online.external`, native MuJoCo physics) share it. The settled start state is
`rollout.standing_state` (the environment's reset)."""

from __future__ import annotations

import dataclasses
import enum
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hte_jax.sim.controller import servo_command
from hte_jax.sim.damage import Damage, held_targets
from hte_jax.sim.mjx_import import mjx
from hte_jax.sim.robot import Robot, RobotConfig


class InvalidReason(enum.IntFlag):
    """Bits of a robot's invalid reason (`RolloutResult.invalid_reason`)."""

    NON_FINITE = 1  # NaN or inf in qpos / qvel
    EXPLODED = 2  # some |qvel| above ValidityLimits.max_speed
    FLIPPED = 4  # body tilted more than ValidityLimits.max_tilt
    HEIGHT = 8  # base height outside [min_base_height, max_base_height]
    BODY_ON_FLOOR = 16  # a corner of the body box below the floor (only feet collide with it)
    WARP_OVERFLOW = 32  # MuJoCo Warp dropped contacts or constraint rows: a buffer too small (impl "warp")


@dataclasses.dataclass(frozen=True)
class ValidityLimits:
    """When a state is invalid."""

    max_tilt: float = math.pi / 4  # rad between the body's and the world's z axes
    min_base_height: float = 0.04  # m (the belly touches the floor at 0.021; gaits stay above 0.079)
    max_base_height: float = 1.0  # m
    max_speed: float = 100.0  # largest |qvel| entry
    body_on_floor: bool = True  # a body corner below the floor is invalid (off with `RobotConfig.body_floor_contact`)


@struct.dataclass
class SimState:
    """Physical state of robots (any leading batch shape): qpos (..., 25) base position, quaternion w-x-y-z, 18
    joint angles (leg-major); qvel (..., 24) base linear (world) and angular (body) velocity, 18 joint rates;
    qacc_warmstart (..., 24) the solver's warm start (carried, chained rollouts equal one long rollout)."""

    qpos: jax.Array
    qvel: jax.Array
    qacc_warmstart: jax.Array


# Bottom corners of the body box in the body frame (half sizes 0.114 x 0.0905 x 0.021).
_BODY_BOTTOM = np.array([[sx * 0.114, sy * 0.0905, -0.021] for sx in (-1, 1) for sy in (-1, 1)], np.float32)


def _world_z_of(qpos: jax.Array, points: np.ndarray) -> jax.Array:
    """World height of body-frame points (N, 3) for a base pose qpos[:7] (unit quaternion)."""
    w, x, y, z = qpos[3], qpos[4], qpos[5], qpos[6]
    row_z = jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)])
    return qpos[2] + points @ row_z


def up_z(qpos):
    """World z of the body's z axis (cosine of its tilt) for a base pose qpos[:7] (jax or NumPy)."""
    return 1.0 - 2.0 * (qpos[4] ** 2 + qpos[5] ** 2)


def reflex_braced(braced, fresh, qpos, config: RobotConfig):
    """Whether the tilt reflex (`RobotConfig.reflex_*`) holds the neutral pose after this step's check: `braced`
    whether it held it, `fresh` whether a controller segment starts now (it lets go). Jax or NumPy (np.bool_)."""
    cos_tilt = up_z(qpos)
    braced = braced & ~fresh
    if config.reflex_release > 0.0:  # back below the release angle: the gait resumes
        braced = braced & (cos_tilt < math.cos(config.reflex_release))
    return braced | (cos_tilt < math.cos(config.reflex_tilt))


def control(config: RobotConfig, joint_qpos, qpos, gait, neutral, damage: Damage, braced, fresh, xp=jnp):
    """One control step's servo command (18,) rad/s and the reflex's new `braced`: the controller's joint targets
    `gait` (18,) (the neutral pose's `neutral` while the tilt reflex holds), the damaged legs of `damage`
    (unbatched) in the pose their damage model holds, a velocity servo towards them from the joints
    qpos[joint_qpos]. Jax (xp=jnp) or NumPy."""
    if config.reflex_tilt > 0.0:  # past the reflex tilt: the neutral pose (until the segment ends or release)
        braced = reflex_braced(braced, fresh, qpos, config)
        gait = xp.where(braced, neutral, gait)
    target = held_targets(gait, damage, xp)
    return servo_command(target, qpos[np.asarray(joint_qpos)], config.max_joint_velocity, xp), braced


def check_state(qpos: jax.Array, qvel: jax.Array, limits: ValidityLimits) -> jax.Array:
    """InvalidReason bits (int32 scalar, 0 = valid) of one state: qpos (25,), qvel (24,)."""
    finite = jnp.isfinite(qpos).all() & jnp.isfinite(qvel).all()
    exploded = jnp.abs(qvel).max() > limits.max_speed
    flipped = up_z(qpos) < math.cos(limits.max_tilt)
    height = (qpos[2] < limits.min_base_height) | (qpos[2] > limits.max_base_height)
    on_floor = (_world_z_of(qpos, _BODY_BOTTOM).min() < 0.0) & limits.body_on_floor
    return (jnp.where(finite, 0, InvalidReason.NON_FINITE) | jnp.where(exploded, InvalidReason.EXPLODED, 0)
            | jnp.where(flipped, InvalidReason.FLIPPED, 0) | jnp.where(height, InvalidReason.HEIGHT, 0)
            | jnp.where(on_floor, InvalidReason.BODY_ON_FLOOR, 0)).astype(jnp.int32)


def warp_overflow(data: mjx.Data) -> jax.Array:
    """`InvalidReason.WARP_OVERFLOW` (int32 scalar) if MuJoCo Warp dropped contacts or constraint rows, else 0."""
    from mujoco.mjx.third_party.mujoco_warp import OverflowType
    lost = (OverflowType.NEFC | OverflowType.NJMAX_NNZ | OverflowType.BROADPHASE | OverflowType.NARROWPHASE
            | OverflowType.CCD | OverflowType.NVMAX)
    return jnp.where((data._impl.overflow & int(lost)) != 0, InvalidReason.WARP_OVERFLOW, 0).astype(jnp.int32)


def step(robot: Robot, data: mjx.Data, reason: jax.Array, gait: jax.Array, neutral: jax.Array, damage: Damage,
         braced: jax.Array, fresh: jax.Array, limits: ValidityLimits):
    """One control step of one robot (unbatched; vmap for a population; `robot.model` already carries the model
    values of its `damage`: `damage.edited_model`): `control`, then the physics' substeps
    and the validity check. An invalid robot (`reason` != 0 before, or its new state invalid) stays at its last
    valid state, so no NaN leaves it. Returns (data, reason, command (18,), braced, ok): `reason` the first
    invalid reason (0: valid), `ok` whether this step's state is valid."""
    config = robot.config
    command, braced = control(config, robot.info.joint_qpos, data.qpos, gait, neutral, damage, braced, fresh)
    stepped = data.replace(ctrl=command)
    for _ in range(config.substeps):
        stepped = mjx.step(robot.model, stepped)
    found = check_state(stepped.qpos, stepped.qvel, limits)
    if config.impl == "warp":
        found = found | warp_overflow(stepped)
    reason = jnp.where(reason == 0, found, reason)
    ok = reason == 0
    stepped = stepped.replace(qpos=jnp.where(ok, stepped.qpos, data.qpos), qvel=jnp.where(ok, stepped.qvel, data.qvel),
                              qacc_warmstart=jnp.where(ok, stepped.qacc_warmstart, data.qacc_warmstart))
    return stepped, reason, command, braced, ok
