"""The paper's statistics on hand-made data: nearest data-point percentiles, replication medians,
failure rates, Bonferroni-corrected Wilcoxon-Mann-Whitney tests."""

import matplotlib.image
import numpy as np
import pytest
from scipy import stats

from hte_jax.online.maze import PAPER_MAZE
from hte_jax.online.plots import plot_failures, plot_prediction_error, plot_protocol_box, plot_variant_mazes

from hte_jax.online.statistics import (
    bonferroni,
    failure_reduction,
    failure_reductions,
    nearest_percentile,
    pairwise_tests,
    protocol_statistics,
    replication_medians,
)


def test_nearest_percentile_takes_a_data_point():
    values = [7, 1, 3, 9, 5]  # sorted 1 3 5 7 9, positions 0..4
    assert nearest_percentile(values, 25) == 3  # position 1.0
    assert nearest_percentile(values, 50) == 5
    assert nearest_percentile(values, 75) == 7
    assert nearest_percentile(values, 0) == 1 and nearest_percentile(values, 100) == 9
    assert nearest_percentile(range(1, 11), 25) == 3  # position 2.25 -> the 3rd value
    assert nearest_percentile(range(1, 11), 75) == 8  # position 6.75 -> the 8th value
    assert nearest_percentile([10, 20, 30, 40], 50) == 20  # position 1.5: halfway goes to the lower point
    assert nearest_percentile([4], 75) == 4
    with pytest.raises(ValueError, match="percentile"):
        nearest_percentile([1, 2], 101)
    with pytest.raises(ValueError, match="no values"):
        nearest_percentile([], 50)


def test_bonferroni_multiplies_by_the_number_of_tests_and_caps_at_one():
    np.testing.assert_allclose(bonferroni([0.01, 0.2, 0.001]), [0.03, 0.6, 0.003])
    np.testing.assert_allclose(bonferroni([0.5, 0.4]), [1.0, 0.8])
    np.testing.assert_allclose(bonferroni([0.01], tests=15), [0.15])


def _records():
    """Two variants, 2 damages x 3 replicates x 2 repertoire seeds; 'a' needs fewer actions than 'b'."""
    rows = []
    for variant, base in (("a", 10), ("b", 40)):
        for damage in ("leg0", "leg1"):
            for replicate in range(3):
                for seed, offset in ((0, 0), (1, 4)):
                    actions = base + replicate + offset
                    failed = variant == "b" and replicate == 2
                    rows.append({"variant": variant, "damage": damage, "replicate": replicate, "seed": seed,
                                 "actions": 80 if failed else actions, "reached": not failed, "broken": False})
    return rows


def test_protocol_statistics_on_hand_made_records():
    records = _records()
    medians = replication_medians(records)
    # a: per (damage, replicate) the median of seeds (10 + r, 14 + r) = 12 + r
    np.testing.assert_allclose(medians["a"], [12, 13, 14, 12, 13, 14])
    np.testing.assert_allclose(medians["b"], [42, 43, 80, 42, 43, 80])
    result = protocol_statistics(records)
    a, b = result["variants"]["a"], result["variants"]["b"]
    assert (a["p25"], a["p50"], a["p75"]) == (12, 13, 14)  # sorted 12 12 13 13 14 14: positions 1.25, 2.5, 3.75
    assert (b["p25"], b["p50"], b["p75"]) == (42, 43, 80)
    assert a["failure_percent"] == 0 and b["failures"] == 4 and b["failure_percent"] == pytest.approx(100 * 4 / 12)
    assert b["replications"] == 6 and b["episodes"] == 12 and a["seeds_per_median"] == b["seeds_per_median"] == 2
    dropped = protocol_statistics(records[1:])  # one (damage, replicate) of 'a' keeps one seed
    assert dropped["variants"]["a"]["seeds_per_median"] == 1 and dropped["variants"]["b"]["seeds_per_median"] == 2
    (test,) = result["tests"]
    expected = stats.mannwhitneyu(medians["a"], medians["b"], alternative="two-sided")
    assert test["a"] == "a" and test["b"] == "b"
    assert test["p"] == pytest.approx(expected.pvalue) and test["p_bonferroni"] == pytest.approx(expected.pvalue)
    assert test["u"] == 0  # every 'a' median is below every 'b' median


def test_protocol_figures_of_hand_made_records(tmp_path):
    """The protocol's figures (actions per variant with the paper's quartiles, failures, GP prediction error,
    sample tracks in the maze) are written from statistics and curves alone."""
    statistics = protocol_statistics(_records())
    plot_protocol_box(tmp_path / "box.png", statistics, 80, paper={"a": (11, 12, 14)})
    plot_failures(tmp_path / "failures.png", statistics)
    errors = np.full((3, 10), np.nan)
    errors[:, :4] = np.linspace(0.3, 0.05, 4)
    plot_prediction_error(tmp_path / "error.png", {"a": errors, "b": np.full((2, 10), np.nan)})  # b: no action
    track = np.stack([np.linspace(0, 2, 9), np.linspace(0, 1, 9), np.zeros(9)], axis=1)
    plot_variant_mazes(tmp_path / "tracks.png", PAPER_MAZE, {"a": [("leg0", track)], "b": [("leg1", track[:4])]})
    for name in ("box", "failures", "error", "tracks"):
        image = matplotlib.image.imread(tmp_path / f"{name}.png")
        assert image.ndim == 3 and image.shape[0] > 100 and image.std() > 0, name


def test_pairwise_tests_correct_over_all_pairs():
    rng = np.random.default_rng(1)
    samples = {name: rng.normal(loc, 1.0, 30) for name, loc in (("x", 0.0), ("y", 0.1), ("z", 3.0))}
    tests = pairwise_tests(samples)
    assert [(t["a"], t["b"]) for t in tests] == [("x", "y"), ("x", "z"), ("y", "z")]
    for t in tests:
        raw = stats.mannwhitneyu(samples[t["a"]], samples[t["b"]], alternative="two-sided").pvalue
        assert t["p_bonferroni"] == pytest.approx(min(1.0, 3 * raw))
    assert tests[1]["p_bonferroni"] < 1e-6 and tests[0]["p_bonferroni"] > 0.05
    (same,) = pairwise_tests({"u": np.full(5, 80.0), "v": np.full(5, 80.0)})
    assert same["p"] == 1.0 and same["p_bonferroni"] == 1.0


def test_failure_reduction():
    statistics = {"variants": {"hte": {"failure_percent": 3.0}, "2d-rte": {"failure_percent": 7.0},
                               "none": {"failure_percent": 0.0}}}
    assert failure_reduction(statistics, "hte", "2d-rte") == pytest.approx(100 * (1 - 3 / 7))
    assert failure_reduction(statistics, "hte", "none") is None
    every = failure_reductions(statistics, "2d-rte")
    assert list(every) == ["hte", "none"]
    assert every["hte"] == pytest.approx(100 * (1 - 3 / 7)) and every["none"] == pytest.approx(100.0)
    assert failure_reductions(statistics, "none") == {"hte": None, "2d-rte": None}


def test_pool_statistics_script_pools_runs_with_a_seed_subset_under_labels(tmp_path):
    """benchmarks/pool_statistics.py: the chosen variant and seeds of each run, relabelled; a
    replication's median covers the kept seeds only, paired by position across runs."""
    import gzip
    import json

    from tests.benchmark_runner import run_benchmark

    def run(folder, rows, packed=False):
        folder.mkdir()
        data = json.dumps({"episodes": [dict(zip(("variant", "seed", "replicate", "actions"), row),
                                              damage="leg1", reached=row[3] < 80) for row in rows]})
        if packed:
            (folder / "episodes.json.gz").write_bytes(gzip.compress(data.encode()))
        else:
            (folder / "episodes.json").write_text(data)

    # four seeds; seeds 1 and 3 of 'x' take 10 + r and 20 + r actions, the others 80 (failures)
    run(tmp_path / "four", [("x", s, r, {1: 10 + r, 3: 20 + r}.get(s, 80)) for s in range(4) for r in range(3)]
        + [("y", s, r, 5) for s in range(4) for r in range(3)])
    run(tmp_path / "two", [("z", s, r, 40 + 10 * s) for s in range(2) for r in range(3)], packed=True)
    out = tmp_path / "pooled.json"
    printed = run_benchmark("pool_statistics.py", "--out", str(out), "--key", "k",
                            "--run", f"x on 1,3={tmp_path / 'four'}:x@1,3", "--run", f"z={tmp_path / 'two'}")
    stats = json.loads(out.read_text())["k"]
    assert set(stats["variants"]) == {"x on 1,3", "z"}  # 'y' and seeds 0, 2 left out
    x, z = stats["variants"]["x on 1,3"], stats["variants"]["z"]
    assert (x["p25"], x["p50"], x["p75"]) == (15, 16, 16)  # medians 15 16 17: positions 0.5, 1, 1.5 round down and x["failures"] == 0 and x["episodes"] == 6
    assert (z["p25"], z["p50"], z["p75"]) == (45, 45, 45) and z["episodes"] == 6
    (test,) = stats["tests"]
    assert test["a"] == "x on 1,3" and test["median_a"] == 16 and test["median_b"] == 45
    assert "x on 1,3" in printed and "p = " in printed
