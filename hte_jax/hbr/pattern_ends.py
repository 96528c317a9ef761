"""Measured pattern ends: where each top-layer skill really ends when executed with a contact pattern.

A top-layer skill stores one end (its descriptor and arrival heading): where it ended when its
steps were the middle elites training composed, whatever their patterns. Executed with a chosen
pattern, the same skill runs other elites and ends elsewhere (paper Fig. 4; with a sparing set,
`hbr.sparing`, a median 0.14-0.30 m away). The planner of an episode that executes its skills
with a pattern therefore predicts from a wrong prior. This module measures, once and offline, the
end of every skill executed by the intact robot from the standing state with each candidate
pattern held for its three steps (`execute_skill` with the same planning table and goal as online
execution), so that planning can use the end of the pattern it executes with
(`planning_priors`); the RTE GP then learns only what the damage changes.
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np

from hte_jax.hbr.composition import PatternTable
from hte_jax.hbr.execution import HBR
from hte_jax.hbr.middle import NUM_PATTERNS
from hte_jax.hbr.reexecution import checked_pairs, execute_held, stored_ends
from hte_jax.hbr.top import TopTask
from hte_jax.qd.io import CheckpointError, read_checkpoint, save_checkpoint
from hte_jax.sim.robot import Robot
from hte_jax.sim.rollout import SimState

KIND = "hte_jax.hbr.pattern_ends"
KIND_VERSION = 1
TABLES = ("sparing", "planned")  # which planning table the steps were planned among


def ends_file(table: str) -> str:
    """The file name beside an hbr.npz holding its measured ends for `table`."""
    return f"pattern_ends_{table}.npz"


@dataclasses.dataclass(frozen=True)
class PatternEnds:
    """Ends of N top skills executed with P patterns (host numpy arrays).

    patterns: (P,) int pattern codes. slots: (N,) top-grid cells. ends: (P, N, 3) float32 (dx, dy,
    dyaw) in the start frame. valid: (P, N) bool the execution stayed valid (its end is usable).
    table: the planning table the steps were planned among ("sparing" or "planned").
    fingerprint: `skills_fingerprint` of the HBR (with any spare archive) they were measured on.
    """

    patterns: np.ndarray
    slots: np.ndarray
    ends: np.ndarray
    valid: np.ndarray
    table: str
    fingerprint: str


def skills_fingerprint(hbr: HBR) -> str:
    """A short digest of the stored arrays skill execution depends on (nothing computed, so the
    same on every device): the top genotypes, the middle elites (the HBR's own and any appended
    spare ones) and the bottom layer."""
    digest = hashlib.sha256()
    for array in (hbr.top.genotypes, hbr.top.filled, hbr.middle.genotypes, hbr.middle.filled,
                  hbr.middle.extras["contact_fraction"], hbr.bottom.genotypes):
        digest.update(np.ascontiguousarray(np.asarray(array)).tobytes())
    return digest.hexdigest()[:16]


def measure_pattern_ends(
    robot: Robot, hbr: HBR, task: TopTask, start: SimState, table: PatternTable, table_name: str,
    patterns: np.ndarray, *, skills: np.ndarray | None = None, chunk: int = 4096, progress: bool = True,
) -> PatternEnds:
    """Execute top skills (default every filled cell) with each of `patterns` held for 3 steps,
    planning each step among `table`'s elites towards the skill's stored end, on the intact robot
    from `start` (the unbatched standing state), in fixed-size jitted chunks of `chunk` executions."""
    if table_name not in TABLES:
        raise ValueError(f"unknown table {table_name!r}; choose from {', '.join(TABLES)}")
    slots, patterns = checked_pairs(hbr, skills, patterns)
    # pattern-major pairs: pair k = (pattern k // N, skill k % N)
    ends, valid = execute_held(
        robot, hbr, start, np.asarray(hbr.top.genotypes)[np.tile(slots, patterns.size)], np.repeat(patterns, slots.size),
        np.tile(stored_ends(hbr, task, slots), (patterns.size, 1)), table,
        lambda skill: (skill.displacement, skill.valid), chunk=chunk, progress=progress, desc="pattern ends")
    ends = ends.reshape(patterns.size, slots.size, 3).astype(np.float32)
    valid = valid.reshape(patterns.size, slots.size) & np.isfinite(ends).all(axis=-1)
    return PatternEnds(patterns=patterns.astype(np.int32), slots=slots.astype(np.int32), ends=ends, valid=valid,
                       table=table_name, fingerprint=skills_fingerprint(hbr))


def planning_priors(ends: PatternEnds, action_slots: np.ndarray, stored_prior: np.ndarray) -> np.ndarray:
    """The RTE GP's prior of every action under every pattern: (64, A, 4) (dx, dy, cos, sin).

    action_slots: (A,) top cells of the planner's actions (-1: padding). stored_prior: (A, 4) the
    skills' stored outcomes. Row p holds the measured ends of pattern p where it was measured and
    its execution stayed valid, the stored outcome elsewhere (other patterns, padding, invalid).
    """
    action_slots = np.asarray(action_slots)
    priors = np.broadcast_to(np.asarray(stored_prior, np.float32), (NUM_PATTERNS, *np.shape(stored_prior))).copy()
    slots = np.asarray(ends.slots)
    order = np.argsort(slots, kind="stable")
    rows = np.flatnonzero(action_slots >= 0)
    at = np.minimum(np.searchsorted(slots[order], action_slots[rows]), max(slots.size - 1, 0))
    found = slots[order][at] == action_slots[rows] if slots.size else np.zeros(rows.size, bool)
    rows, cols = rows[found], order[at[found]]  # the actions that were measured, and their columns in `ends`
    for k, pattern in enumerate(ends.patterns):
        usable = ends.valid[k, cols]
        moved = ends.ends[k, cols[usable]]
        priors[pattern, rows[usable]] = np.concatenate(
            [moved[:, :2], np.cos(moved[:, 2:3]), np.sin(moved[:, 2:3])], axis=1)
    return priors


def save_pattern_ends(path: str | Path, ends: PatternEnds, metadata: dict | None = None) -> None:
    """Atomically write measured ends (the format `load_pattern_ends` reads)."""
    arrays = {"patterns": ends.patterns, "slots": ends.slots, "ends": ends.ends, "valid": ends.valid}
    header = {"kind": KIND, "kind_version": KIND_VERSION, "table": ends.table, "fingerprint": ends.fingerprint,
              **(metadata or {})}
    save_checkpoint(path, arrays, header, compress=True)


def load_pattern_ends(path: str | Path, hbr: HBR | None = None) -> PatternEnds:
    """Measured ends from `path`; with `hbr`, checked to have been measured on it (its skills and
    middle elites, spare ones included)."""
    arrays, header = read_checkpoint(path)
    meta = header.get("metadata", {})
    if meta.get("kind") != KIND:
        raise CheckpointError(f"{path}: not a pattern-ends file (kind {meta.get('kind')!r})")
    if meta.get("table") not in TABLES:
        raise CheckpointError(f"{path}: unknown planning table {meta.get('table')!r}")
    try:
        patterns, slots = np.asarray(arrays["patterns"]), np.asarray(arrays["slots"])
        ends, valid = np.asarray(arrays["ends"]), np.asarray(arrays["valid"])
    except KeyError as error:
        raise CheckpointError(f"{path}: missing array {error}") from None
    if ends.shape != (patterns.size, slots.size, 3) or valid.shape != ends.shape[:2]:
        raise CheckpointError(f"{path}: ends {ends.shape} / valid {valid.shape} do not match "
                              f"{patterns.size} patterns x {slots.size} skills")
    result = PatternEnds(patterns=patterns, slots=slots, ends=ends.astype(np.float32), valid=valid.astype(bool),
                         table=meta["table"], fingerprint=str(meta.get("fingerprint")))
    if hbr is not None and result.fingerprint != skills_fingerprint(hbr):
        raise CheckpointError(f"{path}: the ends were measured on other skills or middle elites "
                              f"(re-measure: python -m experiments.pattern_ends)")
    return result
