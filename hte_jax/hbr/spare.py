"""Spare sets: a pattern's 0 bit allows a foot down up to 30 % of the second; the spare set of pattern p
holds the middle elites below a strict 5 % on each leg p lifts, from the HBR and from a second archive
trained at that threshold (`experiments.train_spare`) appended after its slots (`with_spare`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.hbr.composition import PatternTable, StepModel, descriptor_steps, hbr_steps, member_table
from hte_jax.hbr.hierarchy import ANY_PATTERN, HBR
from hte_jax.hbr.middle import NUM_PATTERNS, PRIMARY, pattern_bits
from hte_jax.qd.repertoire import Repertoire

STRICT_CONTACT = 0.05  # a leg counts as lifted by a step that has its foot down less than this share
SPARE_L = 0.035  # the spare archive's distance threshold (the HBR's middle layer: 0.05)
SPARE_STREAM = 7  # folded into the seed's key: the spare archive's draws differ from the HBR's layers'


def lifted_legs(pattern: np.ndarray) -> np.ndarray:
    """(...,) pattern codes (leg 0 = most significant bit, 1 = down) -> (..., 6) bool, legs lifted."""
    return pattern_bits(pattern, xp=np) == 0


def spare_members(contact_fraction: np.ndarray, present: np.ndarray, strict: float = STRICT_CONTACT) -> np.ndarray:
    """(Cm, 6) stored contact fractions and (Cm,) bool usable slots -> (64, Cm) bool: elite e is in
    the spare set of pattern p when its contact is below `strict` on every leg p lifts."""
    off = np.asarray(contact_fraction) < strict  # (Cm, 6)
    lifted = lifted_legs(np.arange(NUM_PATTERNS))  # (64, 6)
    return np.asarray(present)[None, :] & np.all(off[None, :, :] | ~lifted[:, None, :], axis=-1)


def spare_table(hbr: HBR, strict: float = STRICT_CONTACT) -> PatternTable:
    """The spare sets of every pattern as a planning table; the pattern that lifts no leg keeps its own elites."""
    present = np.asarray(hbr.middle_patterns) >= 0
    if hbr.spare_count:
        present = present | (np.arange(present.size) >= present.size - hbr.spare_count)
    members = spare_members(np.asarray(hbr.middle.extras["contact_fraction"]), present, strict)
    # a pattern that lifts no leg spares nothing: its own elites, not the whole layer (and as wide)
    members[NUM_PATTERNS - 1] = np.asarray(hbr.middle_patterns) == NUM_PATTERNS - 1
    return member_table(members, hbr_steps(hbr))


def with_spare(hbr: HBR, spare: Repertoire, spare_params: jnp.ndarray, spare_steps: StepModel | None) -> HBR:
    """The HBR with the filled elites of a second middle archive `spare` (over its own bottom layer;
    extras with "contact_fraction") appended after its own slots, with their (Cs, 36) controllers and
    measured steps (None: descriptors); their contact bits re-computed at the HBR's threshold."""
    rows = np.flatnonzero(np.asarray(spare.filled))
    descriptors = np.asarray(spare.descriptors).copy()
    descriptors[:, PRIMARY:] = np.asarray(spare.extras["contact_fraction"]) > hbr.middle_task.contact_threshold

    def append(own, added):  # own's rows, then the spare's filled rows
        return jax.device_put(np.concatenate([np.asarray(own), np.asarray(added)[rows]]))  # on the host: no program

    main, own = hbr.middle, hbr_steps(hbr)
    added = spare_steps if spare_steps is not None else descriptor_steps(spare.descriptors)
    middle = Repertoire(genotypes=append(main.genotypes, spare.genotypes),
                        descriptors=append(main.descriptors, descriptors),
                        fitnesses=append(main.fitnesses, spare.fitnesses),
                        filled=jax.device_put(np.concatenate([np.asarray(main.filled), np.zeros(rows.size, bool)])),
                        extras={name: append(value, spare.extras[name]) for name, value in main.extras.items()})
    patterns = np.concatenate([np.asarray(hbr.middle_patterns), np.full(rows.size, ANY_PATTERN, np.int32)])
    steps = StepModel(steps=append(own.steps, added.steps), spread=append(own.spread, added.spread))
    return hbr.replace(middle=middle, middle_params=append(hbr.middle_params, spare_params),
                       middle_patterns=jax.device_put(patterns), step_model=steps, spare_count=int(rows.size))
