"""The planner's actions: the skills of a repertoire, and RTE's GP model of their outcome (facts 7.1).

An action is one elite of a repertoire (a top-layer skill of an HBR, or a flat controller). Its
GP input is the elite's normalised descriptor (2-D for the HBR top layer and Flat-2D, 8-D for
Flat-8D); its outcome is (dx, dy, cos dtheta, sin dtheta) in the pre-action frame, and the GP's
prior mean is the repertoire's own prediction: the stored final position and arrival heading.
`replayed_models` rebuilds the GPs of finished episodes from what they recorded.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hte_jax.geometry import wrap_angle
from hte_jax.online.gp import RTE_KERNEL, GPData, Kernel, add_observation, empty_gp, posterior
from hte_jax.qd.repertoire import Repertoire

OUTCOME_DIM = 4  # dx, dy, cos dtheta, sin dtheta


@struct.dataclass
class ActionSet:
    """A = number of actions (the filled elites, padded to a fixed size).

    slots: (A,) int32 repertoire slot of each action. inputs: (A, D) GP inputs (descriptors).
    prior: (A, 4) the repertoire's predicted outcome. mask: (A,) bool real actions.
    """

    slots: jax.Array
    inputs: jax.Array
    prior: jax.Array
    mask: jax.Array

    @property
    def size(self) -> int:
        return self.mask.shape[0]


def action_set(repertoire: Repertoire, extent: float, pad_to: int | None = None) -> ActionSet:
    """The filled elites of a repertoire whose descriptors start with normalised final (x, y) over
    +-extent and whose extras hold "arrival_yaw"."""
    filled = np.flatnonzero(np.asarray(repertoire.filled))
    size = filled.size if pad_to is None else pad_to
    if size < filled.size:
        raise ValueError(f"pad_to={pad_to} is smaller than the {filled.size} elites")
    descriptors = np.asarray(repertoire.descriptors)[filled]
    xy = descriptors[:, :2] * 2 * extent - extent
    yaw = np.asarray(repertoire.extras["arrival_yaw"])[filled]
    prior = np.concatenate([xy, np.cos(yaw)[:, None], np.sin(yaw)[:, None]], axis=1)

    def pad(values, fill=0):
        out = np.full((size, *values.shape[1:]), fill, values.dtype)
        out[: len(values)] = values
        return jnp.asarray(out)

    mask = np.zeros(size, bool)
    mask[: filled.size] = True
    return ActionSet(
        slots=pad(filled.astype(np.int32), -1),
        inputs=pad(descriptors.astype(np.float32)),
        prior=pad(prior.astype(np.float32)),
        mask=jnp.asarray(mask),
    )


def outcome(displacement: jax.Array) -> jax.Array:
    """(..., 3) measured (dx, dy, dtheta) -> (..., 4) GP target."""
    return jnp.concatenate(
        [displacement[..., :2], jnp.cos(displacement[..., 2:3]), jnp.sin(displacement[..., 2:3])], axis=-1
    )


def displacement_of(prediction: jax.Array, extent: float = 1.5) -> jax.Array:
    """(..., 4) predicted outcome -> (..., 3) (dx, dy, dtheta), dx and dy clipped to +-extent."""
    xy = jnp.clip(prediction[..., :2], -extent, extent)
    theta = jnp.arctan2(jnp.clip(prediction[..., 3], -1, 1), jnp.clip(prediction[..., 2], -1, 1))
    return jnp.concatenate([xy, wrap_angle(theta)[..., None]], axis=-1)


def empty_model(actions: ActionSet, capacity: int) -> GPData:
    return empty_gp(capacity, actions.inputs.shape[1], OUTCOME_DIM)


def observe(model: GPData, actions: ActionSet, index: jax.Array, displacement: jax.Array) -> GPData:
    """Add what action `index` did: its measured (dx, dy, dtheta) in the pre-action frame."""
    return add_observation(model, actions.inputs[index], outcome(displacement), actions.prior[index])


def predict(model: GPData, actions: ActionSet, kernel: Kernel = RTE_KERNEL) -> tuple[jax.Array, jax.Array]:
    """Predicted outcome (A, 4) and variance (A,) of every action at once."""
    return posterior(kernel, model, actions.inputs, actions.prior)


@jax.jit
def replayed_models(actions: ActionSet, executed: jax.Array, displacements: jax.Array) -> GPData:
    """The RTE GPs (B, L) of B episodes that executed actions `executed` (B, L) (-1: none, after the
    episode ended) and measured `displacements` (B, L, 3) (`episode.History.action` and `.observed`
    of episodes planning on one repertoire with its stored prior), with room for L observations.
    Actions whose displacement is not finite (a robot whose simulation failed) are left out."""
    executed, displacements = jnp.asarray(executed), jnp.asarray(displacements, jnp.float32)
    mask = (executed >= 0) & jnp.all(jnp.isfinite(displacements), axis=-1)
    index = jnp.maximum(executed, 0)

    def filled(values):
        return jnp.where(mask[..., None], values, 0.0).astype(jnp.float32)

    return GPData(
        inputs=filled(actions.inputs[index]),
        targets=filled(outcome(jnp.where(mask[..., None], displacements, 0.0))),
        prior=filled(actions.prior[index]),
        mask=mask,
        count=mask.sum(axis=-1).astype(jnp.int32),
    )
