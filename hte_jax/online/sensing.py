"""What a robot senses of its own legs: which ones it should stop using (ours, not the paper's;
`docs/design.md`, Sensing the legs). contacts and motion: (..., 2, 6), sensed (row 0) beside expected.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from hte_jax.hbr.middle import pattern_code

CONTACT_EVIDENCE = 0.3  # seconds of expected floor contact before a leg is judged (`unusable_legs`)
CONTACT_RATIO = 0.1  # a leg sensed down for less than this share of its expected contact is unusable
JOINT_EVIDENCE = 3.0  # rad of commanded joint travel before a leg's tracking is judged (`stuck_legs`)
JOINT_RATIO = 0.55  # a leg whose joints moved less than this share of the commanded travel is stuck


def unusable_legs(contacts: jax.Array, evidence: float = CONTACT_EVIDENCE, ratio: float = CONTACT_RATIO) -> jax.Array:
    """(..., 2, 6) seconds each leg was sensed and expected down -> (..., 6) bool: sensed less than `ratio`
    of the expected contact, once at least `evidence` seconds were expected."""
    sensed, expected = contacts[..., 0, :], contacts[..., 1, :]
    return (expected >= evidence) & (sensed < ratio * expected)


def stuck_legs(motion: jax.Array, evidence: float = JOINT_EVIDENCE, ratio: float = JOINT_RATIO) -> jax.Array:
    """(..., 2, 6) rad each leg's joints moved and were commanded to move -> (..., 6) bool: moved less than
    `ratio` of the commanded travel, once at least `evidence` rad were commanded."""
    moved, commanded = motion[..., 0, :], motion[..., 1, :]
    return (commanded >= evidence) & (moved < ratio * commanded)


def usable_pattern(contacts: jax.Array, motion: jax.Array | None = None) -> jax.Array:
    """(..., 2, 6) sensed and expected contact, optionally (..., 2, 6) moved and commanded travel -> (...,)
    int32 the pattern with every leg down but the unusable (or stuck) ones, or -1 while all seem usable."""
    bad = unusable_legs(contacts)
    if motion is not None:
        bad = bad | stuck_legs(motion)
    return jnp.where(bad.any(axis=-1), pattern_code((~bad).astype(jnp.float32)), -1).astype(jnp.int32)
