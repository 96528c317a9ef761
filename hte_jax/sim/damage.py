"""Leg damages: a per-rollout (6,) bool mask; a damaged leg's servos hold a pose (`RobotConfig.damage_model`):
"raised" (the paper's "blocked in the air": femur and tibia straight up, the foot 0.19 m above the hip, off the
floor unless the body tilts ~80 degrees) or "locked" (standing, joints at 0: likely what the original simulated,
`docs/original_code.md` §10). The paper's seven conditions: each single leg and the middle legs 1+4."""

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

PAPER_DAMAGES: dict[str, tuple[int, ...]] = {**{f"leg{i}": (i,) for i in range(NUM_LEGS)}, "legs1+4": (1, 4)}
DAMAGE_NAMES = ("none", *PAPER_DAMAGES)
# APROL's prior conditions (paper section 5): the 6 single-leg and the 15 two-leg damages.
APROL_DAMAGES: dict[str, tuple[int, ...]] = {f"leg{i}": (i,) for i in range(NUM_LEGS)} | {
    f"legs{i}+{j}": (i, j) for i in range(NUM_LEGS) for j in range(i + 1, NUM_LEGS)}


def damage_mask(legs: Iterable[int]) -> np.ndarray:
    """(6,) bool mask with the given legs damaged."""
    mask = np.zeros(NUM_LEGS, bool)
    for leg in legs:
        if not (isinstance(leg, (int, np.integer)) and 0 <= leg < NUM_LEGS):
            raise ConfigError(f"leg index must be an integer in 0..{NUM_LEGS - 1}, got {leg!r}")
        mask[leg] = True
    return mask


def parse_damage(name: str | int) -> np.ndarray:
    """Mask for a damage name ('none', 'leg<i>', 'legs<i>+<j>') or the original's -l index (6: legs 1+4, -1: none)."""
    if isinstance(name, (int, np.integer)):
        names = list(PAPER_DAMAGES)
        if name == -1:
            return damage_mask(())
        if 0 <= name < len(names):
            return damage_mask(PAPER_DAMAGES[names[name]])
        raise ConfigError(f"unknown damage index {name}; expected -1 (none) or 0..{len(names) - 1}")
    if name == "none":
        return damage_mask(())
    if name in APROL_DAMAGES:  # the paper's too
        return damage_mask(APROL_DAMAGES[name])
    raise ConfigError(f"unknown damage {name!r}; expected 'none', 'leg<i>' or 'legs<i>+<j>' with 0 <= i < j <= 5 "
                      f"(the paper's: {', '.join(DAMAGE_NAMES)})")


def paper_damage_masks() -> np.ndarray:
    """(7, 6) bool masks of the paper's conditions, in `PAPER_DAMAGES` order."""
    return np.stack([damage_mask(legs) for legs in PAPER_DAMAGES.values()])


def damage_masks(names: Iterable[str]) -> np.ndarray:
    """(N, 6) bool masks of damage names (see `parse_damage`)."""
    return np.stack([parse_damage(name) for name in names])


def damaged_joint_mask(damage: jax.Array, xp=jnp) -> jax.Array:
    """(6,) leg mask -> (18,) joint mask, leg-major joint order (jax or NumPy)."""
    return xp.repeat(damage, JOINTS_PER_LEG, axis=-1)


def damaged_pose(model: str) -> tuple[float, float, float]:
    """(hip yaw, femur, tibia) a damaged leg holds under damage model `model` ("raised" or "locked")."""
    if model not in DAMAGED_POSES:
        raise ConfigError(f"unknown damage model {model!r}; expected one of {', '.join(DAMAGED_POSES)}")
    return DAMAGED_POSES[model]


def apply_damage(targets: jax.Array, damage: jax.Array, pose: tuple[float, float, float] = DAMAGED_POSE,
                 xp=jnp) -> jax.Array:
    """targets (18,) rad with the legs damaged by `damage` (6,) bool set to `pose` (one leg's three joints; jax or
    NumPy)."""
    pose = xp.tile(xp.asarray(pose, targets.dtype), NUM_LEGS)
    return xp.where(damaged_joint_mask(damage, xp), pose, targets)
