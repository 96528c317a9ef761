"""Batched, jitted rollouts (`vmap` over individuals, `lax.scan` over steps); invalid ones freeze: no NaN out."""

from __future__ import annotations

import dataclasses
import enum
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hte_jax import sharding
from hte_jax.errors import ConfigError
from hte_jax.sim.controller import NUM_PARAMS, SAMPLES_PER_PERIOD, servo_command, target_table
from hte_jax.sim.damage import apply_damage, damaged_joint_mask, damaged_pose
from hte_jax.sim.mjx_import import mjx
from hte_jax.sim.robot import FOOT_RADIUS, NUM_JOINTS, NUM_LEGS, Robot, mj_model, warp_capacity


class InvalidReason(enum.IntFlag):
    """Bits of `RolloutResult.invalid_reason`."""

    NON_FINITE = 1  # NaN or inf in qpos / qvel
    EXPLODED = 2  # some |qvel| above ValidityLimits.max_speed
    FLIPPED = 4  # body tilted more than ValidityLimits.max_tilt
    HEIGHT = 8  # base height outside [min_base_height, max_base_height]
    BODY_ON_FLOOR = 16  # a corner of the body box below the floor (only feet collide with it)
    WARP_OVERFLOW = 32  # MuJoCo Warp dropped contacts or constraint rows: a buffer too small (impl "warp")


@dataclasses.dataclass(frozen=True)
class ValidityLimits:
    """When a rollout is invalid."""

    max_tilt: float = math.pi / 4  # rad between the body's and the world's z axes
    min_base_height: float = 0.04  # m (the belly touches the floor at 0.021; gaits stay above 0.079)
    max_base_height: float = 1.0  # m
    max_speed: float = 100.0  # largest |qvel| entry
    body_on_floor: bool = True  # a body corner below the floor is invalid (off with `RobotConfig.body_floor_contact`)


@dataclasses.dataclass(frozen=True)
class RolloutSpec:
    """Static description of a rollout (hashable; changing it recompiles); record_*: what `RolloutResult` holds."""

    num_steps: int = 300  # control steps, 100 per second
    pose_steps: tuple[int, ...] = ()  # steps in [0, num_steps] after which the base pose is recorded (0: initial)
    record_contacts: bool = True
    record_feet: bool = False
    record_joints: bool = False
    record_joint_travel: bool = False
    record_qpos_every: int = 0
    contact_tolerance: float = 1e-3  # m: a foot closer to the floor touches it
    limits: ValidityLimits = ValidityLimits()

    def __post_init__(self):
        if not isinstance(self.num_steps, int) or self.num_steps < 1:
            raise ConfigError(f"num_steps must be a positive integer, got {self.num_steps!r}")
        for step in self.pose_steps:
            if not (isinstance(step, int) and 0 <= step <= self.num_steps):
                raise ConfigError(f"pose step {step!r} outside [0, num_steps={self.num_steps}]")
        if not isinstance(self.record_qpos_every, int) or self.record_qpos_every < 0:
            raise ConfigError(f"record_qpos_every must be an integer >= 0, got {self.record_qpos_every!r}")


@struct.dataclass
class SimState:
    """Physical state of robots (any leading batch shape): qpos (..., 25) base position, quaternion w-x-y-z, 18
    joint angles (leg-major); qvel (..., 24) base linear (world) and angular (body) velocity, 18 joint rates;
    qacc_warmstart (..., 24) the solver's warm start (carried, chained rollouts equal one long rollout)."""

    qpos: jax.Array
    qvel: jax.Array
    qacc_warmstart: jax.Array


@struct.dataclass
class RolloutResult:
    """A batched rollout of B individuals, T = num_steps, P = len(pose_steps): final_state SimState (B, ...) (the
    last valid one); valid (B,) bool; invalid_step (B,) int32 (T if valid); invalid_reason (B,) int32
    `InvalidReason` bits (0 if valid); base_pos (B, P, 3), base_quat (B, P, 4) at `pose_steps`; command_abs_sum
    (B, 18) sum of |commanded joint velocity| * control_dt (rad); if recorded (else None), at each step's start:
    foot_contacts (B, T, 6) bool, foot_pos (B, T, 6, 3), joint_pos (B, T, 18), qpos (B, ceil(T / k), 25) every
    k = record_qpos_every steps, joint_travel (B, 18) the valid steps' summed |joint angle change| (rad), and
    target_travel (B, 18) the valid steps' summed |gait target change| around the controller's period, none on
    the steps the tilt reflex held the neutral pose (what the controller commanded; without the reflex one
    period gives `controller.commanded_travel`, whatever the damage holds)."""

    final_state: SimState
    valid: jax.Array
    invalid_step: jax.Array
    invalid_reason: jax.Array
    base_pos: jax.Array
    base_quat: jax.Array
    foot_contacts: jax.Array | None
    foot_pos: jax.Array | None
    command_abs_sum: jax.Array
    joint_pos: jax.Array | None = None
    qpos: jax.Array | None = None
    joint_travel: jax.Array | None = None
    target_travel: jax.Array | None = None


def initial_state(robot: Robot, damage: jax.Array | None = None) -> SimState:
    """Unbatched SimState of the reference pose (base 0.15 m up, joints at 0), `damage` (6,) bool legs in their pose."""
    model = mj_model(robot.config)
    qpos = jnp.asarray(model.qpos0, jnp.float32)
    if damage is not None:
        joints = jnp.asarray(robot.info.joint_qpos)
        pose = jnp.tile(jnp.asarray(damaged_pose(robot.config.damage_model), jnp.float32), NUM_LEGS)
        qpos = qpos.at[joints].set(jnp.where(damaged_joint_mask(jnp.asarray(damage)), pose, qpos[joints]))
    zeros = jnp.zeros(model.nv, jnp.float32)
    return SimState(qpos=qpos, qvel=zeros, qacc_warmstart=zeros)


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


def reflex_braced(braced, fresh, qpos, config):
    """Whether the tilt reflex (`RobotConfig.reflex_*`) holds the neutral pose after this step's check: `braced`
    whether it held it, `fresh` whether a controller segment starts now (it lets go). Jax or NumPy (np.bool_)."""
    cos_tilt = up_z(qpos)
    braced = braced & ~fresh
    if config.reflex_release > 0.0:  # back below the release angle: the gait resumes
        braced = braced & (cos_tilt < math.cos(config.reflex_release))
    return braced | (cos_tilt < math.cos(config.reflex_tilt))


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


def _rollout_one(robot: Robot, spec: RolloutSpec, template: mjx.Data, tables: jax.Array, damage: jax.Array,
                 init: SimState):
    """One individual: tables (S, 100, 18) joint targets, damage (6,), init unbatched."""
    info, config = robot.info, robot.config
    segment_steps = spec.num_steps // tables.shape[0]
    joint_qpos = np.asarray(info.joint_qpos)
    feet = np.asarray(info.foot_geoms)
    pose_slot = np.full(spec.num_steps + 1, -1, np.int32)  # step -> slot in pose buffer
    for slot, step in enumerate(spec.pose_steps):
        pose_slot[step] = slot
    pose_slot = jnp.asarray(pose_slot)
    num_poses = len(spec.pose_steps)

    def record_pose(buffer, qpos, step):
        hit = jnp.arange(num_poses) == pose_slot[step]
        return jnp.where(hit[:, None], qpos[None, :7], buffer)

    neutral = target_table(jnp.zeros(NUM_PARAMS, jnp.float32))  # (100, 18) the all-zero controller

    def control_step(carry, step):
        data, reason, invalid_step, poses, command_sum, travel, braced, asked = carry
        poses = record_pose(poses, data.qpos, step)
        row = (step % segment_steps) % SAMPLES_PER_PERIOD
        gait = tables[step // segment_steps, row]
        gait_move = jnp.abs(gait - tables[step // segment_steps, (row - 1) % SAMPLES_PER_PERIOD])
        if config.reflex_tilt > 0.0:  # past the reflex tilt: the neutral pose (until the segment ends or release)
            braced = reflex_braced(braced, step % segment_steps == 0, data.qpos, config)
            gait = jnp.where(braced, neutral[row], gait)
            gait_move = jnp.where(braced, 0.0, gait_move)
        target = apply_damage(gait, damage, damaged_pose(config.damage_model))
        command = servo_command(target, data.qpos[joint_qpos], config.max_joint_velocity)
        stepped = data.replace(ctrl=command)
        for _ in range(config.substeps):
            stepped = mjx.step(robot.model, stepped)
        found = check_state(stepped.qpos, stepped.qvel, spec.limits)
        if config.impl == "warp":
            found = found | warp_overflow(stepped)
        new_reason = jnp.where(reason == 0, found, reason)
        ok = new_reason == 0
        # Freeze an invalid individual at its last valid state (no NaN leaks out).
        stepped = stepped.replace(qpos=jnp.where(ok, stepped.qpos, data.qpos),
                                  qvel=jnp.where(ok, stepped.qvel, data.qvel),
                                  qacc_warmstart=jnp.where(ok, stepped.qacc_warmstart, data.qacc_warmstart))
        invalid_step = jnp.where((reason == 0) & ~ok, step, invalid_step)
        command_sum = command_sum + jnp.where(ok, jnp.abs(command), 0.0) * config.control_dt
        if spec.record_joint_travel:
            travel = travel + jnp.where(ok, jnp.abs(stepped.qpos[joint_qpos] - data.qpos[joint_qpos]), 0.0)
            asked = asked + jnp.where(ok, gait_move, 0.0)
        # geom_xpos was computed by the step's forward pass, i.e. at the start of this step.
        foot_pos = jnp.where(ok, stepped.geom_xpos[feet], data.geom_xpos[feet])
        outputs = {}
        if spec.record_contacts:
            outputs["contacts"] = foot_pos[:, 2] - FOOT_RADIUS < spec.contact_tolerance
        if spec.record_feet:
            outputs["feet"] = foot_pos
        if spec.record_joints:
            outputs["joints"] = data.qpos[joint_qpos]
        if spec.record_qpos_every:
            outputs["qpos"] = data.qpos
        return (stepped, new_reason, invalid_step, poses, command_sum, travel, braced, asked), outputs

    data = template.replace(qpos=init.qpos, qvel=init.qvel, qacc_warmstart=init.qacc_warmstart)
    data = mjx.kinematics(robot.model, data)  # geom_xpos of the initial state
    zeros = jnp.zeros(NUM_JOINTS, jnp.float32)
    carry = (data, check_state(init.qpos, init.qvel, spec.limits), jnp.int32(spec.num_steps),
             jnp.zeros((num_poses, 7), jnp.float32), zeros, zeros, jnp.bool_(False), zeros)
    scanned = jax.lax.scan(control_step, carry, jnp.arange(spec.num_steps))
    (data, reason, invalid_step, poses, command_sum, travel, _, asked), outputs = scanned
    poses = record_pose(poses, data.qpos, spec.num_steps)
    invalid_step = jnp.where((reason != 0) & (invalid_step == spec.num_steps), 0, invalid_step)
    return RolloutResult(
        final_state=SimState(qpos=data.qpos, qvel=data.qvel, qacc_warmstart=data.qacc_warmstart), valid=reason == 0,
        invalid_step=invalid_step, invalid_reason=reason, base_pos=poses[:, :3], base_quat=poses[:, 3:],
        foot_contacts=outputs.get("contacts"), foot_pos=outputs.get("feet"), command_abs_sum=command_sum,
        joint_pos=outputs.get("joints"), joint_travel=travel if spec.record_joint_travel else None,
        target_travel=asked if spec.record_joint_travel else None,
        qpos=outputs["qpos"][:: spec.record_qpos_every] if spec.record_qpos_every else None)


@functools.partial(jax.jit, static_argnames=("spec",))
def rollout(robot: Robot, params: jax.Array, damage: jax.Array, init: SimState, spec: RolloutSpec) -> RolloutResult:
    """B hexapods simulated in one jitted call: params (B, 36) controllers, or (B, S, 36) run back to back for
    num_steps / S steps each (clock reset); damage (B, 6) or (6,) bool; init SimState batched (B, ...) or not."""
    if params.ndim == 2:
        params = params[:, None, :]
    if params.ndim != 3 or params.shape[-1] != NUM_PARAMS:
        raise ConfigError(f"params must have shape (B, 36) or (B, S, 36), got {params.shape}")
    batch, num_segments = params.shape[:2]
    if spec.num_steps % num_segments:
        raise ConfigError(f"{num_segments} controller segments do not divide num_steps={spec.num_steps}")
    damage = jnp.asarray(damage, bool)
    if damage.shape[-1] != NUM_LEGS or damage.ndim > 2:
        raise ConfigError(f"damage must have shape (6,) or (B, 6), got {damage.shape}")
    if damage.ndim == 1:
        damage = jnp.broadcast_to(damage, (batch, NUM_LEGS))
    if init.qpos.ndim == 1:
        init = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), init)
    tables = jax.vmap(jax.vmap(target_table))(params.astype(jnp.float32))  # (B, S, 100, 18)
    template = empty_data(robot, batch)

    def run(shared, rows):
        return jax.vmap(functools.partial(_rollout_one, shared[0], spec, shared[1]))(*rows)

    return sharding.map_rows(run, (robot, template), (tables, damage, init))


def empty_data(robot: Robot, rows: int) -> mjx.Data:
    """The mjx.Data that `rows` robots simulated together start from (Warp: buffers sized by `warp_capacity`)."""
    if robot.config.impl == "jax":
        return mjx.make_data(robot.model, device=sharding.local_device(), impl="jax")
    contacts, constraint_rows = warp_capacity(robot.config)
    return mjx.make_data(mj_model(robot.config), device=sharding.local_device(), impl="warp", naconmax=rows * contacts,
                          njmax=constraint_rows)


def standing_state(robot: Robot, damage: jax.Array | None = None, settle_steps: int = 100) -> SimState:
    """A settled standing pose (zero controller, then x = y = 0), batched like `damage` (6,) or (B, 6) bool."""
    damage = jnp.zeros(NUM_LEGS, bool) if damage is None else jnp.asarray(damage, bool)
    batched = damage.ndim == 2
    damage = damage.reshape(-1, NUM_LEGS)
    init = jax.vmap(lambda d: initial_state(robot, d))(damage)
    params = jnp.zeros((damage.shape[0], NUM_PARAMS))
    spec = RolloutSpec(num_steps=settle_steps, record_contacts=False)
    state = rollout(robot, params, damage, init, spec).final_state
    state = state.replace(qpos=state.qpos.at[:, :2].set(0.0))
    return state if batched else jax.tree.map(lambda x: x[0], state)
