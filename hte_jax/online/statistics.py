"""The paper's statistics of an adaptation protocol (section 6): per-replication medians, nearest
data-point percentiles, failure rates and pairwise Wilcoxon-Mann-Whitney tests with Bonferroni
correction.

An episode's score is the number of actions it needed, the cap (80) when it failed. For each
variant, the medians over repertoire seeds of each (damage, replicate) give 7 x 30 = 210 values;
their 25th, 50th and 75th percentiles are taken as data points, without interpolation.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter, defaultdict

import numpy as np
from scipy import stats as scipy_stats

QUARTILES = (25, 50, 75)
# The paper's Fig. 6: 25th / 50th / 75th percentiles of the replication medians (actions).
PAPER_QUARTILES = {
    "perfect-hte": (16, 19, 24),
    "hte": (19, 24, 32),
    "2d-rte": (22, 28, 40),
    "8d-rte": (26, 32, 39),
    "aprol": (34, 39, 48),
}
PAPER_FAILURE_REDUCTION = ("hte", "2d-rte", 57.0)  # HTE has 57 % fewer failures than 2D-RTE (Fig. 7)


def nearest_percentile(values, q: float) -> float:
    """The data point closest to the q-th percentile's position (q/100)(n - 1) in the sorted values;
    halfway ties go to the lower point. No interpolation (paper section 6)."""
    data = np.sort(np.asarray(values, float).ravel())
    if data.size == 0:
        raise ValueError("nearest_percentile of no values")
    if not 0 <= q <= 100:
        raise ValueError(f"percentile must be in [0, 100], got {q}")
    position = q / 100.0 * (data.size - 1)
    index = math.ceil(position - 0.5)  # round half down
    return float(data[index])


def replication_medians(records: list[dict]) -> dict[str, np.ndarray]:
    """variant -> medians over repertoire seeds of the actions of each (damage, replicate), sorted by
    (damage, replicate). Records: dicts with variant, damage, replicate, actions and optionally seed."""
    groups: dict[str, dict[tuple, list[int]]] = defaultdict(lambda: defaultdict(list))
    for r in records:
        groups[r["variant"]][(r["damage"], r["replicate"])].append(r["actions"])
    return {variant: np.array([float(np.median(v)) for _, v in sorted(cells.items())]) for variant, cells in groups.items()}


def bonferroni(p_values, tests: int | None = None) -> np.ndarray:
    """p-values multiplied by the number of tests (default: how many are given), capped at 1."""
    p = np.asarray(p_values, float)
    return np.minimum(p * (p.size if tests is None else tests), 1.0)


def pairwise_tests(samples: dict[str, np.ndarray]) -> list[dict]:
    """Two-sided Wilcoxon-Mann-Whitney test of every pair of variants, Bonferroni-corrected over the pairs."""
    pairs = list(itertools.combinations(samples, 2))
    raw = []
    for a, b in pairs:
        x, y = np.asarray(samples[a], float), np.asarray(samples[b], float)
        test = scipy_stats.mannwhitneyu(x, y, alternative="two-sided")
        # Identical constant samples give p = nan on some scipy versions: no evidence of a difference.
        raw.append((float(test.statistic), float(test.pvalue) if np.isfinite(test.pvalue) else 1.0))
    corrected = bonferroni([p for _, p in raw]) if raw else np.array([])
    return [{"a": a, "b": b, "u": u, "p": p, "p_bonferroni": float(c), "median_a": float(np.median(samples[a])),
             "median_b": float(np.median(samples[b]))} for (a, b), (u, p), c in zip(pairs, raw, corrected)]


def protocol_statistics(records: list[dict]) -> dict:
    """Per variant: the quartiles of its replication medians, how many seeds the fewest of those
    medians cover, the failure rate over all episodes, and the pairwise tests between variants."""
    medians = replication_medians(records)
    episodes_per_cell = Counter((r["variant"], r["damage"], r["replicate"]) for r in records)
    variants = {}
    for variant, values in medians.items():
        rows = [r for r in records if r["variant"] == variant]
        failures = sum(not r["reached"] for r in rows)
        variants[variant] = {
            "replications": int(values.size),
            "seeds_per_median": min(n for (v, _, _), n in episodes_per_cell.items() if v == variant),
            "episodes": len(rows),
            **{f"p{q}": nearest_percentile(values, q) for q in QUARTILES},
            "failures": failures,
            "failure_percent": 100.0 * failures / len(rows),
            "flipped": sum(r.get("broken", False) for r in rows),
        }
    return {"variants": variants, "tests": pairwise_tests(medians), "medians": {k: v.tolist() for k, v in medians.items()}}


def failure_reduction(statistics: dict, variant: str, baseline: str) -> float | None:
    """How many fewer failures (in %) `variant` has than `baseline` (the paper: HTE 57 % fewer than 2D-RTE)."""
    v = statistics["variants"]
    base = v[baseline]["failure_percent"]
    return None if base == 0 else 100.0 * (1.0 - v[variant]["failure_percent"] / base)


def failure_reductions(statistics: dict, baseline: str) -> dict[str, float | None]:
    """`failure_reduction` of every other variant of `statistics` against `baseline`, in their order."""
    return {name: failure_reduction(statistics, name, baseline) for name in statistics["variants"] if name != baseline}
