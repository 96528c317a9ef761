"""The skills an episode plans with, and RTE's GP model of their outcome (`docs/original_code.md` §7.1):
input the elite's normalised descriptor, outcome (dx, dy, cos dtheta, sin dtheta) in the pre-action
frame, prior mean the repertoire's stored final position and heading.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hte_jax import sharding
from hte_jax.geometry import wrap_angle
from hte_jax.errors import ConfigError
from hte_jax.hbr.composition import COMPOSITIONS, PatternTable, planning_table
from hte_jax.hbr.hierarchy import HBR
from hte_jax.hbr.skill_grid import TopTask
from hte_jax.hbr.spare import spare_table
from hte_jax.online.gp import RTE_KERNEL, GPData, Kernel, posterior
from hte_jax.qd.repertoire import Repertoire
from hte_jax.sim.controller import NUM_PARAMS

OUTCOME_DIM = 4  # dx, dy, cos dtheta, sin dtheta


@struct.dataclass
class ActionSet:
    """A actions (the filled elites, padded). slots: (A,) int32 repertoire slot of each. inputs: (A, D) GP
    inputs (descriptors). prior: (A, 4) the repertoire's predicted outcome. mask: (A,) bool real actions."""

    slots: jax.Array
    inputs: jax.Array
    prior: jax.Array
    mask: jax.Array

    @property
    def size(self) -> int:
        return self.mask.shape[0]


def action_set(repertoire: Repertoire, extent: float, pad_to: int | None = None) -> ActionSet:
    """The filled elites of a repertoire of normalised final (x, y) over +-extent and "arrival_yaw" extras."""
    filled = np.flatnonzero(np.asarray(repertoire.filled))
    size = filled.size if pad_to is None else pad_to
    if size < filled.size:
        raise ValueError(f"pad_to={pad_to} is smaller than the {filled.size} elites")
    descriptors = np.asarray(repertoire.descriptors)[filled]
    xy, yaw = descriptors[:, :2] * 2 * extent - extent, np.asarray(repertoire.extras["arrival_yaw"])[filled]
    prior = np.concatenate([xy, np.cos(yaw)[:, None], np.sin(yaw)[:, None]], axis=1)

    def pad(values, fill=0):
        out = np.full((size, *values.shape[1:]), fill, values.dtype)
        out[: len(values)] = values
        return jax.device_put(out)

    return ActionSet(slots=pad(filled.astype(np.int32), -1), inputs=pad(descriptors.astype(np.float32)),
                     prior=pad(prior.astype(np.float32)), mask=jax.device_put(np.arange(size) < filled.size))


def _slot_rows(table: jax.Array, actions: ActionSet) -> jax.Array:
    """The rows of `table` (one per repertoire slot) of every action (row 0 for padding), gathered on the host."""
    return jax.device_put(np.asarray(table)[np.maximum(np.asarray(actions.slots), 0)])


def outcome(displacement: jax.Array) -> jax.Array:
    """(..., 3) measured (dx, dy, dtheta) -> (..., 4) GP target."""
    return jnp.concatenate([displacement[..., :2], jnp.cos(displacement[..., 2:3]), jnp.sin(displacement[..., 2:3])],
                           axis=-1)


def displacement_of(prediction: jax.Array, extent: float = 1.5) -> jax.Array:
    """(..., 4) predicted outcome -> (..., 3) (dx, dy, dtheta), dx and dy clipped to +-extent."""
    xy = jnp.clip(prediction[..., :2], -extent, extent)
    theta = jnp.arctan2(jnp.clip(prediction[..., 3], -1, 1), jnp.clip(prediction[..., 2], -1, 1))
    return jnp.concatenate([xy, wrap_angle(theta)[..., None]], axis=-1)


def predict(model: GPData, actions: ActionSet, kernel: Kernel = RTE_KERNEL) -> tuple[jax.Array, jax.Array]:
    """Predicted outcome (A, 4) and variance (A,) of every action at once."""
    return posterior(kernel, model, actions.inputs, actions.prior)


@struct.dataclass
class Skills:
    """The A actions an episode batch plans with: actions ActionSet (A,) or (K, A) for K repertoires, genotypes
    (A, 9) top-layer genotypes of `hbr` or (A, 36) / (K, A, 36) controllers, table the HBR's elites by pattern
    for planned steps (None: the paper's nearest elite), spare its spare sets (`hbr.spare`) or None."""

    actions: ActionSet
    genotypes: jax.Array
    hbr: HBR | None = None
    table: PatternTable | None = None
    spare: PatternTable | None = None

    @property
    def hierarchical(self) -> bool:
        return self.hbr is not None

    @property
    def num_maps(self) -> int:
        """K, the number of repertoires (1 unless APROL's set)."""
        return 1 if self.actions.mask.ndim == 1 else self.actions.mask.shape[0]

    @property
    def map_actions(self) -> ActionSet:
        """The actions with a leading (K,) repertoire axis (K = 1 for one repertoire)."""
        return self.actions if self.actions.mask.ndim == 2 else jax.tree.map(lambda x: x[None], self.actions)

    @property
    def map_genotypes(self) -> jax.Array:
        """(K, A, G) genotypes with a leading repertoire axis."""
        return self.genotypes if self.actions.mask.ndim == 2 else self.genotypes[None]


def hbr_skills(hbr: HBR, top_task: TopTask, pad_to: int | None = None, composition: str = "planned",
               spare: bool = False) -> Skills:
    """The filled top-layer cells of an HBR as actions; a step's elite is "waypoints" (the paper's nearest to the
    next waypoint) or "planned" (`hbr.composition`); spare: also build the spare sets (`hbr.spare`)."""
    if composition not in COMPOSITIONS:
        raise ConfigError(f"unknown composition {composition!r}; choose from {', '.join(COMPOSITIONS)}")
    if spare and composition != "planned":
        raise ConfigError("variants that run steps from spare sets need --composition planned")
    actions = action_set(hbr.top, top_task.extent, pad_to)
    genotypes = _slot_rows(hbr.top.genotypes, actions)
    table = planning_table(hbr) if composition == "planned" else None
    return Skills(actions=actions, genotypes=genotypes, hbr=hbr, table=table, spare=spare_table(hbr) if spare else None)


def flat_skills(repertoire: Repertoire, extent: float, pad_to: int | None = None) -> Skills:
    """The elites of a flat repertoire (2-D or 8-D descriptors) as actions."""
    actions = action_set(repertoire, extent, pad_to)
    genotypes = _slot_rows(repertoire.genotypes, actions)
    if genotypes.shape[-1] != NUM_PARAMS:
        raise ValueError(f"a flat repertoire holds {NUM_PARAMS}-parameter controllers, got {genotypes.shape[-1]} genes")
    return Skills(actions=actions, genotypes=genotypes)


def flat_skill_maps(repertoires: Repertoire, extent: float) -> Skills:
    """K flat repertoires (a `Repertoire` with a leading (K,) axis) as actions (K, A), A the largest's elites."""
    host = jax.device_get(repertoires)
    count = int(np.asarray(host.filled).sum(axis=-1).max())
    maps = [flat_skills(jax.tree.map(lambda x, k=k: x[k], host), extent, pad_to=count)
            for k in range(host.filled.shape[0])]
    return sharding.put_stacked(maps)
