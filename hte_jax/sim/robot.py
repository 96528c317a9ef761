"""The hexapod model: `load_robot(config)` compiles `assets/hexapod.xml` into a `Robot` (MJX model + `RobotInfo`)."""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from pathlib import Path

import jax
import mujoco
import numpy as np
from flax import struct

from hte_jax import sharding
from hte_jax.control_step import STEPS_PER_SECOND  # noqa: F401  (the robot's control rate, re-exported)
from hte_jax.errors import ConfigError, check_fields, choice, integer, number
from hte_jax.sim.mjx_import import IMPLS, mjx, require_impl

NUM_LEGS = 6
JOINTS_PER_LEG = 3
NUM_JOINTS = NUM_LEGS * JOINTS_PER_LEG
FOOT_RADIUS = 0.025
FOOT_REACH = 0.176  # m: horizontal hip-to-foot distance at the standing pose (assets/hexapod.xml; tests/test_robot.py)
LEG_NAMES = ("front-right", "middle-right", "rear-right", "rear-left", "middle-left", "front-left")
# Collision bits (see assets/hexapod.xml): feet touch the floor, body and links touch walls.
FLOOR_BIT = 1
WALL_BIT = 2
WALL_HEIGHT = 0.9
WALL_CONTACTS = ("bumper", "links", "feet")
# The damage models a plain leg mask can name (`RobotConfig.damage_model`; all of them, with their parameters,
# in hte_jax.sim.damage).
DAMAGE_MODELS = ("raised", "locked", "removed")
# The solver settings (`SolverConfig`) of every configuration stored before they were settings.
LEGACY_SOLVER = (4, 8, 1e-8, "jax")


def assets_dir() -> Path:
    """Folder holding the MJCF and shipped repertoires (`$HTE_JAX_ASSETS` overrides)."""
    env = os.environ.get("HTE_JAX_ASSETS")
    path = Path(env) if env else Path(__file__).resolve().parents[2] / "assets"
    if not (path / "hexapod.xml").is_file():
        raise FileNotFoundError(f"hexapod.xml not found in {path}; install hte-jax from a checkout "
                                "(pip install -e .) or point HTE_JAX_ASSETS at the assets folder")
    return path


@dataclasses.dataclass(frozen=True)
class RobotConfig:
    """Simulation options of the hexapod (hashable: a static jit argument); reflex: past `reflex_tilt` the neutral
    pose is held until the controller segment ends, or the tilt is back below `reflex_release`."""

    timestep: float = number(0.01, 0.0, open_low=True)  # physics step (s), dividing control_dt
    control_dt: float = number(0.01, 0.0, open_low=True)  # controller period (s; the original's servos: 100 Hz)
    solver_iterations: int = integer(4)  # Newton iteration cap
    ls_iterations: int = integer(4)  # line-search iteration cap
    solver_tolerance: float = number(1e-8, 0.0)  # Newton early stop below this cost improvement or scaled gradient
    impl: str = choice("jax", IMPLS)  # MJX's physics: "jax" (any device) or "warp" (MuJoCo Warp, the `warp` extra)
    servo_gain: float = number(1.0, 0.0, open_low=True)  # velocity servo kv, N m s/rad: torque = kv (v_cmd - qdot)
    armature: float = number(0.01, 0.0)  # rotor inertia added to every leg joint, kg m^2
    max_torque: float = number(4.0, 0.0, open_low=True)  # N m
    max_joint_velocity: float = number(5.0, 0.0, open_low=True)  # commanded, rad/s
    joint_limits: bool = True  # the +-pi/2 joint ranges
    walls: tuple[tuple[float, float, float, float], ...] = ()  # boxes (x1, y1, x2, y2), m, 0.9 m high
    # What touches walls: "bumper" (an invisible massless sphere, the planner's disc: cheap sphere-box contacts),
    # "links" (body, links and feet: exact, about 25x slower in the maze) or "feet".
    wall_contact: str = choice("bumper", WALL_CONTACTS)
    bumper_radius: float = number(0.25, 0.0, open_low=True)  # m, the planner's robot radius
    body_floor_contact: bool = False  # body and links collide with the floor (online: a robot that tips over)
    damage_model: str = choice("raised", DAMAGE_MODELS)  # what a leg mask's damaged legs suffer (hte_jax.sim.damage)
    reflex_tilt: float = number(0.0, 0.0, math.pi)  # rad; 0: no reflex (the paper's robot)
    reflex_release: float = number(0.0, 0.0)  # rad; 0: held until the segment ends

    def __post_init__(self):
        check_fields(self)
        ratio = self.control_dt / self.timestep
        if abs(ratio - round(ratio)) > 1e-6:
            raise ConfigError(f"control_dt={self.control_dt} must be a whole multiple of timestep={self.timestep}")
        if self.reflex_release and not self.reflex_tilt:
            raise ConfigError("reflex_release shapes the tilt reflex: set reflex_tilt > 0 too")
        if self.reflex_release >= self.reflex_tilt > 0.0:
            raise ConfigError(f"reflex_release={self.reflex_release} must be below reflex_tilt={self.reflex_tilt}")
        for wall in self.walls:
            if len(wall) != 4 or not (wall[0] < wall[2] and wall[1] < wall[3]):
                raise ConfigError(f"wall {wall!r} must be (x1, y1, x2, y2) with x1 < x2 and y1 < y2")

    @property
    def substeps(self) -> int:
        """Physics steps per control step."""
        return int(round(self.control_dt / self.timestep))


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """The `RobotConfig` solver settings configurations carry (inlined); `load_robot` checks that `impl` runs here."""

    solver_iterations: int = RobotConfig.solver_iterations
    ls_iterations: int = RobotConfig.ls_iterations
    solver_tolerance: float = RobotConfig.solver_tolerance
    impl: str = RobotConfig.impl

    def __post_init__(self):
        self.robot()  # RobotConfig validates the settings

    def robot(self, **options) -> RobotConfig:
        """The robot with this solver and the other `options` (RobotConfig's fields)."""
        return RobotConfig(**dataclasses.asdict(self), **options)


SOLVER_FIELDS = tuple(field.name for field in dataclasses.fields(SolverConfig))


@dataclasses.dataclass(frozen=True)
class RobotInfo:
    """Static facts about a compiled model (Python ints and tuples only)."""

    config: RobotConfig
    nq: int
    nv: int
    joint_qpos: tuple[int, ...]  # qpos address of the 18 leg joints, leg-major (leg0 hip, femur, tibia, leg1 ...)
    joint_dof: tuple[int, ...]  # their qvel address
    foot_geoms: tuple[int, ...]  # geom id of the six foot spheres
    base_body: int  # body id of base_link
    leg_bodies: tuple[tuple[int, ...], ...] = ()  # (6, 3) body ids of each leg's hip, femur and tibia
    leg_geoms: tuple[tuple[int, ...], ...] = ()  # (6, 4) geom ids of each leg's hip, femur, tibia links and foot
    leg_actuators: tuple[tuple[int, ...], ...] = ()  # (6, 3) actuator ids of each leg's servos
    floor_geom: int = 0


@struct.dataclass
class Robot:
    """A compiled hexapod: `model` is the MJX model pytree, `info` its static facts."""

    model: mjx.Model
    info: RobotInfo = struct.field(pytree_node=False)

    @property
    def config(self) -> RobotConfig:
        return self.info.config


def build_spec(config: RobotConfig) -> mujoco.MjSpec:
    """The MJCF as an editable spec with `config` applied (walls, options, servo)."""
    spec = mujoco.MjSpec.from_file(str(assets_dir() / "hexapod.xml"))
    spec.option.timestep = config.timestep
    spec.option.iterations = config.solver_iterations
    spec.option.ls_iterations = config.ls_iterations
    spec.option.tolerance = config.solver_tolerance
    limited = mujoco.mjtLimited.mjLIMITED_TRUE if config.joint_limits else mujoco.mjtLimited.mjLIMITED_FALSE
    for joint in spec.joints:
        if joint.type == mujoco.mjtJoint.mjJNT_HINGE:
            joint.armature = config.armature
            joint.limited = limited
    for actuator in spec.actuators:
        actuator.set_to_velocity(kv=config.servo_gain)
        actuator.ctrlrange = [-config.max_joint_velocity, config.max_joint_velocity]
        actuator.forcerange = [-config.max_torque, config.max_torque]
        actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    if config.walls and config.wall_contact == "bumper":
        for geom in spec.geoms:
            if geom.contype & WALL_BIT:
                geom.contype = geom.contype & ~WALL_BIT  # links: floor-blind already, now wall-blind too
        spec.body("base_link").add_geom(
            name="bumper", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[config.bumper_radius, 0.0, 0.0], contype=WALL_BIT,
            conaffinity=0, mass=0.0, group=3, rgba=[0.0, 0.0, 0.0, 0.0])
    if config.body_floor_contact:
        for geom in spec.geoms:
            if geom.name == "base_link" or geom.name.startswith("leg_"):
                geom.contype = geom.contype | FLOOR_BIT
    affinity = {"bumper": WALL_BIT, "links": FLOOR_BIT | WALL_BIT, "feet": FLOOR_BIT}[config.wall_contact]
    for i, (x1, y1, x2, y2) in enumerate(config.walls):
        spec.worldbody.add_geom(
            name=f"wall_{i}", type=mujoco.mjtGeom.mjGEOM_BOX, pos=[(x1 + x2) / 2, (y1 + y2) / 2, 0.0], contype=0,
            size=[(x2 - x1) / 2, (y2 - y1) / 2, WALL_HEIGHT / 2], conaffinity=affinity, rgba=[0.6, 0.4, 0.3, 1.0])
    return spec


def stored_solver(stored: dict) -> dict:
    """The solver settings of a stored configuration (flat or under "solver"; none: `LEGACY_SOLVER`)."""
    stored = {**stored.get("solver", {}), **stored}
    return {name: stored.get(name, legacy) for name, legacy in zip(SOLVER_FIELDS, LEGACY_SOLVER)}


@functools.lru_cache(maxsize=16)
def mj_model(config: RobotConfig = RobotConfig()) -> mujoco.MjModel:
    """The native MuJoCo model of `config` (`without_idle_springs`), cached and shared: never alter it."""
    return without_idle_springs(build_spec(config).compile())


def without_idle_springs(model: mujoco.MjModel) -> mujoco.MjModel:
    """`model` with MuJoCo's spring term off, in place, if it has no spring (no joint stiffness, no tendon):
    no force changes, and MJX traces no spring code, which crashed XLA (SIGSEGV) compiling a shard_map rollout."""
    if not model.jnt_stiffness.any() and model.ntendon == 0:
        model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_SPRING)
    return model


def robot_info(model: mujoco.MjModel, config: RobotConfig) -> RobotInfo:
    """Index bookkeeping for a compiled model."""
    names = (name for leg in range(NUM_LEGS) for name in (f"body_leg_{leg}", f"leg_{leg}_1_2", f"leg_{leg}_2_3"))
    joints = [model.joint(name) for name in names]
    links = [[f"leg_{leg}_{link}" for link in (1, 2, 3)] for leg in range(NUM_LEGS)]
    joint_of = {int(model.actuator_trnid[a, 0]): a for a in range(model.nu)}
    return RobotInfo(config=config, nq=model.nq, nv=model.nv, joint_qpos=tuple(int(j.qposadr[0]) for j in joints),
                     joint_dof=tuple(int(j.dofadr[0]) for j in joints), base_body=model.body("base_link").id,
                     foot_geoms=tuple(model.geom(f"foot_{leg}").id for leg in range(NUM_LEGS)),
                     leg_bodies=tuple(tuple(model.body(name).id for name in leg) for leg in links),
                     leg_geoms=tuple(tuple(model.geom(name).id for name in [*leg, f"foot_{i}"])
                                     for i, leg in enumerate(links)),
                     leg_actuators=tuple(tuple(joint_of[int(j.id)] for j in joints[3 * leg: 3 * leg + 3])
                                         for leg in range(NUM_LEGS)),
                     floor_geom=model.geom("floor").id)


def load_robot(config: RobotConfig = RobotConfig()) -> Robot:
    """The hexapod for `config` in MJX's `config.impl` (ConfigError if it cannot run here), arrays uncommitted."""
    require_impl(config.impl)
    model = mj_model(config)
    mjx_model = mjx.put_model(model, device=sharding.local_device(), impl=config.impl)
    if config.impl == "warp":
        mjx_model = without_solver_cap_notices(mjx_model)
    return Robot(model=sharding.uncommitted(mjx_model), info=robot_info(model, config))


def without_solver_cap_notices(model: mjx.Model) -> mjx.Model:
    """A Warp-backend model quiet about Newton solves stopping at their iteration caps (as MJX's JAX one is)."""
    from mujoco.mjx.third_party.mujoco_warp import OverflowType
    options = model.opt._impl
    quiet = int(options.warn_overflow) & ~int(OverflowType.ITERATIONS | OverflowType.LS_ITERATIONS)
    return model.replace(opt=model.opt.replace(_impl=options.replace(warn_overflow=quiet)))


@functools.lru_cache(maxsize=16)
def warp_capacity(config: RobotConfig) -> tuple[int, int]:
    """(contacts, constraint rows) one robot can need under MuJoCo Warp (whose defaults drop contacts beyond a few
    robots): the JAX implementation's static layout plus the 4 more contacts (and rows) of a box-box pair in Warp."""
    model = mj_model(config)
    with jax.ensure_compile_time_eval():  # concrete even when first asked while tracing a rollout
        layout = mjx.make_data(model, device=sharding.local_device(), impl="jax")._impl
    geoms = np.asarray(layout.contact.geom)
    box_box = (model.geom_type[geoms] == mujoco.mjtGeom.mjGEOM_BOX).all(axis=1)
    dims = np.asarray(layout.contact.dim)[box_box]
    pyramidal = model.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
    extra_rows = np.where(dims == 1, 1, 2 * (dims - 1) if pyramidal else dims).sum()
    return len(geoms) + int(box_box.sum()), int(layout.efc_J.shape[0] + extra_rows)
