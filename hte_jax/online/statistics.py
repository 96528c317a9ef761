"""Statistics of an adaptation protocol at three levels, each named for what it treats as the sample.

* The paper's method (section 6), the replications as the sample: an episode's score is the number
  of actions it needed, the cap (80) when it failed; for each variant the medians over repertoire
  seeds of each (damage, replicate) give 7 x 30 = 210 values, whose 25th, 50th and 75th percentiles
  are taken as data points, without interpolation; pairwise two-sided Wilcoxon-Mann-Whitney tests on
  these medians, Bonferroni-corrected over the pairs. Failure rates: failed episodes / all.
* Episode level, the episodes as the sample (treated as independent, though the episodes of one seed
  share its repertoires): success rates with 95 % Wilson intervals and the actions of the successful
  episodes, per variant pooled, per damage and per seed; pairwise Fisher's exact tests of success and
  Wilcoxon-Mann-Whitney tests of the successful episodes' actions, pooled over damages.
* Seed level, the repertoire seed (a separately trained set of repertoires, the unit that was
  replicated) as the sample: per seed, each variant's success rate and median successful actions,
  compared over the seeds two variants share with an exact Wilcoxon signed-rank test, reported with
  the smallest p-value that many seeds can give.
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
Z95 = float(scipy_stats.norm.ppf(0.975))  # the normal quantile of a two-sided 95 % interval
RECORD_KEYS = ("variant", "damage", "replicate", "actions", "reached")  # what every episode record must carry
PAPER_METHOD = ("the paper's method (section 6), the replications as the sample: variants' p25 / p50 / p75 are the "
                "nearest-data-point quartiles of the replication medians (per damage and replicate, the median over "
                "seeds of the actions, a failure counting as the cap); tests: two-sided Wilcoxon-Mann-Whitney on "
                "those medians, Bonferroni over the pairs")
EPISODE_SAMPLE = ("episode level: treats episodes as independent (the episodes of one seed share its repertoires), "
                  "pooled over damages")
SEED_SAMPLE = ("seed level: the repertoire seed is the unit, each variant's value per seed compared over the seeds "
               "both variants have, paired by seed index; exact two-sided Wilcoxon signed-rank test; zero differences "
               "are dropped (Wilcoxon's rule) and tied |differences| share their mean rank (the exact distribution "
               "is that of these ranks); min_p is the smallest p the ranked seeds can give")


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
    """Two-sided Wilcoxon-Mann-Whitney test of every pair of variants, Bonferroni-corrected over the pairs.
    A pair with an empty sample has no test: u, p and p_bonferroni are None (still counted among the pairs)."""
    pairs = list(itertools.combinations(samples, 2))
    raw = []
    for a, b in pairs:
        x, y = np.asarray(samples[a], float), np.asarray(samples[b], float)
        if x.size == 0 or y.size == 0:
            raw.append((None, None))
            continue
        test = scipy_stats.mannwhitneyu(x, y, alternative="two-sided")
        # Identical constant samples give p = nan on some scipy versions: no evidence of a difference.
        raw.append((float(test.statistic), float(test.pvalue) if np.isfinite(test.pvalue) else 1.0))
    corrected = bonferroni_or_none([p for _, p in raw])
    return [{"a": a, "b": b, "u": u, "p": p, "p_bonferroni": c, "n_a": len(samples[a]), "n_b": len(samples[b]),
             "median_a": _median_or_none(samples[a]), "median_b": _median_or_none(samples[b])}
            for (a, b), (u, p), c in zip(pairs, raw, corrected)]


def bonferroni_or_none(p_values: list[float | None]) -> list[float | None]:
    """`bonferroni` over all the given tests (None counted among them and kept as None)."""
    return [None if p is None else float(bonferroni([p], tests=len(p_values))[0]) for p in p_values]


def _median_or_none(values) -> float | None:
    return float(np.median(values)) if len(values) else None


def check_records(records: list[dict]) -> None:
    """ValueError unless `records` is a non-empty list of episode records carrying RECORD_KEYS."""
    if not records:
        raise ValueError("protocol statistics need episode records; got none")
    for i, record in enumerate(records):
        missing = [key for key in RECORD_KEYS if key not in record]
        if missing:
            raise ValueError(f"episode record {i} lacks {', '.join(missing)} "
                             f"(every record needs {', '.join(RECORD_KEYS)})")


def wilson_interval(successes: int, trials: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion p = successes / trials (default 95 %): centre -+ half with
    centre = (p + z^2 / 2n) / (1 + z^2 / n) and half = z / (1 + z^2 / n) sqrt(p (1 - p) / n + z^2 / 4n^2)."""
    if trials <= 0:
        raise ValueError(f"a Wilson interval needs at least one trial, got {trials}")
    if not 0 <= successes <= trials:
        raise ValueError(f"successes must be in [0, {trials}], got {successes}")
    p, z2 = successes / trials, z * z
    scale = 1.0 + z2 / trials
    centre = (p + z2 / (2 * trials)) / scale
    half = z / scale * math.sqrt(p * (1.0 - p) / trials + z2 / (4 * trials * trials))
    return max(0.0, centre - half), min(1.0, centre + half)


def action_summary(actions) -> dict:
    """count, median (numpy's: the mean of the two middle values of an even count) and p25 / p75 (the nearest
    data point, `nearest_percentile`) of the actions of some episodes; None for each statistic of none."""
    values = np.asarray(actions, float).ravel()
    if values.size == 0:
        return {"count": 0, "median": None, "p25": None, "p75": None}
    return {"count": int(values.size), "median": float(np.median(values)),
            "p25": nearest_percentile(values, 25), "p75": nearest_percentile(values, 75)}


def success_summary(records: list[dict]) -> dict:
    """Episodes, successes (the goal reached), the success rate with its 95 % Wilson interval, and the
    `action_summary` of the successful episodes."""
    check_records(records)
    successful = [r["actions"] for r in records if r["reached"]]
    return {"episodes": len(records), "successes": len(successful), "rate": len(successful) / len(records),
            "ci95": list(wilson_interval(len(successful), len(records))), "actions": action_summary(successful)}


def _seed(record: dict) -> int:
    return int(record.get("seed", 0))  # runs on the shipped repertoires have one seed, 0


def success_rates(records: list[dict]) -> dict:
    """variant -> `success_summary` of its episodes "pooled" over damages, per damage ("damages", in record
    order) and per repertoire seed ("seeds", keyed by the seed index as a string, in increasing order)."""
    check_records(records)
    out = {}
    for variant in dict.fromkeys(r["variant"] for r in records):
        rows = [r for r in records if r["variant"] == variant]
        damages = dict.fromkeys(r["damage"] for r in rows)
        seeds = sorted({_seed(r) for r in rows})
        out[variant] = {"pooled": success_summary(rows),
                        "damages": {d: success_summary([r for r in rows if r["damage"] == d]) for d in damages},
                        "seeds": {str(s): success_summary([r for r in rows if _seed(r) == s]) for s in seeds}}
    return out


def episode_success_tests(records: list[dict]) -> dict:
    """Per pair of variants, two-sided Fisher's exact test on the 2 x 2 table of successes and failures of all
    their episodes (pooled over damages), Bonferroni-corrected over the pairs."""
    check_records(records)
    counts = {v: [0, 0] for v in dict.fromkeys(r["variant"] for r in records)}  # successes, episodes
    for r in records:
        counts[r["variant"]][0] += bool(r["reached"])
        counts[r["variant"]][1] += 1
    return fisher_tests({v: (successes, episodes) for v, (successes, episodes) in counts.items()})


def fisher_tests(counts: dict[str, tuple[int, int]]) -> dict:
    """Per pair of variants (variant -> (successes, episodes)), two-sided Fisher's exact test on their 2 x 2
    table of successes and failures, Bonferroni-corrected over the pairs."""
    pairs = list(itertools.combinations(counts, 2))
    raw = []
    for a, b in pairs:
        (sa, na), (sb, nb) = counts[a], counts[b]
        raw.append(float(scipy_stats.fisher_exact([[sa, na - sa], [sb, nb - sb]], alternative="two-sided").pvalue))
    corrected = bonferroni_or_none(raw)
    tests = [{"a": a, "b": b, "successes_a": counts[a][0], "episodes_a": counts[a][1], "successes_b": counts[b][0],
              "episodes_b": counts[b][1], "rate_a": counts[a][0] / counts[a][1], "rate_b": counts[b][0] / counts[b][1],
              "p": p, "p_bonferroni": c} for (a, b), p, c in zip(pairs, raw, corrected)]
    return {"test": "Fisher's exact test, two-sided, on the successes and failures of all episodes",
            "bonferroni_pairs": len(pairs), "pairs": tests}


def episode_action_tests(records: list[dict]) -> dict:
    """Per pair of variants, `pairwise_tests` (two-sided Wilcoxon-Mann-Whitney, Bonferroni over the pairs) on
    the actions of their successful episodes, pooled over damages; no test where a variant has no success."""
    check_records(records)
    samples = {v: [] for v in dict.fromkeys(r["variant"] for r in records)}
    for r in records:
        if r["reached"]:
            samples[r["variant"]].append(r["actions"])
    tests = pairwise_tests({v: np.asarray(x, float) for v, x in samples.items()})
    return {"test": "Wilcoxon-Mann-Whitney, two-sided, on the actions of the successful episodes",
            "bonferroni_pairs": len(tests), "pairs": tests}


def signed_rank_test(differences) -> tuple[float, int, float]:
    """Exact two-sided Wilcoxon signed-rank test of paired differences. Zero differences are dropped (Wilcoxon's
    rule); the m left are ranked by |difference|, ties sharing their mean rank. The null distribution of W+ (the
    sum of the positive differences' ranks) is counted over all 2^m sign assignments of these ranks. Returns
    (W+, m, p) with p = min(1, 2 min(P(W <= W+), P(W >= W+))); m = 0 gives (0, 0, 1)."""
    d = np.asarray(differences, float).ravel()
    if not np.isfinite(d).all():
        raise ValueError("signed-rank differences must be finite")
    d = d[d != 0]
    if d.size == 0:
        return 0.0, 0, 1.0
    doubled = np.rint(2 * scipy_stats.rankdata(np.abs(d))).astype(int)  # mean ranks are multiples of 1/2
    ways = np.zeros(int(doubled.sum()) + 1)  # ways[w]: sign assignments whose doubled W+ is w
    ways[0] = 1.0
    for rank in doubled:
        ways[rank:] = ways[rank:] + ways[:-rank].copy()
    observed = int(doubled[d > 0].sum())
    total = 2.0 ** d.size
    lower, upper = ways[: observed + 1].sum() / total, ways[observed:].sum() / total
    return observed / 2, int(d.size), float(min(1.0, 2 * min(lower, upper)))


def min_signed_rank_p(seeds: int) -> float:
    """The smallest two-sided p an exact signed-rank test of `seeds` non-zero differences can give: all of one
    sign, the one assignment of 2^seeds at the extreme, doubled (4 seeds: 0.125); 1 without any."""
    if seeds < 0:
        raise ValueError(f"a number of seeds must be >= 0, got {seeds}")
    return min(1.0, 2.0 ** (1 - seeds))


SEED_QUANTITIES = ("success_rate", "median_actions")


def seed_cells(records: list[dict]) -> dict[str, dict[int, dict]]:
    """variant -> seed -> `success_summary` of that seed's episodes (all damages), seeds in increasing order."""
    check_records(records)
    rows: dict[str, dict[int, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for r in records:
        rows[r["variant"]][_seed(r)].append(r)
    return {v: {s: success_summary(cell) for s, cell in sorted(seeds.items())} for v, seeds in rows.items()}


def cell_values(cells: dict[str, dict[int, dict]], quantity: str) -> dict[str, dict[int, float | None]]:
    """variant -> seed -> the "success_rate" (successes / episodes) or the "median_actions" (of the successful
    episodes, None without one) of per-seed `success_summary` cells."""
    if quantity not in SEED_QUANTITIES:
        raise ValueError(f"seed quantity must be one of {', '.join(SEED_QUANTITIES)}, got {quantity!r}")
    return {v: {s: (c["successes"] / c["episodes"] if quantity == "success_rate" else c["actions"]["median"])
                for s, c in seeds.items()} for v, seeds in cells.items()}


def seed_values(records: list[dict], quantity: str) -> dict[str, dict[int, float | None]]:
    """variant -> seed -> its "success_rate" (successes / episodes of that seed, all damages) or its
    "median_actions" (np.median of the actions of that seed's successful episodes, None without one)."""
    return cell_values(seed_cells(records), quantity)


def seed_level_tests(records: list[dict], quantity: str) -> dict:
    """`signed_rank_tests` of the records' `seed_values`."""
    return signed_rank_tests(seed_values(records, quantity), quantity)


def signed_rank_tests(values: dict[str, dict[int, float | None]], quantity: str) -> dict:
    """Per pair of variants, `signed_rank_test` of the differences a - b of their per-seed values over the seeds
    both have (for median_actions, both with a successful episode: the seeds left out are counted), with the
    smallest p those seeds can give; Bonferroni over the pairs (None where no seed is left to compare)."""
    pairs = list(itertools.combinations(values, 2))
    tests = []
    for a, b in pairs:
        shared = sorted(set(values[a]) & set(values[b]))
        kept = [s for s in shared if values[a][s] is not None and values[b][s] is not None]
        w_plus, ranked, p = signed_rank_test([values[a][s] - values[b][s] for s in kept])
        tests.append({"a": a, "b": b, "seeds": len(kept), "seed_ids": kept, "values_a": [values[a][s] for s in kept],
                      "values_b": [values[b][s] for s in kept], "seeds_without_success": len(shared) - len(kept),
                      "zero_differences": len(kept) - ranked, "w_plus": w_plus if kept else None,
                      "p": p if kept else None, "min_p": min_signed_rank_p(ranked)})
    corrected = bonferroni_or_none([t["p"] for t in tests])
    for t, c in zip(tests, corrected):
        t["p_bonferroni"] = c
        t["min_p_bonferroni"] = float(bonferroni([t["min_p"]], tests=len(tests))[0])
    what = "success rate" if quantity == "success_rate" else "median actions of the successful episodes"
    return {"test": f"exact Wilcoxon signed-rank, two-sided, on each seed's {what}", "bonferroni_pairs": len(pairs),
            "pairs": tests}


def cell_statistics(cells: dict[str, dict[int, dict]]) -> dict:
    """The statistics that per-seed `success_summary` cells (variant -> seed -> cell) determine without the
    episodes: per variant the successes pooled over the seeds with a 95 % Wilson interval and the cells
    ("success"); Fisher's tests of those counts ("episode_success", episodes as the sample); the seed level
    (`signed_rank_tests` of both SEED_QUANTITIES). Pooled actions and the paper's method need the episodes."""
    success = {}
    for v, seeds in cells.items():
        successes, episodes = sum(c["successes"] for c in seeds.values()), sum(c["episodes"] for c in seeds.values())
        success[v] = {"pooled": {"episodes": episodes, "successes": successes, "rate": successes / episodes,
                                 "ci95": list(wilson_interval(successes, episodes))},
                      "seeds": {str(s): c for s, c in sorted(seeds.items())}}
    counts = {v: (c["pooled"]["successes"], c["pooled"]["episodes"]) for v, c in success.items()}
    return {"success": success, "episode_success": {"sample": EPISODE_SAMPLE, **fisher_tests(counts)},
            "seed_tests": {"sample": SEED_SAMPLE, **{q: signed_rank_tests(cell_values(cells, q), q)
                                                     for q in SEED_QUANTITIES}}}


def protocol_statistics(records: list[dict]) -> dict:
    """The three levels of statistics of a protocol's episode records.

    The paper's method (PAPER_METHOD): "variants" (per variant the quartiles of its replication medians, how
    many seeds the fewest of those medians cover, the failure rate over all episodes), "tests" (the pairwise
    tests between variants, each with method "paper") and "medians". Episode level: "success" (`success_rates`)
    and "episode_tests" (`episode_success_tests`, `episode_action_tests`). Seed level: "seed_tests"
    (`seed_level_tests` of the success rate and of the median actions)."""
    check_records(records)
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
    return {"paper_method": PAPER_METHOD, "variants": variants,
            "tests": [{**t, "method": "paper"} for t in pairwise_tests(medians)],
            "medians": {k: v.tolist() for k, v in medians.items()},
            "success": success_rates(records),
            "episode_tests": {"sample": EPISODE_SAMPLE, "success": episode_success_tests(records),
                              "actions": episode_action_tests(records)},
            "seed_tests": {"sample": SEED_SAMPLE, **{q: seed_level_tests(records, q) for q in SEED_QUANTITIES}}}


def failure_reduction(statistics: dict, variant: str, baseline: str) -> float | None:
    """How many fewer failures (in %) `variant` has than `baseline` (the paper: HTE 57 % fewer than 2D-RTE)."""
    v = statistics["variants"]
    base = v[baseline]["failure_percent"]
    return None if base == 0 else 100.0 * (1.0 - v[variant]["failure_percent"] / base)


def failure_reductions(statistics: dict, baseline: str) -> dict[str, float | None]:
    """`failure_reduction` of every other variant of `statistics` against `baseline`, in their order."""
    return {name: failure_reduction(statistics, name, baseline) for name in statistics["variants"] if name != baseline}


def p_text(value: float | None) -> str:
    """A p-value as printed: two significant digits, "-" where there is none."""
    return "-" if value is None else f"{value:.2g}"


def rank_test_text(test: dict) -> str:
    """A signed-rank pair test of `seed_level_tests` as printed: Bonferroni p (units compared, min: the smallest
    Bonferroni p they can give)."""
    return f"{p_text(test['p_bonferroni'])} ({test['seeds']}, min {p_text(test['min_p_bonferroni'])})"


def rates_text(cells: dict) -> str:
    """Per-unit success rates {unit: {"rate": ...}} as printed, "a / b / ..." in percent, in increasing unit
    order (also where the units' keys were sorted as strings in a JSON file)."""
    return " / ".join(f"{100 * cells[k]['rate']:.0f}" for k in sorted(cells, key=int))


def success_lines(statistics: dict) -> list[str]:
    """One line per variant of `protocol_statistics`: the success rate with its 95 % Wilson interval, the
    successful episodes' median actions (p25-p75, nearest data point) and each seed's success rate, in
    increasing seed order (also where the seeds' keys were sorted as strings in a JSON file)."""
    lines, width = [], max(12, *(len(name) for name in statistics["success"]))
    for name, cell in statistics["success"].items():
        pooled, actions = cell["pooled"], cell["pooled"]["actions"]
        low, high = pooled["ci95"]
        spread = ("-" if actions["count"] == 0
                  else f"{actions['median']:.0f} ({actions['p25']:.0f}-{actions['p75']:.0f})")
        lines.append(f"{name:<{width}} success {100 * pooled['rate']:5.1f} % [{100 * low:.1f}, {100 * high:.1f}] "
                     f"{pooled['successes']}/{pooled['episodes']}, actions {spread}; per seed {rates_text(cell['seeds'])} %")
    return lines


def pair_lines(statistics: dict) -> list[str]:
    """One line per pair of variants of `protocol_statistics`: the paper's test (U, Bonferroni p), the
    Bonferroni p of the episode-level tests (success, actions) and of the seed-level tests, with the seeds
    each compared and the smallest Bonferroni p they can give."""
    episode, seed = statistics["episode_tests"], statistics["seed_tests"]

    def by_pair(family):
        return {(t["a"], t["b"]): t for t in family["pairs"]}

    e_success, e_actions = by_pair(episode["success"]), by_pair(episode["actions"])
    s_success, s_actions = by_pair(seed["success_rate"]), by_pair(seed["median_actions"])
    lines = []
    for paper in statistics["tests"]:
        pair = (paper["a"], paper["b"])
        lines.append(f"  {paper['a']} vs {paper['b']}: paper U = {paper['u']:.0f}, p {p_text(paper['p_bonferroni'])}"
                     f" | episodes: success {p_text(e_success[pair]['p_bonferroni'])}, actions "
                     f"{p_text(e_actions[pair]['p_bonferroni'])} | seeds: success {rank_test_text(s_success[pair])}, "
                     f"actions {rank_test_text(s_actions[pair])}")
    return lines


PAPER_METHOD_HEADER = "the paper's method: quartiles of the replication medians (actions, a failure counting as the cap)"
PAIR_LEGEND = ("pairs, Bonferroni p: paper = Mann-Whitney on replication medians; episodes = Fisher (success) and\n"
               "  Mann-Whitney (successful actions), episodes as independent; seeds = exact signed-rank per seed\n"
               "  (seeds compared, min: the smallest p they can give)")


def level_lines(statistics: dict) -> list[str]:
    """What a command prints below its paper's-method table: `success_lines`, then `PAIR_LEGEND` and `pair_lines`."""
    return [*success_lines(statistics), PAIR_LEGEND, *pair_lines(statistics)]
