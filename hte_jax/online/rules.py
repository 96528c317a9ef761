"""Pattern rules: how an adaptation variant picks the contact pattern of each 1 s step of a skill.

A rule is a frozen dataclass that owns its state (a pytree with a leading (B,) episode axis):
`init(damages (B, 6), max_actions) -> state` (damages: each robot's damaged legs, whatever their damage model;
only an oracle reads them), `choose(state, context)
-> (pattern (B,) int32, -1: any; spare (B,) bool)` and `learn(state, observation) -> state`.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hte_jax.hbr.hierarchy import ANY_PATTERN, HBR, STEPS_PER_SKILL, select_middle
from hte_jax.hbr.middle import PRIMARY
from hte_jax.online.gp import HTE_KERNEL, GPData, add_observation, empty_gp, posterior
from hte_jax.online.secondary import ERROR_DIM, acquisition, allowed_patterns, oracle_patterns, relative_error, ucb_beta
from hte_jax.online.sensing import unusable_legs, usable_pattern
from hte_jax.sim.controller import commanded_travel
from hte_jax.sim.robot import NUM_LEGS

CANDIDATE_PATTERNS = allowed_patterns()  # (36,) the paper's candidates
DESCRIPTOR_DIM = 9  # a middle elite's descriptor: x, y, yaw, 6 contact bits


@struct.dataclass
class StepContext:
    """What B robots know before one 1 s step. hbr: the HBR. desired: (B, 3) normalised primary step
    wanted. t: (B,) int32 steps so far + 1 (GP-UCB's t). keys: (B, 2) PRNG keys of this step."""

    hbr: HBR
    desired: jax.Array
    t: jax.Array
    keys: jax.Array


@struct.dataclass
class StepObservation:
    """What B robots observed in one executed step. hbr: the HBR. elite: (B,) int32 middle elite executed.
    observed: (B, 3) normalised primary descriptor of the step made. contact_fraction: (B, 6) share of the
    second each foot was sensed down. leg_travel: (B, 6) rad each leg's joints moved. leg_commanded: (B, 6) rad its
    joint targets moved (what the controller commanded, after the tilt reflex), or None (a robot that does not
    report it: the elite's whole period, `controller.commanded_travel`)."""

    hbr: HBR
    elite: jax.Array
    observed: jax.Array
    contact_fraction: jax.Array
    leg_travel: jax.Array
    leg_commanded: jax.Array | None = None


@struct.dataclass
class NoState:
    """The state of a stateless rule (no fields)."""


class PatternRule(abc.ABC):
    """Base of pattern rules: stateless unless `init` and `learn` are overridden."""

    def init(self, damages: np.ndarray, max_actions: int) -> Any:
        return NoState()

    @abc.abstractmethod
    def choose(self, state: Any, context: StepContext) -> tuple[jax.Array, jax.Array]:
        """(pattern (B,) int32, spare (B,) bool)."""

    def learn(self, state: Any, observation: StepObservation) -> Any:
        return state


def _never(context: StepContext) -> jax.Array:
    return jnp.zeros(context.desired.shape[0], bool)


def candidate_elites(hbr: HBR, desired: jax.Array, patterns: np.ndarray = CANDIDATE_PATTERNS):
    """For desired primary steps (B, 3): the middle elite index (B, C) each of `patterns` (C,) would execute
    and found (B, C) (False where the repertoire has no elite with that pattern)."""
    batch, count = desired.shape[0], patterns.size
    queries, wanted = jnp.repeat(desired, count, axis=0), jnp.tile(jnp.asarray(patterns), batch)
    index, found = select_middle(hbr, queries, wanted)
    return index.reshape(batch, count), found.reshape(batch, count)


@dataclasses.dataclass(frozen=True)
class AnyPattern(PatternRule):
    """RTE on an HBR: the nearest elite in primary descriptor, any pattern, exactly as in training. spare: among
    the HBR's elites and the spare archive's together (`hbr.spare`), still any pattern and nothing sensed."""

    spare: bool = False

    def choose(self, state, context):
        rows = context.desired.shape[0]
        return jnp.full(rows, ANY_PATTERN, jnp.int32), jnp.full(rows, self.spare)


@struct.dataclass
class ErrorModel:
    """GP-UCB's state: the secondary GP (B, 3 L, 9 -> 3) of each step's relative errors."""

    gp: GPData


@dataclasses.dataclass(frozen=True)
class GpUcb(PatternRule):
    """The paper's HTE: GP-UCB over the 36 allowed patterns' nearest elites' predicted relative errors."""

    def init(self, damages, max_actions):
        gp = empty_gp(STEPS_PER_SKILL * max_actions, DESCRIPTOR_DIM, ERROR_DIM)
        return ErrorModel(jax.tree.map(lambda x: jnp.broadcast_to(x, (len(damages), *x.shape)), gp))

    def choose(self, state, context):
        columns = jnp.asarray(CANDIDATE_PATTERNS)
        every, found = candidate_elites(context.hbr, context.desired)
        inputs = context.hbr.middle.descriptors[every]
        mean, variance = jax.vmap(lambda gp, x: posterior(HTE_KERNEL, gp, x))(state.gp, inputs)
        score = acquisition(mean, variance, ucb_beta(context.t)[:, None])
        ucb = columns[jnp.argmax(jnp.where(found, score, -jnp.inf), axis=-1)]  # ties: the lowest pattern
        return jnp.where(found.any(axis=-1), ucb, ANY_PATTERN), _never(context)

    def learn(self, state, observation):
        executed = observation.hbr.middle.descriptors[observation.elite]  # (B, 9)
        return ErrorModel(jax.vmap(add_observation)(state.gp, executed, relative_error_of(observation)))


def relative_error_of(observation: StepObservation) -> jax.Array:
    """(B, 3) the paper's relative errors of the executed elites' steps (`secondary.relative_error`)."""
    executed = observation.hbr.middle.descriptors[observation.elite]
    return relative_error(executed[:, :PRIMARY], observation.observed)


@struct.dataclass
class TruePattern:
    """The oracle's state: (B,) int32 the pattern with exactly the intact legs down."""

    pattern: jax.Array


@dataclasses.dataclass(frozen=True)
class Oracle(PatternRule):
    """Perfect HTE: the pattern of the true damage, its damaged legs off the floor whatever their damage model
    (an upper bound; the only rule that reads it; a damage of the floor alone damages no leg). spare: run that
    pattern's steps from its spare set (the damaged legs kept off the floor)."""

    spare: bool = False

    def init(self, damages, max_actions):
        return TruePattern(oracle_patterns(damages))

    def choose(self, state, context):
        return state.pattern, jnp.full(context.desired.shape[0], self.spare)


@dataclasses.dataclass(frozen=True)
class RandomPattern(PatternRule):
    """Random HTE: a uniform pattern among the allowed ones the repertoire holds (a lower bound)."""

    def choose(self, state, context):
        columns = jnp.asarray(CANDIDATE_PATTERNS)
        _, found = candidate_elites(context.hbr, context.desired)
        drawn = columns[jax.vmap(jax.random.categorical)(context.keys, jnp.where(found, 0.0, -jnp.inf))]
        return jnp.where(found.any(axis=-1), drawn, ANY_PATTERN), _never(context)


@struct.dataclass
class LegSense:
    """What the robot sensed of its legs, summed over the episode (`sensing`). contacts: (B, 2, 6) seconds
    each leg was sensed down (row 0) and expected down by the executed elites (row 1). motion: (B, 2, 6)
    rad each leg's joints moved (row 0) and were commanded to move (row 1; none while the tilt reflex held the
    neutral pose)."""

    contacts: jax.Array
    motion: jax.Array


@dataclasses.dataclass(frozen=True)
class SensedLegs(PatternRule):
    """Ours: RTE's choice until a leg is sensed off the floor when it should be down, or not moving as
    commanded; then the pattern with every other leg down. spare: once a leg is sensed off the floor,
    run the pattern's steps from its spare set."""

    spare: bool = False

    def init(self, damages, max_actions):
        zeros = jnp.zeros((len(damages), 2, NUM_LEGS), jnp.float32)
        return LegSense(contacts=zeros, motion=zeros)

    def choose(self, state, context):
        spare = unusable_legs(state.contacts).any(axis=-1) if self.spare else _never(context)
        return usable_pattern(state.contacts, state.motion), spare

    def learn(self, state, observation):
        hbr, elite = observation.hbr, observation.elite
        expected = hbr.middle.extras["contact_fraction"][elite]  # (B, 6)
        commanded = observation.leg_commanded
        if commanded is None:  # a robot that does not report its commands: the elite's whole period
            commanded = commanded_travel(hbr.middle_params[elite])
        return LegSense(contacts=state.contacts + jnp.stack([observation.contact_fraction, expected], axis=1),
                        motion=state.motion + jnp.stack([observation.leg_travel, commanded], axis=1))


@struct.dataclass
class RuleBatch:
    """The pattern rules of B episodes. rules (static): the batch's rule objects. which: (B,) int32 each
    episode's index into them. states: one per rule, each kept for all (B,) rows (only its rows use it)."""

    which: jax.Array
    states: tuple
    rules: tuple = struct.field(pytree_node=False, default=())


def rule_indices(which, count: int) -> np.ndarray:
    """(B,) int32 NumPy `which`, checked to index `count` rules (ValueError otherwise)."""
    which = np.asarray(which, np.int32)
    if which.size and (which.min() < 0 or which.max() >= count):
        raise ValueError(f"rule indices must be in [0, {count}), got {sorted(set(which.tolist()))}")
    return which


def start_rules(rules: tuple, which: np.ndarray, damages: np.ndarray, max_actions: int) -> RuleBatch:
    """The rules of B new episodes: episode b runs `rules[which[b]]`; damages (B, 6) bool, the damaged legs
    (`Damage.legs`), reach `init`. which is checked (`rule_indices`) unless traced: inside a jit, check it first."""
    which = which if isinstance(which, jax.core.Tracer) else rule_indices(which, len(rules))
    states = tuple(rule.init(damages, max_actions) for rule in rules)
    return RuleBatch(which=jnp.asarray(which, jnp.int32), states=states, rules=tuple(rules))


def choose_patterns(batch: RuleBatch, context: StepContext) -> tuple[jax.Array, jax.Array]:
    """Every episode's pattern (B,) int32 and spare flag (B,) bool by its own rule."""
    choices = [rule.choose(state, context) for rule, state in zip(batch.rules, batch.states)]
    pattern, spare = choices[0]
    for i, (p, s) in enumerate(choices[1:], start=1):
        mine = batch.which == i
        pattern, spare = jnp.where(mine, p, pattern), jnp.where(mine, s, spare)
    return pattern.astype(jnp.int32), spare


def learn_rules(batch: RuleBatch, observation: StepObservation) -> RuleBatch:
    """Every rule learns from the step (each keeps a state for all rows; only its rows read it)."""
    return batch.replace(states=tuple(rule.learn(state, observation) for rule, state in zip(batch.rules, batch.states)))
