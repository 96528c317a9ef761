"""The adaptation variants, one table entry each, and the rules that pick a step's contact pattern.

A `Variant` names the repertoire an episode plans with (the HBR, or a shipped flat repertoire)
and, for the HBR, the `rule` that picks the contact pattern of each 1 s step. A rule is a
function of a `StepContext` (what B robots know before a step) that returns the pattern (B,)
(-1: any pattern, RTE's nearest elite) and, optionally, the primary step (B, 3) to look its elite
up with. Jitted code sees a rule only as its integer, its position in `RULES`: every rule's choice
is computed for the whole batch and each episode takes its own, so all variants share one
compiled program.

Adding a variant is one entry (`add_variant`); adding a rule is one function (`add_rule`);
`docs/extending.md` (example 2) adds HTE on the GP's mean alone and runs it through `maze_eval`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hte_jax.errors import ConfigError
from hte_jax.hbr.execution import ANY_PATTERN, HBR, select_middle
from hte_jax.hbr.middle import NUM_PATTERNS, PRIMARY
from hte_jax.online.gp import HTE_KERNEL, GPData, posterior
from hte_jax.online.secondary import (
    acquisition,
    allowed_patterns,
    leg_effects,
    leg_miss,
    predicted_landing_miss,
    predicted_miss,
    ucb_beta,
    unusable_legs,
    usable_pattern,
)

CANDIDATE_PATTERNS = allowed_patterns()  # (36,) the paper's candidates
ALL_PATTERNS = np.arange(NUM_PATTERNS, dtype=np.int32)  # (64,) the predicted-miss rules' candidates
ERROR_DIM = 3  # the secondary GP's outputs: 3 relative errors, 3 absolute, 3 signed deviations


@struct.dataclass
class StepContext:
    """What B robots know before one 1 s step (shared by every rule; computed once).

    hbr: the HBR. desired: (B, 3) normalised primary step wanted. t: (B,) GP-UCB step count (>= 1).
    keys: (B, 2) PRNG keys. oracle: (B,) int32 the true damage's pattern (Perfect HTE only).
    optimism: (B,) confidence weight of the predicted-miss rule. secondary: GPData (B, ...) the
    secondary GP. contacts: (B, 2, 6) seconds each leg was sensed on the floor (row 0) and expected
    on it by the executed elites' stored contact fractions (row 1), summed over the episode.
    motion: (B, 2, 6) radians each leg's joints moved (row 0) and were commanded to move by the
    executed elites' controllers (row 1), summed over the episode.
    every: (B, 64) int32 nearest elite of each pattern p (column p) to `desired`; found: (B, 64)
    bool, the pattern has elites. inputs: (B, 64, 9) their descriptors. mean: (B, 64, 9) and
    variance: (B, 64) the secondary GP's posterior at them.
    """

    hbr: HBR
    desired: jax.Array
    t: jax.Array
    keys: jax.Array
    oracle: jax.Array
    optimism: jax.Array
    secondary: GPData
    contacts: jax.Array
    motion: jax.Array
    every: jax.Array
    found: jax.Array
    inputs: jax.Array
    mean: jax.Array
    variance: jax.Array


Rule = Callable[[StepContext], "tuple[jax.Array, jax.Array | None]"]


@struct.dataclass
class PatternState:
    """What the pattern rules of B episodes carry from step to step.

    mode: (B,) int32 each episode's rule (`rule_index`). oracle: (B,) int32 the true damage's
    pattern. optimism: (B,) float32 confidence weight of the predicted-miss rule. secondary: GPData
    (B, 3 L, 9, 9) HTE's error model (relative errors, absolute and signed deviations of each
    executed elite). contacts: (B, 2, 6) float32 seconds each leg was sensed on the floor (row 0)
    and expected on it by the executed elites' stored contact fractions (row 1), summed.
    motion: (B, 2, 6) float32 radians each leg's joints moved (row 0) and were commanded to move
    (row 1), summed. sparing: (B,) int32 when a chosen pattern is executed from its sparing set
    (`hbr.sparing`: the elites that keep its lifted legs off the floor) rather than from its
    elites, an index into `SPARING` (`spares_now`).
    measured: (B,) bool, the planner's prior of each skill is its end measured under the pattern of
    the last executed step (`hbr.pattern_ends`), not its stored end. last: (B,) int32 the pattern of
    the last executed step (-1: any, or no step yet).
    """

    mode: jax.Array
    oracle: jax.Array
    optimism: jax.Array
    secondary: GPData
    contacts: jax.Array
    motion: jax.Array
    sparing: jax.Array
    measured: jax.Array
    last: jax.Array


SPARING = ("never", "always", "off-floor")  # when a variant executes a chosen pattern from its sparing set


def spares_now(learnt: PatternState) -> jax.Array:
    """(B,) bool: the episodes that execute their chosen pattern from its sparing set now: "always",
    or "off-floor" once some leg is sensed off the floor (`secondary.unusable_legs`). A leg locked
    in its standing pose keeps touching the floor and holds the body up, so a locked leg is lifted
    by the pattern's own elites (which may still touch), while a leg blocked in the air is spared."""
    off_floor = unusable_legs(learnt.contacts).any(axis=-1)
    return (learnt.sparing == SPARING.index("always")) | ((learnt.sparing == SPARING.index("off-floor")) & off_floor)


def candidate_elites(hbr: HBR, desired: jax.Array, patterns: np.ndarray = CANDIDATE_PATTERNS):
    """For desired primary descriptors (B, 3): the middle elite each of `patterns` (C,) would execute.

    Returns index (B, C) and found (B, C) (False where the repertoire has no elite with that pattern).
    """
    batch, count = desired.shape[0], patterns.size
    queries = jnp.repeat(desired, count, axis=0)
    wanted = jnp.tile(jnp.asarray(patterns), batch)
    index, found = select_middle(hbr, queries, wanted)
    return index.reshape(batch, count), found.reshape(batch, count)


def step_context(hbr: HBR, desired: jax.Array, t: jax.Array, keys: jax.Array, oracle: jax.Array,
                 optimism: jax.Array, secondary: GPData, contacts: jax.Array, motion: jax.Array) -> StepContext:
    """The context every rule reads: each pattern's nearest elite and the GP's posterior there."""
    every, found = candidate_elites(hbr, desired, ALL_PATTERNS)
    inputs = hbr.middle.descriptors[every]
    mean, variance = jax.vmap(lambda gp, x: posterior(HTE_KERNEL, gp, x))(secondary, inputs)
    return StepContext(hbr=hbr, desired=desired, t=t, keys=keys, oracle=oracle, optimism=optimism,
                       secondary=secondary, contacts=contacts, motion=motion, every=every, found=found, inputs=inputs,
                       mean=mean, variance=variance)


def any_pattern(ctx: StepContext):
    """RTE on an HBR: the nearest elite in primary descriptor, any pattern, exactly as in training."""
    return jnp.full(ctx.desired.shape[0], ANY_PATTERN, jnp.int32), None


def gp_ucb(ctx: StepContext):
    """HTE (the paper's): GP-UCB over the 36 allowed patterns on the predicted relative errors."""
    columns = jnp.asarray(CANDIDATE_PATTERNS)
    found = ctx.found[:, columns]
    score = acquisition(ctx.mean[:, columns, :ERROR_DIM], ctx.variance[:, columns], ucb_beta(ctx.t)[:, None])
    ucb = columns[jnp.argmax(jnp.where(found, score, -jnp.inf), axis=-1)]  # ties: the lowest pattern
    return jnp.where(found.any(axis=-1), ucb, ANY_PATTERN), None


def oracle(ctx: StepContext):
    """Perfect HTE: the pattern of the true damage (the intact legs down)."""
    return ctx.oracle, None


def random_pattern(ctx: StepContext):
    """Random HTE: a uniform pattern among the allowed ones the repertoire holds."""
    columns = jnp.asarray(CANDIDATE_PATTERNS)
    found = ctx.found[:, columns]
    drawn = columns[jax.vmap(jax.random.categorical)(ctx.keys, jnp.where(found, 0.0, -jnp.inf))]
    return jnp.where(found.any(axis=-1), drawn, ANY_PATTERN), None


def least_miss(ctx: StepContext):
    """Ours: every pattern's nearest elite scored by its predicted miss (primary mismatch plus the
    GP's predicted deviation, `secondary.predicted_miss`); RTE's choice while nothing is learnt."""
    miss = predicted_miss(ctx.desired, ctx.inputs[..., :PRIMARY], ctx.mean[..., ERROR_DIM:2 * ERROR_DIM],
                          jnp.sqrt(jnp.maximum(ctx.variance, 0.0)), ctx.optimism[:, None, None])
    return jnp.argmin(jnp.where(ctx.found, miss, jnp.inf), axis=-1).astype(jnp.int32), None


def drift(ctx: StepContext):
    """Ours: as `least_miss`, but each candidate lands where the GP's signed deviation moves it, and
    the candidates also include every pattern's nearest elite to the wanted step less the drift
    predicted for RTE's choice (a damage that pulls the robot one way is aimed against)."""
    hbr, desired = ctx.hbr, ctx.desired
    signed = ctx.mean[..., 2 * ERROR_DIM:]  # (B, 64, 3)
    nearest, _ = select_middle(hbr, desired, jnp.full(desired.shape[0], ANY_PATTERN, jnp.int32))
    rte_column = hbr.middle_patterns[nearest]  # RTE's elite is the nearest of its own pattern
    aim = desired - jnp.take_along_axis(signed, rte_column[:, None, None], axis=1)[:, 0]
    aimed, aimed_found = candidate_elites(hbr, aim, ALL_PATTERNS)
    aimed_inputs = hbr.middle.descriptors[aimed]
    aimed_mean, _ = jax.vmap(lambda gp, x: posterior(HTE_KERNEL, gp, x))(ctx.secondary, aimed_inputs)
    miss = jnp.concatenate([
        jnp.where(ctx.found, predicted_landing_miss(desired, ctx.inputs[..., :PRIMARY], signed), jnp.inf),
        jnp.where(aimed_found, predicted_landing_miss(desired, aimed_inputs[..., :PRIMARY],
                                                      aimed_mean[..., 2 * ERROR_DIM:]), jnp.inf),
    ], axis=-1)
    best = jnp.argmin(miss, axis=-1)
    query = jnp.where((best >= NUM_PATTERNS)[:, None], aim, desired)
    return (best % NUM_PATTERNS).astype(jnp.int32), query


def legs(ctx: StepContext):
    """Ours: every pattern's nearest elite scored by its primary mismatch plus the learnt effect of
    each leg it puts down (`secondary.leg_effects`); RTE's choice while nothing is learnt."""
    by_legs = leg_miss(ctx.desired, ctx.inputs, jax.vmap(leg_effects)(ctx.secondary))
    return jnp.argmin(jnp.where(ctx.found, by_legs, jnp.inf), axis=-1).astype(jnp.int32), None


def sensed_contacts(ctx: StepContext):
    """Ours: RTE's choice until a leg is sensed not to touch the floor when its elites should
    (`secondary.usable_pattern`); then the pattern with every other leg down."""
    return usable_pattern(ctx.contacts), None


def sensed_legs(ctx: StepContext):
    """Ours: RTE's choice until a leg is sensed not to touch the floor when its elites should, or not
    to move its joints as its controllers ask (`secondary.usable_pattern` with the joint motion: a
    leg locked in any pose); then the pattern with every other leg down."""
    return usable_pattern(ctx.contacts, ctx.motion), None


RULES: dict[str, Rule] = {
    "any": any_pattern,
    "gp-ucb": gp_ucb,
    "oracle": oracle,
    "random": random_pattern,
    "least-miss": least_miss,
    "drift": drift,
    "legs": legs,
    "contacts": sensed_contacts,
    "sensed": sensed_legs,
}


@dataclasses.dataclass(frozen=True)
class Variant:
    """One adaptation variant.

    name: what `maze_eval --variant` calls it. rule: the key in `RULES` that picks each step's
    pattern ("any" for flat repertoires). repertoire: "hbr", or the shipped flat repertoire it plans
    with ("2d", "8d", "aprol": APROL's 21). summary: one line for the docs and `--help`.
    sparing: when a chosen pattern's steps are planned among its sparing set (`hbr.sparing`: the
    middle elites with under 5 % contact on each leg the pattern lifts, any contact on the others)
    instead of among the elites of that pattern at the HBR's contact threshold (needs planned
    composition): one of `SPARING`, "never", "always" or "off-floor" (`spares_now`).
    measured_ends: the planner predicts each skill from its end measured under the pattern the
    last step was executed with (`hbr.pattern_ends`, a file beside the HBR), not its stored end.
    """

    name: str
    rule: str = "any"
    repertoire: str = "hbr"
    summary: str = ""
    sparing: str = "never"
    measured_ends: bool = False

    @property
    def hierarchical(self) -> bool:
        return self.repertoire == "hbr"

    @property
    def spares(self) -> bool:
        """Whether the variant ever executes from sparing sets."""
        return self.sparing != "never"


VARIANTS: dict[str, Variant] = {}


def add_variant(variant: Variant) -> Variant:
    """Register a variant (its rule must be registered first; names are unique)."""
    if variant.name in VARIANTS:
        raise ConfigError(f"variant {variant.name!r} is already defined")
    if variant.rule not in RULES:
        raise ConfigError(f"variant {variant.name!r}: unknown rule {variant.rule!r}; known: {', '.join(RULES)}")
    if variant.sparing not in SPARING:
        raise ConfigError(f"variant {variant.name!r}: sparing {variant.sparing!r} is not one of {', '.join(SPARING)}")
    if not variant.hierarchical and (variant.rule != "any" or variant.spares or variant.measured_ends):
        raise ConfigError(f"variant {variant.name!r}: a flat repertoire has no contact patterns to choose")
    VARIANTS[variant.name] = variant
    return variant


def add_rule(name: str, rule: Rule) -> int:
    """Register a pattern rule; returns its integer (the programs compiled after this include it)."""
    if name in RULES:
        raise ConfigError(f"rule {name!r} is already defined")
    RULES[name] = rule
    return rule_index(name)


def rule_index(name: str) -> int:
    """The integer jitted code sees for a rule."""
    return list(RULES).index(name)


for _variant in (
    Variant("hte", "gp-ucb", summary="the paper's HTE: GP-UCB over 36 contact patterns"),
    Variant("perfect-hte", "oracle", summary="the pattern of the true damage (an upper bound)"),
    Variant("random-hte", "random", summary="a uniform random pattern each step (a lower bound)"),
    Variant("rte", "any", summary="RTE on the HBR: the nearest middle elite of any pattern"),
    Variant("hte-miss", "least-miss", summary="ours: the least predicted miss over every pattern"),
    Variant("hte-drift", "drift", summary="ours: the least predicted landing error, aiming against the drift"),
    Variant("hte-legs", "legs", summary="ours: primary mismatch plus a learnt per-leg penalty"),
    Variant("hte-contacts", "contacts", summary="ours: lift the legs sensed not to touch the floor"),
    Variant("hte-sensed", "sensed", summary="ours: lift the legs sensed off the floor or not following their joint commands"),
    Variant("hte-spare", "sensed", sparing="off-floor",
            summary="ours: as hte-sensed, with steps that keep the legs sensed off the floor really off it"),
    Variant("hte-spare-always", "sensed", sparing="always",
            summary="as hte-spare, keeping every lifted leg really off the floor, also a locked one"),
    Variant("perfect-spare", "oracle", sparing="always",
            summary="the true damage's legs kept really off the floor (an upper bound for hte-spare)"),
    Variant("hte-measured", "sensed", sparing="always", measured_ends=True,
            summary="ours: as hte-spare, planning with each skill's end measured under the chosen pattern"),
    Variant("perfect-measured", "oracle", sparing="always", measured_ends=True,
            summary="as perfect-spare, planning with each skill's end measured under the true damage's pattern"),
    Variant("2d-rte", repertoire="2d", summary="RTE on the flat x-y repertoire"),
    Variant("8d-rte", repertoire="8d", summary="RTE on the flat 8-D repertoire"),
    Variant("aprol", repertoire="aprol", summary="APROL's choice among 21 damage repertoires"),
):
    add_variant(_variant)


def variant(name: str) -> Variant:
    """The variant called `name` (clear error otherwise)."""
    if name not in VARIANTS:
        raise ConfigError(f"unknown variant {name!r}; choose from {', '.join(VARIANTS)}")
    return VARIANTS[name]


def rule_names() -> tuple[str, ...]:
    """The registered rules in integer order: jitted callers take it as a static argument, so a rule
    registered after a program was compiled gets a program of its own."""
    return tuple(RULES)


def choose(ctx: StepContext, mode: jax.Array, rules: tuple[str, ...] | None = None) -> tuple[jax.Array, jax.Array]:
    """Every episode's pattern (B,) and lookup step (B, 3) by its own rule `mode` (B,) int32, the
    integer of a name in `rules` (default: every registered rule, `rule_names()`)."""
    choices = [RULES[name](ctx) for name in (rule_names() if rules is None else rules)]
    pattern = jnp.select([mode == i for i in range(1, len(choices))], [c[0] for c in choices[1:]], choices[0][0])
    query = ctx.desired
    for i, (_, aimed) in enumerate(choices):
        if aimed is not None:
            query = jnp.where((mode == i)[:, None], aimed, query)
    return pattern.astype(jnp.int32), query
