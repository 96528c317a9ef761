"""Secondary-descriptor modulation (paper section 5, Fig. 4 and 5): every skill re-executed with each contact
pattern held, counting the patterns (i) shown over the 3 s and (ii) ending in the skill's own top-grid cell."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from hte_jax.hbr.composition import PatternTable, skill_ends
from hte_jax.hbr.hierarchy import HBR, STEPS_PER_SKILL, SkillResult, execute_skill
from hte_jax.hbr.middle import NUM_PATTERNS, pattern_code
from hte_jax.hbr.top import TopTask
from hte_jax.sim.robot import Robot
from hte_jax.sim.env import SimState
from hte_jax.warp_calls import waited


@dataclasses.dataclass(frozen=True)
class Modulation:
    """Re-executions of N skills with P contact patterns (numpy): slots (N,) top-grid cells, patterns (P,),
    target_xy (N, 2) m stored ends, final_xy (N, P, 2) m reached, measured (N, P) pattern shown, valid (N, P),
    available (N, P) elites of the pattern for all 3 steps, final_cell (N, P) cell reached (-1 outside)."""

    slots: np.ndarray
    patterns: np.ndarray
    target_xy: np.ndarray
    final_xy: np.ndarray
    measured: np.ndarray
    valid: np.ndarray
    available: np.ndarray
    final_cell: np.ndarray

    def save(self, path) -> None:
        np.savez_compressed(path, **dataclasses.asdict(self))

    @classmethod
    def load(cls, path) -> Modulation:
        with np.load(path) as data:
            fields = [f.name for f in dataclasses.fields(cls)]
            missing = [name for name in fields if name not in data.files]
            if missing:
                raise ValueError(f"{path}: not a modulation file (missing {missing})")
            return cls(**{name: data[name] for name in fields})

    @property
    def shows_pattern(self) -> np.ndarray:
        """(N, P) the robot showed the wanted contact pattern."""
        return self.valid & (self.measured == self.patterns[None, :])

    def reaches(self, radius: float | None = None) -> np.ndarray:
        """(N, P) the robot ended in the skill's own cell (radius None) or within `radius` m of its end."""
        return self.valid & ((self.final_cell == self.slots[:, None]) if radius is None else (self.error <= radius))

    @property
    def error(self) -> np.ndarray:
        """(N, P) distance (m) between the reached and the skill's stored final position."""
        return np.linalg.norm(self.final_xy - self.target_xy[:, None, :], axis=-1)

    def counts(self, radius: float | None = None) -> dict[str, np.ndarray]:
        """Per skill (N,): "shows" (i), "reaches" (ii), "both", "median_error" (m) of the shown (NaN: none)."""
        shows, reaches = self.shows_pattern, self.reaches(radius)
        error = np.where(shows, self.error, np.nan)
        some = shows.any(axis=1)
        median = np.full(self.slots.size, np.nan)
        median[some] = np.nanmedian(error[some], axis=1)
        return {"shows": shows.sum(axis=1), "reaches": reaches.sum(axis=1), "both": (shows & reaches).sum(axis=1),
                "median_error": median}

    def summary(self, radii: tuple[float, ...] = (0.05, 0.1, 0.2)) -> dict:
        counts = self.counts()
        per_pattern = self.shows_pattern.sum(axis=0)
        within = {}
        for radius in radii:
            near = self.counts(radius)
            some = near["shows"] > 0
            share = near["both"][some] / near["shows"][some] if some.any() else np.array([np.nan])
            within[f"{radius:g}"] = {"reaches": float(near["reaches"].mean()), "both": float(near["both"].mean()),
                                     "share_of_shown": float(share.mean())}
        error = counts["median_error"]
        return {"skills": int(self.slots.size), "patterns": int(self.patterns.size),
                "mean_patterns_shown_per_skill": float(counts["shows"].mean()),
                "mean_patterns_reaching_cell_per_skill": float(counts["reaches"].mean()),
                "mean_patterns_both_per_skill": float(counts["both"].mean()),
                "skills_with_a_shown_pattern": int((counts["shows"] > 0).sum()),
                "median_error_m": float(np.nanmedian(error)) if np.isfinite(error).any() else float("nan"),
                "skills_showing_each_pattern": per_pattern.tolist(), "feasible_patterns": int((per_pattern > 0).sum()),
                "mean_patterns_per_skill_within_radius_m": within}


def checked_pairs(hbr: HBR, skills: np.ndarray | None, patterns: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(N,) top-grid cells (default all filled) and (P,) patterns (default all 64), else ValueError."""
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


def execute_held(robot: Robot, hbr: HBR, start: SimState, genes: np.ndarray, patterns: np.ndarray, ends: np.ndarray,
                 table: PatternTable | None, summarise: Callable[[SkillResult], tuple], *, chunk: int = 4096,
                 progress: bool = True, desc: str = "re-execution") -> list[np.ndarray]:
    """Execute M skills from the unbatched `start`: genotypes genes (M, 9), patterns (M,) each held 3 steps,
    ends (M, 3) in the start frame (planned towards with `table`; None: nearest elite to each waypoint), in
    fixed-size chunks. Returns `summarise(skill)`'s tuple of (B, ...) arrays concatenated over the M rows."""
    total = int(genes.shape[0])
    chunk = min(chunk, total)
    starts = jax.tree.map(lambda x: jnp.broadcast_to(x, (chunk, *x.shape)), start)

    @jax.jit
    def run_chunk(hbr, table, genes, wanted, ends):
        held = jnp.broadcast_to(wanted[:, None], (wanted.shape[0], STEPS_PER_SKILL))
        return summarise(execute_skill(robot, hbr, genes, starts, patterns=held, table=table, ends=ends))

    def padded(rows: np.ndarray) -> np.ndarray:  # to `chunk` rows, with copies of the last
        return np.concatenate([rows, np.repeat(rows[-1:], chunk - len(rows), axis=0)])

    outputs = []
    for begin in tqdm(range(0, total, chunk), disable=not progress, desc=desc, unit="chunk", leave=False):
        stop = min(begin + chunk, total)
        out = jax.device_get(waited(run_chunk, hbr, table, jnp.asarray(padded(genes[begin:stop])),
                                    jnp.asarray(padded(patterns[begin:stop]), jnp.int32),
                                    jnp.asarray(padded(ends[begin:stop]))))
        outputs.append([np.asarray(o)[: stop - begin] for o in out])
    return [np.concatenate(parts) for parts in zip(*outputs)]


def spread_skills(filled: np.ndarray, descriptors: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """Sorted cells of min(count, filled.sum()) skills spread over the map, drawn with `seed`: filled (C,)
    bool, descriptors (C, 2) normalised final x-y. Every (filled / count)-th skill along a Z-order
    curve from a random start: one per equal patch, each skill equally likely."""
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    slots = np.flatnonzero(np.asarray(filled))
    if count >= slots.size:
        return slots
    coords = np.minimum((np.clip(np.asarray(descriptors)[slots], 0.0, 1.0) * 1024).astype(np.int64), 1023)
    curve = np.zeros(slots.size, np.int64)
    for bit in range(10):  # interleave the 10 bits of x and y
        curve |= ((coords[:, 0] >> bit) & 1) << (2 * bit + 1) | ((coords[:, 1] >> bit) & 1) << (2 * bit)
    ordered = slots[np.argsort(curve, kind="stable")]
    step = slots.size / count
    start = np.random.default_rng(seed).uniform(0.0, step)
    return np.sort(ordered[np.floor(start + step * np.arange(count)).astype(np.int64)])


def modulate(robot: Robot, hbr: HBR, task: TopTask, start: SimState, *, skills: np.ndarray | None = None,
             patterns: np.ndarray | None = None, chunk: int = 4096, progress: bool = True,
             table: PatternTable | None = None) -> Modulation:
    """Re-execute top skills (default all) with each pattern (default all 64) from the standing state `start`."""
    slots, patterns = checked_pairs(hbr, skills, patterns)
    threshold = hbr.middle_task.contact_threshold

    def summarise(skill):
        fraction = skill.steps.contact_fraction.mean(axis=0)  # (B, 6) over the 3 s
        xy = skill.displacement[:, :2]
        cell = task.grid().cell_index(task.normalise(xy))
        shown = pattern_code((fraction > threshold).astype(jnp.float32))
        return xy, shown, skill.valid, skill.steps.pattern_found.all(axis=0), cell

    # skill-major pairs: pair k = (skill k // P, pattern k % P)
    xy, measured, valid, available, cell = execute_held(
        robot, hbr, start, np.repeat(np.asarray(hbr.top.genotypes)[slots], patterns.size, axis=0),
        np.tile(patterns, slots.size), np.repeat(stored_ends(hbr, task, slots), patterns.size, axis=0), table,
        summarise, chunk=chunk, progress=progress, desc="modulation")
    shape = (slots.size, patterns.size)
    return Modulation(slots=slots, patterns=patterns,
                      target_xy=np.asarray(task.denormalise(np.asarray(hbr.top.descriptors)[slots])),
                      final_xy=xy.reshape(*shape, 2), measured=measured.reshape(shape), valid=valid.reshape(shape),
                      available=available.reshape(shape), final_cell=cell.reshape(shape))
