"""Leg damages: a per-rollout (6,) bool mask, batched like any other input.

A damaged leg's three servos hold a fixed pose whatever the controller asks. Two damage
models (`RobotConfig.damage_model`) choose the pose:

- "raised" (default, the paper's words: "a leg that is blocked in the air", section 5):
  `DAMAGED_POSE`, femur and tibia both pointing straight up, so the foot sits 0.19 m above
  the hip and 0.045 m outside it, and cannot reach the floor unless the body tilts by about
  80 degrees (training rollouts are invalid past 45).
- "locked": the standing pose (all three joints at 0), the foot on the floor. This is most
  likely what the original code simulated (`docs/original_code.md` §10: DART's initial position was
  never applied before the joints were locked).

The paper's seven conditions are each single leg 0..5 and the two middle legs 1+4.
"""

from __future__ import annotations

from collections.abc import Iterable

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.errors import ConfigError
from hte_jax.sim.robot import DAMAGE_MODELS, JOINTS_PER_LEG, NUM_LEGS

# (hip yaw, femur, tibia) in radians. The femur joint (+y axis) at -pi/2 turns the femur
# straight up; the tibia joint (-y axis) at +pi/2 turns the tibia up in line with it.
DAMAGED_POSE = (0.0, -np.pi / 2, np.pi / 2)
DAMAGED_POSES: dict[str, tuple[float, float, float]] = {"raised": DAMAGED_POSE, "locked": (0.0, 0.0, 0.0)}
assert tuple(DAMAGED_POSES) == DAMAGE_MODELS

PAPER_DAMAGES: dict[str, tuple[int, ...]] = {
    "leg0": (0,),
    "leg1": (1,),
    "leg2": (2,),
    "leg3": (3,),
    "leg4": (4,),
    "leg5": (5,),
    "legs1+4": (1, 4),
}
DAMAGE_NAMES = ("none", *PAPER_DAMAGES)
# APROL's prior conditions (paper section 5): the 6 single-leg and the 15 two-leg damages.
APROL_DAMAGES: dict[str, tuple[int, ...]] = {
    **{f"leg{i}": (i,) for i in range(NUM_LEGS)},
    **{f"legs{i}+{j}": (i, j) for i in range(NUM_LEGS) for j in range(i + 1, NUM_LEGS)},
}


def damage_mask(legs: Iterable[int]) -> np.ndarray:
    """(6,) bool mask with the given legs damaged."""
    mask = np.zeros(NUM_LEGS, bool)
    for leg in legs:
        if not (isinstance(leg, (int, np.integer)) and 0 <= leg < NUM_LEGS):
            raise ConfigError(f"leg index must be an integer in 0..{NUM_LEGS - 1}, got {leg!r}")
        mask[leg] = True
    return mask


def parse_damage(name: str | int) -> np.ndarray:
    """Mask for a damage name ('none', 'leg0'..'leg5', 'legs<i>+<j>') or the original's -l index.

    The original code's indices are 0..5 for single legs, 6 for legs 1+4, -1 for none.
    """
    if isinstance(name, (int, np.integer)):
        names = list(PAPER_DAMAGES)
        if name == -1:
            return damage_mask(())
        if 0 <= name < len(names):
            return damage_mask(PAPER_DAMAGES[names[name]])
        raise ConfigError(f"unknown damage index {name}; expected -1 (none) or 0..{len(names) - 1}")
    if name == "none":
        return damage_mask(())
    if name in PAPER_DAMAGES:
        return damage_mask(PAPER_DAMAGES[name])
    if name in APROL_DAMAGES:
        return damage_mask(APROL_DAMAGES[name])
    raise ConfigError(
        f"unknown damage {name!r}; expected 'none', 'leg<i>' or 'legs<i>+<j>' with 0 <= i < j <= 5 "
        f"(the paper's: {', '.join(DAMAGE_NAMES)})"
    )


def paper_damage_masks() -> np.ndarray:
    """(7, 6) bool masks of the paper's conditions, in `PAPER_DAMAGES` order."""
    return np.stack([damage_mask(legs) for legs in PAPER_DAMAGES.values()])


def damage_masks(names: Iterable[str]) -> np.ndarray:
    """(N, 6) bool masks of damage names (see `parse_damage`)."""
    return np.stack([parse_damage(name) for name in names])


def damaged_joint_mask(damage: jax.Array) -> jax.Array:
    """(6,) leg mask -> (18,) joint mask, leg-major joint order."""
    return jnp.repeat(damage, JOINTS_PER_LEG, axis=-1)


def damaged_pose(model: str) -> tuple[float, float, float]:
    """(hip yaw, femur, tibia) a damaged leg holds under damage model `model` ("raised" or "locked")."""
    if model not in DAMAGED_POSES:
        raise ConfigError(f"unknown damage model {model!r}; expected one of {', '.join(DAMAGED_POSES)}")
    return DAMAGED_POSES[model]


def apply_damage(targets: jax.Array, damage: jax.Array, pose: tuple[float, float, float] = DAMAGED_POSE) -> jax.Array:
    """Override the joint targets of damaged legs with `pose` (one leg's three joints).

    Args: targets (18,) radians; damage (6,) bool. Returns: (18,) radians.
    """
    pose = jnp.tile(jnp.asarray(pose, targets.dtype), NUM_LEGS)
    return jnp.where(damaged_joint_mask(damage), pose, targets)
