"""Middle layer: 1 s body motions (paper section 3; `docs/original_code.md` §4). Per leg a target in the
bottom descriptor space (18 genes), mapped to its nearest primitive, runs `samples` chained seconds; the
medoid second's (x, y, yaw) step and contact bits are the descriptor, its angle error the fitness."""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections import OrderedDict

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.errors import check_fields, integer, number
from hte_jax.hbr import bottom
from hte_jax.geometry import angle_error, medoid_index, planar_pose, relative_pose
from hte_jax.qd.archive import Archive, map_rows, squared_distance
from hte_jax.qd.repertoire import Evaluation, Repertoire
from hte_jax.qd.task_spec import EvaluateFn, TaskSpec
from hte_jax.sim.robot import NUM_LEGS, Robot
from hte_jax.sim.env import SimState
from hte_jax.sim.rollout import RolloutSpec, rollout

GENES = NUM_LEGS * bottom.DESCRIPTORS  # per leg a target in the bottom layer's descriptor space
PRIMARY = 3  # x, y, yaw
DESCRIPTORS = PRIMARY + NUM_LEGS
NUM_PATTERNS = 2**NUM_LEGS
EXTRAS = {"contact_fraction": ((NUM_LEGS,), "float32"), "medoid": ((), "int32")}  # of the reported (medoid) second
ARCHIVE_L = 0.05  # default distance threshold of the layer's archive (`HBRConfig.middle_l`)
QD_OFFSET = -math.pi  # the lowest angle error


@dataclasses.dataclass(frozen=True)
class MiddleTask:
    """How a body motion is evaluated (hashable): `samples` chained seconds of `steps` control steps;
    max_step (m) / max_turn (rad): |x|, |y| / |yaw| range of the primary descriptor; a leg's bit is 1
    above `contact_threshold` of the second; purity: fitness penalty per unit of contact on lifted legs."""

    samples: int = integer(10)
    steps: int = integer(100)
    max_step: float = number(0.5, 0.0, open_low=True)
    max_turn: float = number(1.0, 0.0, open_low=True)
    contact_threshold: float = number(0.3, 0.0, 1.0)
    purity: float = number(0.0, 0.0)

    def __post_init__(self):
        check_fields(self, "middle ")

    @property
    def spec(self) -> RolloutSpec:
        total = self.samples * self.steps
        return RolloutSpec(num_steps=total, pose_steps=tuple(range(0, total + 1, self.steps)), record_contacts=True)

    def normalise(self, displacement: jax.Array) -> jax.Array:
        """(..., 3) displacement (m, m, rad) -> (..., 3) primary descriptor."""
        scale = jnp.asarray([2 * self.max_step, 2 * self.max_step, 2 * self.max_turn], jnp.float32)
        return displacement / scale + 0.5

    def denormalise(self, primary: jax.Array) -> jax.Array:
        """Inverse of `normalise`."""
        scale = jnp.asarray([2 * self.max_step, 2 * self.max_step, 2 * self.max_turn], jnp.float32)
        return (primary - 0.5) * scale


def middle_spec(capacity: int, l: float = ARCHIVE_L, evaluate: EvaluateFn | None = None) -> TaskSpec:
    """The middle layer as a QD task: 18 genes, an archive of `capacity` slots over [0, 1]^9, threshold `l`."""
    return TaskSpec("hbr-middle", GENES, Archive(capacity, (0.0,) * DESCRIPTORS, (1.0,) * DESCRIPTORS, l), evaluate,
                    EXTRAS, QD_OFFSET)


def nearest_index(points: jax.Array, mask: jax.Array, queries: jax.Array, chunk: int = 4096) -> jax.Array:
    """(...,) index of the nearest `mask`-ed row of points (C, D) to queries (..., D) (ties: lowest; -1: none)."""
    shape = queries.shape[:-1]
    flat = queries.reshape(-1, queries.shape[-1])

    def block(args):
        (q,) = args
        dist = jnp.where(mask[None, :], squared_distance(q, points), jnp.inf)
        return jnp.argmin(dist, axis=-1).astype(jnp.int32)

    return jnp.where(mask.any(), map_rows(block, (flat,), (0.0,), chunk), -1).reshape(shape)


_nearest_index = jax.jit(nearest_index, static_argnames=("chunk",))  # one program for host-side lookups


def leg_controllers(bottom: Repertoire, targets: jax.Array) -> jax.Array:
    """(..., 6, 3) per-leg targets in bottom descriptor space -> (..., 36) controllers."""
    index = nearest_index(bottom.descriptors, bottom.filled, targets)
    return bottom.genotypes[jnp.maximum(index, 0)].reshape(*targets.shape[:-2], NUM_LEGS * 6)


# The last few `elite_controllers` results on concrete inputs, by a digest of those inputs: loading the same HBR
# or spare archive again in a process (a resumed command, a second episode batch) skips the lookup, seconds of
# CPU at the shipped sizes.
ELITE_CACHE_SIZE = 4
_elite_cache: OrderedDict[str, np.ndarray] = OrderedDict()


def _digest(arrays) -> str:
    """sha256 of the arrays' dtypes, shapes and bytes."""
    digest = hashlib.sha256()
    for x in arrays:
        x = np.ascontiguousarray(x)
        digest.update(f"{x.dtype}{x.shape}".encode())
        digest.update(x.tobytes())
    return digest.hexdigest()


def elite_controllers(bottom: Repertoire, genotypes: jax.Array, filled: jax.Array) -> jax.Array:
    """(C, 36) controllers of the `filled` rows of (C, 18) middle genotypes, zeros elsewhere; outside a jit only
    filled rows are looked up, among the filled bottom elites in order (same values, a quarter of the work), and
    the last `ELITE_CACHE_SIZE` results are kept, keyed by a digest of the inputs."""
    inputs = (bottom.descriptors, bottom.filled, bottom.genotypes, genotypes, filled)
    if any(isinstance(x, jax.core.Tracer) for x in inputs) or not np.asarray(bottom.filled).any():
        return jnp.where(filled[:, None], leg_controllers(bottom, decode(genotypes)), 0.0)
    key = _digest([np.asarray(x) for x in inputs])
    if key in _elite_cache:
        _elite_cache.move_to_end(key)
        return jax.device_put(_elite_cache[key])
    keep = np.flatnonzero(np.asarray(bottom.filled))
    rows = np.flatnonzero(np.asarray(filled))
    genes = np.asarray(bottom.genotypes)
    out = np.zeros((genotypes.shape[0], NUM_LEGS * genes.shape[-1]), genes.dtype)
    if rows.size:
        points = np.asarray(bottom.descriptors)[keep]
        index = _nearest_index(points, np.ones(keep.size, bool), decode(np.asarray(genotypes)[rows]))
        out[rows] = genes[keep[np.asarray(index)]].reshape(rows.size, -1)
    out.flags.writeable = False
    _elite_cache[key] = out
    while len(_elite_cache) > ELITE_CACHE_SIZE:
        _elite_cache.popitem(last=False)
    return jax.device_put(out)


def decode(genotypes: jax.Array) -> jax.Array:
    """(..., 18) middle genotypes -> (..., 6, 3) per-leg bottom-descriptor targets."""
    return genotypes.reshape(*genotypes.shape[:-1], NUM_LEGS, 3)


def pattern_code(bits: jax.Array, xp=jnp) -> jax.Array:
    """(..., 6) contact bits (leg 0 first) -> (...,) int32 pattern in [0, 64), leg 0 the most significant bit (jax
    or NumPy)."""
    weights = 2 ** xp.arange(NUM_LEGS - 1, -1, -1)
    return xp.sum(xp.round(bits).astype(xp.int32) * weights, axis=-1).astype(xp.int32)


def pattern_bits(code: jax.Array, xp=jnp) -> jax.Array:
    """Inverse of `pattern_code`: (...,) int -> (..., 6) float32 bits (jax or NumPy)."""
    return ((xp.asarray(code)[..., None] >> xp.arange(NUM_LEGS - 1, -1, -1)) & 1).astype(xp.float32)


def evaluate_controllers(robot: Robot, start: SimState, task: MiddleTask, params: jax.Array) -> Evaluation:
    """Evaluate (B, 36) controllers as body motions from `start`: descriptors (B, 9), extras (B, ...) `EXTRAS`."""
    batch = params.shape[0]
    tiled = jnp.broadcast_to(params[:, None, :], (batch, task.samples, params.shape[-1]))
    result = rollout(robot, tiled, jnp.zeros(NUM_LEGS, bool), start, task.spec)
    poses = planar_pose(result.base_pos, result.base_quat)  # (B, S + 1, 3)
    displacement = relative_pose(poses[:, :-1], poses[:, 1:])  # (B, S, 3)
    primary = task.normalise(displacement)
    medoid = medoid_index(primary)
    rows = jnp.arange(batch)
    chosen = primary[rows, medoid]
    fraction = result.foot_contacts.reshape(batch, task.samples, task.steps, NUM_LEGS).mean(axis=2)[rows, medoid]
    bits = (fraction > task.contact_threshold).astype(jnp.float32)
    valid = result.valid & jnp.all((chosen >= 0.0) & (chosen <= 1.0), axis=-1)
    fitness = angle_error(displacement[rows, medoid])
    if task.purity:
        fitness = fitness - task.purity * jnp.sum(fraction * (1.0 - bits), axis=-1)
    return Evaluation(fitnesses=fitness, descriptors=jnp.concatenate([chosen, bits], axis=-1), valid=valid,
                      extras={"contact_fraction": fraction, "medoid": medoid.astype(jnp.int32)})


def evaluate_middle(robot: Robot, start: SimState, task: MiddleTask, bottom: Repertoire, key: jax.Array,
                    genotypes: jax.Array) -> Evaluation:
    """Evaluate (B, 18) middle genotypes (key unused: the evaluation is deterministic)."""
    del key
    return evaluate_controllers(robot, start, task, leg_controllers(bottom, decode(genotypes)))
