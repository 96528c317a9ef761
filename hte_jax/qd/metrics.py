"""Repertoire metrics and CSV log; QD score = sum of (fitness - offset), offset a fitness lower bound: it only grows."""

from __future__ import annotations

import csv
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hte_jax.qd.repertoire import Repertoire

FIELDS = ("block", "generation", "evaluations", "filled", "coverage", "qd_score", "mean_fitness", "max_fitness",
          "accepted", "wall_time_s")


@struct.dataclass
class RepertoireMetrics:
    """0-d arrays: filled (elites), coverage (filled / capacity), qd_score (sum of fitness - offset), and
    mean_fitness, max_fitness over elites (NaN when empty)."""

    filled: jax.Array
    coverage: jax.Array
    qd_score: jax.Array
    mean_fitness: jax.Array
    max_fitness: jax.Array


def repertoire_metrics(repertoire: Repertoire, offset: float) -> RepertoireMetrics:
    filled = repertoire.filled
    count = filled.sum(dtype=jnp.int32)
    total = jnp.where(filled, repertoire.fitnesses, 0.0).sum()
    best = jnp.where(filled, repertoire.fitnesses, -jnp.inf).max()
    return RepertoireMetrics(filled=count, coverage=count / repertoire.capacity, qd_score=total - offset * count,
                             mean_fitness=jnp.where(count > 0, total / jnp.maximum(count, 1), jnp.nan),
                             max_fitness=jnp.where(count > 0, best, jnp.nan))


class MetricsLog:
    """Appends one CSV row per block; a resumed run keeps appending to the same file (its wall_time_s column
    counting on from the last kept row: the seconds of every session together)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)

    def truncate_after(self, block: int) -> None:
        """Drop rows of blocks > `block` (written after the checkpoint a run resumes from)."""
        if self.path.exists():
            self._write([r for r in self.read() if int(r["block"]) <= block], mode="w")

    def last_wall_time(self) -> float:
        """The wall_time_s of the last row (0.0 without one)."""
        rows = self.read() if self.path.exists() else []
        return float(rows[-1]["wall_time_s"]) if rows else 0.0

    def append(self, row: dict) -> None:
        self._write([row], mode="a")

    def read(self) -> list[dict]:
        with self.path.open(newline="") as handle:
            return list(csv.DictReader(handle))

    def _write(self, rows, mode: str) -> None:
        new_file = mode == "w" or not self.path.exists() or self.path.stat().st_size == 0
        with self.path.open(mode, newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=FIELDS)
            if new_file:
                writer.writeheader()
            # JAX and NumPy scalars become Python ints and floats
            writer.writerows({k: row[k].item() if hasattr(row[k], "item") else row[k] for k in FIELDS} for row in rows)


def projected_statistics(descriptors, fitnesses, filled, bins: int) -> dict:
    """The paper's Table 2 columns of a repertoire (host): descriptors (C, D), the first two x, y in [0, 1];
    fitnesses (C,); filled (C,). "size": elites; "effective_size": occupied cells of a bins x bins x-y grid;
    "mean_fitness": mean of those cells' best (what a planner sees); "mean_fitness_all": mean of all elites."""
    filled = np.asarray(filled, bool)
    xy = np.asarray(descriptors, np.float64)[filled, :2]
    fitness = np.asarray(fitnesses, np.float64)[filled]
    cells = np.clip(np.floor(xy * bins).astype(np.int64), 0, bins - 1)
    flat = cells[:, 0] * bins + cells[:, 1]
    best = np.full(bins * bins, -np.inf)
    np.maximum.at(best, flat, fitness)
    best = best[np.isfinite(best)]
    return {"size": int(filled.sum()), "effective_size": int(best.size),
            "mean_fitness": float(best.mean()) if best.size else float("nan"),
            "mean_fitness_all": float(fitness.mean()) if fitness.size else float("nan")}
