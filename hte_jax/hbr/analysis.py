"""Summary statistics of a trained HBR (what the training summary and the acceptance checks read)."""

from __future__ import annotations

import numpy as np

from hte_jax.hbr.hierarchy import HBR
from hte_jax.hbr.middle import NUM_PATTERNS
from hte_jax.hbr.top import TopTask

DISTANCE_BANDS = (0.0, 0.3, 0.6, 0.9, 1.2, float("inf"))


def pattern_histogram(hbr: HBR) -> np.ndarray:
    """(64,) number of middle elites per contact pattern (leg 0 the most significant bit)."""
    patterns = np.asarray(hbr.middle_patterns)
    return np.bincount(patterns[patterns >= 0], minlength=NUM_PATTERNS)


def speed_by_turn(hbr: HBR, bins: int = 10) -> list[dict]:
    """The middle layer's speed-versus-turn frontier: per |yaw| bin of width max_turn / bins, the number
    of motions and the 95th percentile and maximum of their speed (m/s; None if empty)."""
    steps = np.asarray(hbr.middle_task.denormalise(hbr.middle.descriptors[:, :3]))[np.asarray(hbr.middle.filled)]
    speed, turn = np.hypot(steps[:, 0], steps[:, 1]), np.abs(steps[:, 2])
    edges = np.linspace(0.0, hbr.middle_task.max_turn, bins + 1)
    rows = []
    for low, high in zip(edges[:-1], edges[1:]):
        inside = (turn >= low) & ((turn < high) | (high == edges[-1]))
        chosen = speed[inside]
        rows.append({"turn": [round(float(low), 6), round(float(high), 6)], "motions": int(inside.sum()),
                     "speed_p95": float(np.percentile(chosen, 95)) if chosen.size else None,
                     "speed_max": float(chosen.max()) if chosen.size else None})
    return rows


def fitness_by_distance(hbr: HBR, top_task: TopTask = TopTask(), edges=DISTANCE_BANDS) -> list[dict]:
    """Top-layer cells and mean fitness (None if empty) per band of distance (m) from the start: quality apart
    from coverage (reaching farther adds frontier cells whose arcs are hard)."""
    filled = np.asarray(hbr.top.filled)
    distance = np.hypot(*np.asarray(top_task.denormalise(hbr.top.descriptors))[filled].T)
    fitness = np.asarray(hbr.top.fitnesses)[filled]
    rows = []
    for low, high in zip(edges[:-1], edges[1:]):
        inside = (distance >= low) & (distance < high)
        rows.append({"distance": [float(low), float(high) if np.isfinite(high) else None], "cells": int(inside.sum()),
                     "mean_fitness": float(fitness[inside].mean()) if inside.any() else None})
    return rows


def hbr_statistics(hbr: HBR, top_task: TopTask = TopTask()) -> dict:
    """Elite counts and fitness of each layer, distinct contact patterns, top-layer usage of the middle."""
    stats = {}
    for name in ("bottom", "middle", "top"):
        repertoire = getattr(hbr, name)
        filled = np.asarray(repertoire.filled)
        fitness = np.asarray(repertoire.fitnesses)[filled]
        stats[name] = {"elites": int(filled.sum()), "capacity": int(filled.size),
                       "mean_fitness": float(fitness.mean()) if fitness.size else float("nan"),
                       "min_fitness": float(fitness.min()) if fitness.size else float("nan")}
    histogram = pattern_histogram(hbr)
    stats["middle"].update(contact_patterns=int((histogram > 0).sum()), pattern_histogram=histogram.tolist(),
                           speed_by_turn=speed_by_turn(hbr))
    top_filled = np.asarray(hbr.top.filled)
    used = np.asarray(hbr.top.extras["middle_indices"])[top_filled]
    stats["top"].update(coverage=float(top_filled.mean()), distinct_middle_elites_used=int(np.unique(used).size),
                        fitness_by_distance=fitness_by_distance(hbr, top_task))
    return stats
