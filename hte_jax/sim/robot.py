"""The hexapod model: MJCF loading, simulation options, walls and index bookkeeping.

`load_robot(config)` compiles `assets/hexapod.xml` with the options in `RobotConfig`
and returns a `Robot`: the MJX model (a pytree, so batched model fields can be
`vmap`-ed later) plus static facts (`RobotInfo`) that jitted code needs as Python ints.
"""

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
from hte_jax.errors import ConfigError, require_choice, require_int, require_number
from hte_jax.sim.mjx_import import IMPLS, mjx, require_impl

NUM_LEGS = 6
JOINTS_PER_LEG = 3
NUM_JOINTS = NUM_LEGS * JOINTS_PER_LEG
FOOT_RADIUS = 0.025
LEG_NAMES = ("front-right", "middle-right", "rear-right", "rear-left", "middle-left", "front-left")
# Collision bits (see assets/hexapod.xml): feet touch the floor, body and links touch walls.
FLOOR_BIT = 1
WALL_BIT = 2
WALL_HEIGHT = 0.9
WALL_CONTACTS = ("bumper", "links", "feet")
DAMAGE_MODELS = ("raised", "locked")  # the pose of a damaged leg (poses in hte_jax.sim.damage)
# The solver settings (`SolverConfig`) every configuration stored before they were settings (run
# folders, checkpoints, shipped repertoires) ran with; MJX's JAX implementation ran them all.
LEGACY_SOLVER = (4, 8, 1e-8, "jax")


def assets_dir() -> Path:
    """Folder holding the MJCF and shipped repertoires (`$HTE_JAX_ASSETS` overrides)."""
    env = os.environ.get("HTE_JAX_ASSETS")
    path = Path(env) if env else Path(__file__).resolve().parents[2] / "assets"
    if not (path / "hexapod.xml").is_file():
        raise FileNotFoundError(
            f"hexapod.xml not found in {path}; install hte-jax from a checkout "
            "(pip install -e .) or point HTE_JAX_ASSETS at the assets folder"
        )
    return path


@dataclasses.dataclass(frozen=True)
class RobotConfig:
    """Simulation options of the hexapod (hashable: used as a static jit argument).

    timestep: physics step in seconds; must divide `control_dt`.
    control_dt: controller period (the original runs its servos at 100 Hz).
    solver_iterations / ls_iterations: Newton solver and line-search iterations (caps).
    solver_tolerance: the Newton loop of a rollout stops early once its cost improvement or its
      gradient (scaled by the mass-matrix trace) falls below this (MuJoCo's default 1e-8).
    impl: MJX's implementation of the physics: "jax" (default; any device) or "warp" (MuJoCo Warp
      through MJX: an NVIDIA GPU or the CPU, needs the `warp` extra, `pip install -e ".[warp]"`).
      The same model, options, servo law, reflex and damages; the floating-point path differs.
    servo_gain: velocity-servo gain kv in N m s/rad (torque = kv (v_cmd - qdot), clipped).
    armature: reflected rotor inertia added to every leg joint, kg m^2.
    max_torque / max_joint_velocity: servo torque (N m) and commanded-velocity (rad/s) limits.
    joint_limits: enforce the +-pi/2 joint ranges.
    walls: axis-aligned boxes (x1, y1, x2, y2) in metres, 0.9 m high, added to the world.
    wall_contact: what of the robot touches walls. "bumper" (default): one invisible, massless
      sphere of `bumper_radius` around the body's centre, the planner's disc made solid (MJX
      sphere-box contacts are cheap). "links": the body box, every link box and the feet (exact
      shape, but 171 box-box pairs with the maze's 9 boxes make MJX about 25x slower). "feet":
      the foot spheres only.
    bumper_radius: radius of the bumper sphere in metres (the planner's robot radius).
    body_floor_contact: the body and link boxes collide with the floor too (not only the feet);
      the online phase turns it on so that a damaged robot that tips over lands on its body.
    damage_model: the pose a damaged leg holds: "raised" (blocked in the air, the paper's
      description) or "locked" (in the standing pose); see `hte_jax.sim.damage`.
    reflex_tilt: a tilt reflex of the controller: once the body tilts more than this angle (rad)
      from upright, the gait is dropped and the neutral pose (the all-zero controller) is held until
      the running controller's time is up (a 1 s step; a segment of `rollout`'s params). 0 (default,
      the paper's robot) never fires.
    reflex_release: 0 (default) holds the neutral pose until the segment ends; > 0 (below
      reflex_tilt): the gait resumes as soon as the tilt is back below this angle (rad).
    reflex_rate: 0 (default): the reflex fires on the angle alone; > 0: only while the body also
      tilts further at more than this rate (rad/s; a fall, not a steep but steady gait).
    """

    timestep: float = 0.01
    control_dt: float = 0.01
    solver_iterations: int = 4
    ls_iterations: int = 4
    solver_tolerance: float = 1e-8
    impl: str = "jax"
    servo_gain: float = 1.0
    armature: float = 0.01
    max_torque: float = 4.0
    max_joint_velocity: float = 5.0
    joint_limits: bool = True
    walls: tuple[tuple[float, float, float, float], ...] = ()
    wall_contact: str = "bumper"
    bumper_radius: float = 0.25
    body_floor_contact: bool = False
    damage_model: str = "raised"
    reflex_tilt: float = 0.0
    reflex_release: float = 0.0
    reflex_rate: float = 0.0

    def __post_init__(self):
        for name in ("timestep", "control_dt", "servo_gain", "max_torque", "max_joint_velocity"):
            require_number(name, getattr(self, name), 0.0, open_low=True)
        ratio = self.control_dt / self.timestep
        if abs(ratio - round(ratio)) > 1e-6:
            raise ConfigError(
                f"control_dt={self.control_dt} must be a whole multiple of timestep={self.timestep}"
            )
        require_int("solver_iterations", self.solver_iterations)
        require_int("ls_iterations", self.ls_iterations)
        require_number("solver_tolerance", self.solver_tolerance, 0.0)
        require_choice("impl", self.impl, IMPLS)
        require_number("armature", self.armature, 0.0)
        require_choice("wall_contact", self.wall_contact, WALL_CONTACTS)
        require_number("bumper_radius", self.bumper_radius, 0.0, open_low=True)
        require_number("reflex_tilt", self.reflex_tilt, 0.0, math.pi)
        require_number("reflex_release", self.reflex_release, 0.0)
        require_number("reflex_rate", self.reflex_rate, 0.0)
        if (self.reflex_release or self.reflex_rate) and not self.reflex_tilt:
            raise ConfigError("reflex_release and reflex_rate shape the tilt reflex: set reflex_tilt > 0 too")
        if self.reflex_release >= self.reflex_tilt > 0.0:
            raise ConfigError(f"reflex_release={self.reflex_release} must be below reflex_tilt={self.reflex_tilt}")
        require_choice("damage_model", self.damage_model, DAMAGE_MODELS)
        for wall in self.walls:
            if len(wall) != 4 or not (wall[0] < wall[2] and wall[1] < wall[3]):
                raise ConfigError(f"wall {wall!r} must be (x1, y1, x2, y2) with x1 < x2 and y1 < y2")

    @property
    def substeps(self) -> int:
        """Physics steps per control step."""
        return int(round(self.control_dt / self.timestep))


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """The physics' Newton solver: the settings of `RobotConfig` that training and evaluation
    configurations carry (inlined, `errors.inline`: stored and overridden by these names).

    solver_iterations / ls_iterations: Newton solver and line-search iterations (caps).
    solver_tolerance: the Newton loop's early-stop tolerance (`RobotConfig.solver_tolerance`).
    impl: MJX's implementation, "jax" or "warp" (`RobotConfig.impl`); whether it can run here is
      checked when a robot is loaded (`load_robot`), so a configuration stored with "warp" still reads.
    """

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
    """Static facts about a compiled model (Python ints and tuples only).

    joint_qpos: qpos address of the 18 leg joints, leg-major (leg0 hip, femur, tibia, leg1 ...).
    joint_dof: qvel address of the same joints.
    foot_geoms: geom id of the six foot spheres, leg order.
    base_body: body id of base_link.
    """

    config: RobotConfig
    nq: int
    nv: int
    joint_qpos: tuple[int, ...]
    joint_dof: tuple[int, ...]
    foot_geoms: tuple[int, ...]
    base_body: int


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
    for joint in spec.joints:
        if joint.type == mujoco.mjtJoint.mjJNT_HINGE:
            joint.armature = config.armature
            joint.limited = (
                mujoco.mjtLimited.mjLIMITED_TRUE if config.joint_limits else mujoco.mjtLimited.mjLIMITED_FALSE
            )
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
            name="bumper",
            type=mujoco.mjtGeom.mjGEOM_SPHERE,
            size=[config.bumper_radius, 0.0, 0.0],
            contype=WALL_BIT,
            conaffinity=0,
            mass=0.0,
            group=3,
            rgba=[0.0, 0.0, 0.0, 0.0],
        )
    if config.body_floor_contact:
        for geom in spec.geoms:
            if geom.name == "base_link" or geom.name.startswith("leg_"):
                geom.contype = geom.contype | FLOOR_BIT
    affinity = {"bumper": WALL_BIT, "links": FLOOR_BIT | WALL_BIT, "feet": FLOOR_BIT}[config.wall_contact]
    for i, (x1, y1, x2, y2) in enumerate(config.walls):
        spec.worldbody.add_geom(
            name=f"wall_{i}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=[(x1 + x2) / 2, (y1 + y2) / 2, 0.0],
            size=[(x2 - x1) / 2, (y2 - y1) / 2, WALL_HEIGHT / 2],
            contype=0,
            conaffinity=affinity,
            rgba=[0.6, 0.4, 0.3, 1.0],
        )
    return spec


def stored_solver(stored: dict) -> dict:
    """The solver settings of a stored configuration (flat, or nested under "solver"); one stored
    without them ran `LEGACY_SOLVER`."""
    stored = {**stored.get("solver", {}), **stored}
    return {name: stored.get(name, legacy) for name, legacy in zip(SOLVER_FIELDS, LEGACY_SOLVER)}


def compile_model(config: RobotConfig = RobotConfig()) -> mujoco.MjModel:
    """A newly compiled native MuJoCo model for `config`, the caller's own to alter. A model without
    springs (no joint stiffness, no tendons: the hexapod) gets MuJoCo's spring term switched off,
    which changes no force; MJX then traces no spring computation, whose presence made XLA crash
    (SIGSEGV) while compiling a rollout spread over 2+ devices with `jax.shard_map` (jax 0.11.2,
    CPU and GPU)."""
    return without_idle_springs(build_spec(config).compile())


@functools.lru_cache(maxsize=16)
def mj_model(config: RobotConfig = RobotConfig()) -> mujoco.MjModel:
    """`compile_model(config)`, cached and shared: never alter it (use `compile_model`)."""
    return compile_model(config)


def without_idle_springs(model: mujoco.MjModel) -> mujoco.MjModel:
    """`model` with MuJoCo's spring term switched off if it has no spring (no joint stiffness, no
    tendons), in place; a model with springs is returned unchanged."""
    if not model.jnt_stiffness.any() and model.ntendon == 0:
        model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_SPRING)
    return model


def robot_info(model: mujoco.MjModel, config: RobotConfig) -> RobotInfo:
    """Index bookkeeping for a compiled model."""
    names = [
        name
        for leg in range(NUM_LEGS)
        for name in (f"body_leg_{leg}", f"leg_{leg}_1_2", f"leg_{leg}_2_3")
    ]
    joints = [model.joint(name) for name in names]
    return RobotInfo(
        config=config,
        nq=model.nq,
        nv=model.nv,
        joint_qpos=tuple(int(j.qposadr[0]) for j in joints),
        joint_dof=tuple(int(j.dofadr[0]) for j in joints),
        foot_geoms=tuple(model.geom(f"foot_{leg}").id for leg in range(NUM_LEGS)),
        base_body=model.body("base_link").id,
    )


def load_robot(config: RobotConfig = RobotConfig()) -> Robot:
    """Compile the hexapod for `config` in MJX's `config.impl` (a ConfigError naming the extra if that
    is "warp" and the `warp` extra is missing): its arrays uncommitted on the default JAX device, so
    that a function spreading work over a mesh can take them there (`sharding`'s placement rule)."""
    require_impl(config.impl)
    model = mj_model(config)
    mjx_model = mjx.put_model(model, impl=config.impl)
    if config.impl == "warp":
        mjx_model = without_solver_cap_notices(mjx_model)
    return Robot(model=sharding.uncommitted(mjx_model), info=robot_info(model, config))


def without_solver_cap_notices(model: mjx.Model) -> mjx.Model:
    """A Warp-backend model that does not print "solver iterations limit reached" (nor its line-search
    twin) whenever a step's Newton solve stops at its iteration cap: the caps are settings
    (`solver_iterations`, `ls_iterations`) that MJX's JAX implementation applies silently. Warp's other
    overflow notices (contact, constraint or broadphase buffers too small) stay on: they mean lost
    contacts, which `warp_capacity` sizes the buffers to avoid."""
    from mujoco.mjx.third_party.mujoco_warp import OverflowType

    options = model.opt._impl
    quiet = int(options.warn_overflow) & ~int(OverflowType.ITERATIONS | OverflowType.LS_ITERATIONS)
    return model.replace(opt=model.opt.replace(_impl=options.replace(warn_overflow=quiet)))


@functools.lru_cache(maxsize=16)
def warp_capacity(config: RobotConfig) -> tuple[int, int]:
    """(contacts, constraint rows) one robot can need at once under MJX's Warp backend, the sizes of
    its per-batch contact buffer (`naconmax` = rows x contacts, shared by the batch) and per-robot
    constraint rows (`njmax`). Counted from the JAX implementation's static layout (every candidate
    geom pair at its most contacts), plus the 4 more contacts (and their rows) a box-box pair can
    have in MuJoCo Warp (8, the JAX implementation keeps 4). MuJoCo Warp's defaults (48 contacts for
    the whole batch) drop contacts beyond the first few robots: their feet sink through the floor."""
    model = mj_model(config)
    with jax.ensure_compile_time_eval():  # concrete even when first asked while tracing a rollout
        layout = mjx.make_data(model, impl="jax")._impl
    geoms = np.asarray(layout.contact.geom)
    box_box = (model.geom_type[geoms] == mujoco.mjtGeom.mjGEOM_BOX).all(axis=1)
    dims = np.asarray(layout.contact.dim)[box_box]
    pyramidal = model.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
    extra_rows = np.where(dims == 1, 1, 2 * (dims - 1) if pyramidal else dims).sum()
    return len(geoms) + int(box_box.sum()), int(layout.efc_J.shape[0] + extra_rows)
