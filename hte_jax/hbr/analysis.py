"""Summary statistics of a trained HBR (what the training summary and the acceptance checks read)."""

from __future__ import annotations

import numpy as np

from hte_jax.hbr.execution import HBR
from hte_jax.hbr.middle import NUM_PATTERNS


def pattern_histogram(hbr: HBR) -> np.ndarray:
    """(64,) number of middle elites per contact pattern (leg 0 the most significant bit)."""
    patterns = np.asarray(hbr.middle_patterns)
    return np.bincount(patterns[patterns >= 0], minlength=NUM_PATTERNS)


def hbr_statistics(hbr: HBR) -> dict:
    """Elite counts and fitness of each layer, distinct contact patterns, top-layer usage of the middle."""
    stats = {}
    for name in ("bottom", "middle", "top"):
        repertoire = getattr(hbr, name)
        filled = np.asarray(repertoire.filled)
        fitness = np.asarray(repertoire.fitnesses)[filled]
        stats[name] = {
            "elites": int(filled.sum()),
            "capacity": int(filled.size),
            "mean_fitness": float(fitness.mean()) if fitness.size else float("nan"),
            "min_fitness": float(fitness.min()) if fitness.size else float("nan"),
        }
    histogram = pattern_histogram(hbr)
    stats["middle"]["contact_patterns"] = int((histogram > 0).sum())
    stats["middle"]["pattern_histogram"] = histogram.tolist()
    top_filled = np.asarray(hbr.top.filled)
    used = np.asarray(hbr.top.extras["middle_indices"])[top_filled]
    stats["top"]["coverage"] = float(top_filled.mean())
    stats["top"]["distinct_middle_elites_used"] = int(np.unique(used).size)
    return stats
