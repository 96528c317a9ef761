"""Batched, jitted rollouts (`vmap` over individuals, `lax.scan` over steps); invalid ones freeze: no NaN out."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hte_jax import sharding
from hte_jax.errors import ConfigError
from hte_jax.sim import env
from hte_jax.sim.controller import NUM_PARAMS, SAMPLES_PER_PERIOD, target_table
from hte_jax.sim.damage import Damage, as_damage, edited_model, edits_model, held_targets, touching_feet
from hte_jax.sim.env import SimState, ValidityLimits, check_state
from hte_jax.sim.mjx_import import mjx
from hte_jax.sim.robot import FOOT_RADIUS, NUM_JOINTS, NUM_LEGS, Robot, mj_model, warp_capacity
from hte_jax.warp_calls import waited


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


def initial_state(robot: Robot, damage: jax.Array | Damage | None = None) -> SimState:
    """Unbatched SimState of the reference pose (base 0.15 m up, joints at 0), the legs of `damage` (a (6,) bool
    mask or an unbatched `Damage`) in the pose their damage model holds."""
    model = mj_model(robot.config)
    qpos = jnp.asarray(model.qpos0, jnp.float32)
    if damage is not None:
        joints = jnp.asarray(robot.info.joint_qpos)
        qpos = qpos.at[joints].set(held_targets(qpos[joints], as_damage(damage, robot.config.damage_model)))
    zeros = jnp.zeros(model.nv, jnp.float32)
    return SimState(qpos=qpos, qvel=zeros, qacc_warmstart=zeros)


def _rollout_one(robot: Robot, spec: RolloutSpec, template: mjx.Data, edits: bool, tables: jax.Array,
                 damage: Damage, init: SimState):
    """One individual: tables (S, 100, 18) joint targets, damage and init unbatched; `edits`: its damage changes
    the model's values (`damage.edited_model`)."""
    if edits:
        robot = robot.replace(model=edited_model(robot.model, damage, robot.info))
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
        stepped, new_reason, command, braced, ok = env.step(robot, data, reason, gait, neutral[row], damage, braced,
                                                            step % segment_steps == 0, spec.limits)
        if config.reflex_tilt > 0.0:
            gait_move = jnp.where(braced, 0.0, gait_move)
        invalid_step = jnp.where((reason == 0) & ~ok, step, invalid_step)
        command_sum = command_sum + jnp.where(ok, jnp.abs(command), 0.0) * config.control_dt
        if spec.record_joint_travel:
            travel = travel + jnp.where(ok, jnp.abs(stepped.qpos[joint_qpos] - data.qpos[joint_qpos]), 0.0)
            asked = asked + jnp.where(ok, gait_move, 0.0)
        # geom_xpos was computed by the step's forward pass, i.e. at the start of this step.
        foot_pos = jnp.where(ok, stepped.geom_xpos[feet], data.geom_xpos[feet])
        outputs = {}
        if spec.record_contacts:
            outputs["contacts"] = (foot_pos[:, 2] - FOOT_RADIUS < spec.contact_tolerance) & touching_feet(damage)
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
    num_steps / S steps each (clock reset); damage a (B, 6) or (6,) bool leg mask (its legs under
    `RobotConfig.damage_model`) or a `Damage` batched (B, ...) or not (one program for any mix of damage models);
    init SimState batched (B, ...) or not."""
    if params.ndim == 2:
        params = params[:, None, :]
    if params.ndim != 3 or params.shape[-1] != NUM_PARAMS:
        raise ConfigError(f"params must have shape (B, 36) or (B, S, 36), got {params.shape}")
    batch, num_segments = params.shape[:2]
    if spec.num_steps % num_segments:
        raise ConfigError(f"{num_segments} controller segments do not divide num_steps={spec.num_steps}")
    edits = edits_model(damage, robot.config.damage_model)
    damage = as_damage(damage, robot.config.damage_model)
    if damage.legs.shape[-1] != NUM_LEGS or damage.legs.ndim > 2:
        raise ConfigError(f"damage must have shape (6,) or (B, 6), got {damage.legs.shape}")
    if damage.legs.ndim == 1:
        damage = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), damage)
    if init.qpos.ndim == 1:
        init = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), init)
    # The barrier keeps XLA from folding constant params (the neutral pose's zeros) through the controller's
    # tables: a gather of B x 2100 x 12 floats folded at every compilation, 100 MB at B = 1050.
    params = jax.lax.optimization_barrier(params.astype(jnp.float32))
    tables = jax.vmap(jax.vmap(target_table))(params)  # (B, S, 100, 18)

    def run(robot, rows):  # Warp's buffers sized for the rows of this call (one device's, under a mesh)
        template = empty_data(robot, rows[0].shape[0])
        return jax.vmap(functools.partial(_rollout_one, robot, spec, template, edits))(*rows)

    return sharding.map_rows(run, robot, (tables, damage, init))


def empty_data(robot: Robot, rows: int) -> mjx.Data:
    """The mjx.Data that `rows` robots simulated together start from (Warp: buffers sized by `warp_capacity`)."""
    if robot.config.impl == "jax":
        return mjx.make_data(robot.model, device=sharding.local_device(), impl="jax")
    contacts, constraint_rows = warp_capacity(robot.config)
    return mjx.make_data(mj_model(robot.config), device=sharding.local_device(), impl="warp", naconmax=rows * contacts,
                          njmax=constraint_rows)


def standing_state(robot: Robot, damage: jax.Array | Damage | None = None, settle_steps: int = 100) -> SimState:
    """A settled standing pose (zero controller, then x = y = 0), batched like `damage`: a (6,) or (B, 6) bool leg
    mask, or a `Damage` unbatched or batched (B, ...), concrete or traced. Three programs: the reference poses, the
    rollout, the move to the origin; run eagerly, waited for inside `warp_calls()` (`hte_jax.warp_calls`)."""
    damage = np.zeros(NUM_LEGS, bool) if damage is None else damage
    if not isinstance(damage, Damage):  # traced (under a caller's jit) or concrete
        damage = damage.astype(bool) if isinstance(damage, jax.Array) else np.asarray(damage, bool)
    legs = damage.legs if isinstance(damage, Damage) else damage
    batched = np.ndim(legs) == 2
    damage = jax.tree.map(lambda x: x.reshape(-1, *np.shape(x)[np.ndim(legs) - 1:]), damage)
    spec = RolloutSpec(num_steps=settle_steps, record_contacts=False)

    def settle() -> SimState:
        init = _reference_states(robot, damage)
        params = np.zeros((np.shape(init.qpos)[0], NUM_PARAMS), np.float32)
        return _at_origin(rollout(robot, params, damage, init, spec).final_state, batched)

    traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((robot, damage)))
    return settle() if traced else waited(settle)


@jax.jit
def _reference_states(robot: Robot, damage: jax.Array | Damage) -> SimState:
    """`initial_state` of each robot of `damage` (B, ...)."""
    return jax.vmap(lambda d: initial_state(robot, d))(damage)


@functools.partial(jax.jit, static_argnames=("batched",))
def _at_origin(state: SimState, batched: bool) -> SimState:
    """Robots `state` (B, ...) moved to x = y = 0; the first alone (unbatched) unless `batched`."""
    state = state.replace(qpos=state.qpos.at[:, :2].set(0.0))
    return state if batched else jax.tree.map(lambda x: x[0], state)
