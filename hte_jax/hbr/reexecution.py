"""Re-executing top-layer skills with a contact pattern held for their three steps.

The modulation study (`hbr.modulation`, paper Fig. 4 / 5) and the measured pattern ends
(`hbr.pattern_ends`) both execute many (skill, pattern) pairs on the intact robot from the
standing state, in fixed-size jitted chunks; this module holds what they share: checking the
requested skills and patterns, and the chunked execution itself.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from hte_jax.hbr.composition import PatternTable, skill_ends
from hte_jax.hbr.hierarchy import HBR, STEPS_PER_SKILL, SkillResult, execute_skill
from hte_jax.hbr.middle import NUM_PATTERNS
from hte_jax.hbr.top import TopTask
from hte_jax.sim.robot import Robot
from hte_jax.sim.rollout import SimState


def checked_pairs(hbr: HBR, skills: np.ndarray | None, patterns: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(N,) top-grid cells (default every filled one) and (P,) patterns (default all 64), checked:
    ValueError for a cell that holds no skill or a pattern outside [0, 64)."""
    filled = np.flatnonzero(np.asarray(hbr.top.filled))
    slots = filled if skills is None else np.asarray(skills, np.int64)
    if not np.isin(slots, filled).all():
        raise ValueError(f"skills {slots[~np.isin(slots, filled)].tolist()} are not filled cells of the top layer")
    patterns = np.arange(NUM_PATTERNS) if patterns is None else np.asarray(patterns, np.int64)
    if patterns.size == 0 or patterns.min() < 0 or patterns.max() >= NUM_PATTERNS:
        raise ValueError(f"patterns must be in [0, {NUM_PATTERNS}), got {patterns.tolist()}")
    return slots, patterns


def stored_ends(hbr: HBR, task: TopTask, slots: np.ndarray) -> np.ndarray:
    """(N, 3) the skills' stored ends (x, y, yaw) in their start frame."""
    top = hbr.top
    return np.asarray(skill_ends(np.asarray(top.descriptors)[slots], np.asarray(top.extras["arrival_yaw"])[slots],
                                 task.extent))


def execute_held(
    robot: Robot, hbr: HBR, start: SimState, genes: np.ndarray, patterns: np.ndarray, ends: np.ndarray,
    table: PatternTable | None, summarise: Callable[[SkillResult], tuple], *, chunk: int = 4096,
    progress: bool = True, desc: str = "re-execution",
) -> list[np.ndarray]:
    """Execute M skills, row k with top genotype genes[k] (M, 9) and pattern patterns[k] (M,) held
    for its three steps, towards ends[k] (M, 3) (its end in the start frame, where `table` plans
    each step; None: the paper's nearest elite to each waypoint), from the unbatched state `start`.

    summarise(skill) -> tuple of (B, ...) arrays, traced inside the jitted chunk: what to keep of
    each execution. Runs ceil(M / chunk) chunks of one fixed size (the last padded with copies of
    its last row, which are dropped). Returns summarise's arrays concatenated over the M rows.
    """
    total = int(genes.shape[0])
    chunk = min(chunk, total)
    starts = jax.tree.map(lambda x: jnp.broadcast_to(x, (chunk, *x.shape)), start)

    @jax.jit
    def run_chunk(hbr, table, genes, wanted, ends):
        held = jnp.broadcast_to(wanted[:, None], (wanted.shape[0], STEPS_PER_SKILL))
        return summarise(execute_skill(robot, hbr, genes, starts, patterns=held, table=table, ends=ends))

    def padded(rows: np.ndarray, pad: int) -> np.ndarray:
        return np.concatenate([rows, np.repeat(rows[-1:], pad, axis=0)])

    outputs = []
    for begin in tqdm(range(0, total, chunk), disable=not progress, desc=desc, unit="chunk", leave=False):
        stop = min(begin + chunk, total)
        pad = chunk - (stop - begin)
        out = jax.device_get(run_chunk(hbr, table, jnp.asarray(padded(genes[begin:stop], pad)),
                                       jnp.asarray(padded(patterns[begin:stop], pad), jnp.int32),
                                       jnp.asarray(padded(ends[begin:stop], pad))))
        outputs.append([np.asarray(o)[: stop - begin] for o in out])
    return [np.concatenate(parts) for parts in zip(*outputs)]
