"""The statistics on hand-made data: the paper's (nearest data-point percentiles, replication medians,
failure rates, Bonferroni-corrected Wilcoxon-Mann-Whitney tests), the episode level (Wilson intervals,
Fisher's exact test, Mann-Whitney on successful actions) and the seed level (exact signed-rank tests)."""

import json
import math
import subprocess
import sys
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
from scipy import stats

from hte_jax.online.maze import PAPER_MAZE
from hte_jax.online.plots import plot_failures, plot_prediction_error, plot_protocol_box, plot_variant_mazes

from hte_jax.online.statistics import (
    PAIR_LEGEND,
    action_summary,
    bonferroni,
    cell_statistics,
    episode_action_tests,
    episode_success_tests,
    failure_reduction,
    failure_reductions,
    min_signed_rank_p,
    nearest_percentile,
    pair_lines,
    pairwise_tests,
    protocol_statistics,
    replication_medians,
    seed_cells,
    seed_level_tests,
    seed_values,
    signed_rank_test,
    success_lines,
    success_rates,
    wilson_interval,
)
from hte_jax.qd.io import save_checkpoint
from tests.benchmark_runner import BENCHMARKS, benchmark_module, run_benchmark


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
    assert test["method"] == "paper" and "paper" in result["paper_method"] and "replication" in result["paper_method"]


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
    old = {k: statistics[k] for k in ("variants", "tests", "medians")}  # a statistics.json without the success block
    plot_failures(tmp_path / "old_failures.png", old)
    plot_protocol_box(tmp_path / "old_box.png", old, 80)
    for name in ("box", "failures", "error", "tracks", "old_failures", "old_box"):
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
    assert (x["p25"], x["p50"], x["p75"]) == (15, 16, 16)  # medians 15 16 17: positions 0.5, 1, 1.5 round down
    assert x["failures"] == 0 and x["episodes"] == 6
    assert (z["p25"], z["p50"], z["p75"]) == (45, 45, 45) and z["episodes"] == 6
    (test,) = stats["tests"]
    assert test["a"] == "x on 1,3" and test["median_a"] == 16 and test["median_b"] == 45 and test["method"] == "paper"
    # seeds 1, 3 of 'x' renumbered 0, 1: all 3 episodes reached on each; 'z' reached on both seeds too
    assert stats["success"]["x on 1,3"]["seeds"]["1"]["successes"] == 3 and stats["success"]["z"]["pooled"]["rate"] == 1
    # per seed 'x' median 11 and 21 actions, 'z' 40 and 50: both differences negative, 2 seeds, p = min p = 0.5
    (seed_test,) = stats["seed_tests"]["median_actions"]["pairs"]
    assert seed_test["seeds"] == 2 and seed_test["p"] == seed_test["min_p"] == 0.5 and seed_test["w_plus"] == 0
    assert "x on 1,3" in printed and "success 100.0 %" in printed and "seeds: success 1 (2, min 1)" in printed


def _episodes(rows, damage="d"):
    """Episode records of (variant, replicate, actions) rows; 80 actions is a failure."""
    return [{"variant": v, "seed": 0, "damage": damage, "replicate": r, "actions": a, "reached": a < 80, "broken": False}
            for v, r, a in rows]


def test_pool_statistics_reads_a_partial_run_from_its_batch_files(tmp_path, capsys):
    """A run folder without episodes.json(.gz) is read from its finished episodes_<k>.npz (maze_eval's records in
    their metadata), in batch order (2 before 10), with a note on stderr; --damage keeps the matching labels."""

    run = tmp_path / "cut"
    for k, actions in ((2, 10), (10, 30)):  # batch 2 reached in 10 actions, batch 10 in 30; each also a removed leg
        records = _episodes([("x", 0, actions)], f"d{k}") + _episodes([("x", 0, 50)], f"d{k}:removed")
        save_checkpoint(run / f"episodes_{k}.npz", {"taken": [actions, 50]}, {"seed": 0, "records": records})
    out, summary = tmp_path / "pooled.json", tmp_path / "summary.json"
    benchmark_module("pool_statistics").main(["--out", str(out), "--run", f"x={run}", "--damage", "d[0-9]+",
                                              "--summary", str(summary)])
    printed = capsys.readouterr()
    assert printed.err.strip() == f"note: {run}: a partial run, no episodes.json(.gz); read its 2 finished batch file(s)"
    stats = json.loads(out.read_text())["pooled"]
    assert list(stats["success"]["x"]["damages"]) == ["d2", "d10"]  # batch order; the removed legs left out
    assert stats["variants"]["x"]["episodes"] == 2 and (stats["variants"]["x"]["p25"], stats["variants"]["x"]["p75"]) == (
        10, 30)
    assert "world_level" not in stats and "x " in printed.out and "world level" not in printed.out
    assert json.loads(summary.read_text())["variants"]["x"]["actions_median"] == 10  # numpy's nearest of 10, 30


def test_pool_statistics_pools_worlds_and_tests_them_paired_by_position(tmp_path):
    """Folders joined by + are worlds: each folder's replicates follow the folders' before it, and world_level runs
    the seed level's signed-rank tests with the world in place of the seed."""

    # per world (replicates 0, 1) a's actions and b's (80: b fails once in world 2)
    actions = {0: ((10, 12), (20, 22)), 1: ((11, 13), (13, 15)), 2: ((12, 14), (16, 80))}
    for world, (a, b) in actions.items():
        (tmp_path / f"w{world}").mkdir()
        rows = [("a", r, x) for r, x in enumerate(a)] + [("b", r, x) for r, x in enumerate(b)]
        (tmp_path / f"w{world}" / "episodes.json").write_text(json.dumps({"episodes": _episodes(rows)}))
    worlds = "+".join(str(tmp_path / f"w{world}") for world in actions)
    out = tmp_path / "pooled.json"
    printed = run_benchmark("pool_statistics.py", "--out", str(out), "--run", f"a={worlds}:a", "--run", f"b={worlds}:b")
    pooled = json.loads(out.read_text())["pooled"]
    a = pooled["variants"]["a"]
    # replicates renumbered 0..5: 6 replications of one episode each, 10 11 12 12 13 14 (not 2 medians over worlds);
    # p25 at position 1.25 -> 11, p50 at 2.5 -> 12 (halfway, the lower), p75 at 3.75 -> 13
    assert (a["replications"], a["seeds_per_median"], a["p25"], a["p50"], a["p75"]) == (6, 1, 11, 12, 13)
    level = pooled["world_level"]
    assert "world" in level["sample"] and "unit" in level["sample"]
    assert [level["per_world"]["b"][k]["rate"] for k in ("0", "1", "2")] == [1, 1, 0.5]
    # median actions per world: a 11 12 13, b 21 14 16 (the failure left out): a - b = -10 -2 -3, all negative,
    # ranks 3 1 2, W+ = 0: of the 2^3 sign assignments only all-negative reaches 0, p = 2/8 = 0.25 = min p
    (test,) = level["median_actions"]["pairs"]
    assert (test["seed_ids"], test["values_a"], test["values_b"]) == ([0, 1, 2], [11, 12, 13], [21, 14, 16])
    assert (test["w_plus"], test["p"], test["min_p"], test["p_bonferroni"]) == (0, 0.25, 0.25, 0.25)
    assert test["p"] == pytest.approx(stats.wilcoxon([-10, -2, -3], method="exact").pvalue)  # scipy agrees
    # success rates a - b = 0 0 0.5: the two zeros dropped, one world ranked, p = 1
    (test,) = level["success_rate"]["pairs"]
    assert (test["seeds"], test["zero_differences"], test["w_plus"], test["p"]) == (3, 2, 1, 1)
    assert "a vs b: success 1 (3, min 1), median actions 0.25 (3, min 0.25)" in printed
    assert "success per world 100 / 100 / 50 %" in printed


def test_pool_statistics_merges_runs_of_other_seeds_joined_by_and(tmp_path, capsys):
    """Folders joined by & hold different seeds of the same replications: merged as they are, in any order, they
    give the statistics of one run holding every seed, also as the worlds of + ("A&B+C&D"); two folders holding
    the same episode stop the script with one line."""

    def write(folder, rows):
        """A run folder of (variant, seed, replicate, actions) rows; 80 actions is a failure."""
        folder.mkdir()
        records = [{"variant": v, "seed": s, "damage": "d", "replicate": r, "actions": a, "reached": a < 80,
                    "broken": False} for v, s, r, a in rows]
        (folder / "episodes.json").write_text(json.dumps({"episodes": records}))
        return str(folder)

    def rows(world, seeds):
        return [(v, s, r, 80 if (v, s, r, world) == ("b", 2, 1, 1) else base + world + step * s + r)
                for v, base, step in (("a", 10, 1), ("b", 20, -2)) for s in seeds for r in range(3)]

    both, first, rest = {}, {}, {}
    for world in (0, 1):
        both[world] = write(tmp_path / f"w{world}", rows(world, (0, 1, 2)))
        first[world] = write(tmp_path / f"w{world}-seed0", rows(world, (0,)))
        rest[world] = write(tmp_path / f"w{world}-seeds12", rows(world, (1, 2)))
    out = tmp_path / "pooled.json"
    runs = {"one": [both[0]], "parts": [f"{rest[0]}&{first[0]}"],
            "worlds": [f"{both[0]}+{both[1]}"], "world parts": [f"{first[0]}&{rest[0]}+{rest[1]}&{first[1]}"]}
    for key, (dirs,) in runs.items():
        run_benchmark("pool_statistics.py", "--out", str(out), "--key", key, "--run", f"a={dirs}:a", "--run", f"b={dirs}:b")
    pooled = json.loads(out.read_text())
    assert pooled["parts"] == pooled["one"] and pooled["world parts"] == pooled["worlds"]
    assert pooled["one"]["variants"]["a"]["seeds_per_median"] == 3 and pooled["one"]["seed_tests"]["success_rate"]
    assert pooled["worlds"]["variants"]["b"]["replications"] == 6 and pooled["worlds"]["world_level"]["per_world"]["b"]

    capsys.readouterr()
    assert benchmark_module("pool_statistics").main(["--out", str(out), "--run", f"a={both[0]}&{rest[0]}:a"]) == 2
    assert capsys.readouterr().err == (f"error: --run 'a={both[0]}&{rest[0]}:a': {both[0]} and {rest[0]} both hold "
                                       "variant 'a', seed 1, damage 'd', replicate 0 (& joins runs of other seeds)\n")
    benchmark_module("pool_statistics").main(["--out", str(out), "--key", "b only", "--run", f"b={both[0]}&{rest[0]}:b@0"])
    assert json.loads(out.read_text())["b only"]["variants"]["b"]["episodes"] == 3  # @0 leaves out the shared seeds


def test_pool_statistics_takes_other_seeds_cells_from_an_earlier_file(tmp_path, capsys):
    """--cells LABEL=FILE:KEY[:VARIANT] adds the per-seed cells of seeds whose episodes are gone: "seed_cells" of
    runs of seeds 2-4 plus the file's seeds 0-1 equals the cell statistics of one run holding seeds 0-4; a file's
    own "seed_cells" are read where it has them, also for a label without a run; bad specs, a missing file entry
    and seeds held twice stop the script with one line and exit status 2."""

    def write(folder, seeds):
        folder.mkdir()
        records = [{"variant": v, "seed": s, "damage": "d", "replicate": r, "actions": a, "reached": a < 80,
                    "broken": False}
                   for v, base in (("a", 10), ("b", 14)) for s in seeds for r in range(4)
                   for a in [80 if (v, r) == ("b", s % 4) else base + s + r]]
        (folder / "episodes.json").write_text(json.dumps({"episodes": records}))
        return str(folder)

    every, early = write(tmp_path / "all", range(5)), write(tmp_path / "early", (0, 1))
    late = write(tmp_path / "late", (2, 3, 4))
    out = tmp_path / "s.json"
    run_benchmark("pool_statistics.py", "--out", str(out), "--key", "early", "--run", f"x={early}:a",
                  "--run", f"y={early}:b")
    printed = run_benchmark("pool_statistics.py", "--out", str(out), "--key", "r5", "--run", f"a={late}:a", "--run",
                            f"b={late}:b", "--cells", f"a={out}:early:x", "--cells", f"b={out}:early:y")
    data = json.loads(out.read_text())
    whole = cell_statistics(seed_cells(json.loads(Path(every, "episodes.json").read_text())["episodes"]))
    assert data["r5"]["seed_cells"] == json.loads(json.dumps(whole))
    assert data["r5"]["variants"]["a"]["episodes"] == 12  # the other entries: the runs' episodes alone
    assert list(data["r5"]["seed_cells"]["success"]["b"]["seeds"]) == ["0", "1", "2", "3", "4"]
    (rate,) = data["r5"]["seed_cells"]["seed_tests"]["success_rate"]["pairs"]
    assert rate["seeds"] == 5 and rate["values_a"] == [1.0] * 5 and rate["p"] == pytest.approx(2 / 32)
    assert "every seed (--cells and runs)" in printed and "success  75.0 % [" in printed

    module = benchmark_module("pool_statistics")
    # a file's "seed_cells" where it has them (r5: seeds 0-4), for a label with no --run too
    run_benchmark("pool_statistics.py", "--out", str(out), "--key", "cells", "--run", f"a={late}:a",
                  "--cells", f"b={out}:r5")
    level = json.loads(out.read_text())["cells"]["seed_cells"]
    assert level["success"]["b"] == data["r5"]["seed_cells"]["success"]["b"]
    (rate,) = level["seed_tests"]["success_rate"]["pairs"]
    assert (rate["a"], rate["b"], rate["seed_ids"]) == ("a", "b", [2, 3, 4])
    for cells, message in ((f"a={out}", f"--cells 'a={out}' is not LABEL=FILE:KEY[:VARIANT]"),
                           (f"a={out}:early", f"--cells 'a={out}:early': {out} holds no per-seed cells of "
                                              "early/[seed_cells/]success/a (KeyError: 'a')"),
                           (f"a={out}:r5", f"--cells 'a={out}:r5': seeds [2, 3, 4] are also in the runs or cells of 'a'")):
        capsys.readouterr()
        assert module.main(["--out", str(tmp_path / "x.json"), "--run", f"a={late}:a", "--cells", cells]) == 2
        assert capsys.readouterr().err == f"error: {message}\n"
    assert not (tmp_path / "x.json").exists()


def test_cell_statistics_agree_with_the_episodes_where_both_apply():
    """From per-seed cells alone: the pooled successes and Wilson interval, Fisher's tests and the seed-level tests
    are those the episodes give."""
    records = _three_variants()
    level = cell_statistics(seed_cells(records))
    rates = success_rates(records)
    for variant, cell in level["success"].items():
        pooled = {k: rates[variant]["pooled"][k] for k in ("episodes", "successes", "rate", "ci95")}
        assert cell["pooled"] == pooled and cell["seeds"] == rates[variant]["seeds"]
    assert {k: v for k, v in level["episode_success"].items() if k != "sample"} == episode_success_tests(records)
    for quantity in ("success_rate", "median_actions"):
        assert level["seed_tests"][quantity] == seed_level_tests(records, quantity)
    assert level["success"]["a"]["pooled"]["successes"] == 6 and level["success"]["c"]["pooled"]["rate"] == 0


def test_pool_statistics_errors_are_one_line(tmp_path, capsys):
    """A folder without episodes or batch files, and runs pooling different numbers of worlds, stop with one line
    and exit status 2, as the command too."""

    main = benchmark_module("pool_statistics").main
    for name in ("w0", "w1"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "episodes.json").write_text(json.dumps({"episodes": _episodes([("x", 0, 10)])}))
    (tmp_path / "empty").mkdir()
    out = str(tmp_path / "pooled.json")
    cases = {f"{tmp_path / 'empty'} holds no episodes.json(.gz) or finished batch": ["--run", f"x={tmp_path / 'empty'}"],
             "the runs pool different numbers of folders (worlds): 'x' 2, 'y' 1": [
                 "--run", f"x={tmp_path / 'w0'}+{tmp_path / 'w1'}", "--run", f"y={tmp_path / 'w0'}"]}
    for message, argv in cases.items():
        capsys.readouterr()
        assert main(["--out", out, *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and message in err and err.count("\n") == 1
    assert not (tmp_path / "pooled.json").exists()
    command = subprocess.run([sys.executable, str(BENCHMARKS / "pool_statistics.py"), "--out", out, "--run",
                              f"x={tmp_path / 'empty'}"], capture_output=True, text=True, timeout=120)
    assert command.returncode == 2 and command.stderr.count("\n") == 1 and "holds no episodes" in command.stderr


def test_wilson_interval_by_hand():
    # 8 of 10, z = 1.959964, z^2 = 3.841459: scale = 1 + z^2/10 = 1.384146; centre = (0.8 + z^2/20) / scale = 0.716740;
    # half = z / scale * sqrt(0.8 * 0.2 / 10 + z^2 / 400) = 1.416010 * 0.160011 = 0.226578 -> [0.490162, 0.943318]
    low, high = wilson_interval(8, 10)
    assert low == pytest.approx(0.490162, abs=1e-6) and high == pytest.approx(0.943318, abs=1e-6)
    # 0 of 8: centre = half = (z^2/16) / (1 + z^2/8) = 0.240091 / 1.480182 = 0.162204 -> [0, 0.324408]
    assert wilson_interval(0, 8) == (0.0, pytest.approx(0.324408, abs=1e-6))
    assert wilson_interval(8, 8)[1] == 1.0 and wilson_interval(8, 8)[0] == pytest.approx(1 - 0.324408, abs=1e-6)
    with pytest.raises(ValueError, match="at least one trial"):
        wilson_interval(0, 0)
    with pytest.raises(ValueError, match="successes"):
        wilson_interval(11, 10)


def test_action_summary_uses_numpys_median_and_nearest_data_point_quartiles():
    summary = action_summary([30, 10, 20, 12, 14, 16])  # sorted 10 12 14 16 20 30
    # median (14 + 16) / 2; p25 at position 1.25 -> 12, p75 at 3.75 -> 20
    assert summary == {"count": 6, "median": 15.0, "p25": 12.0, "p75": 20.0}
    assert action_summary([]) == {"count": 0, "median": None, "p25": None, "p75": None}


def test_exact_signed_rank_test_by_hand():
    # 4 seeds all favouring one variant: ranks 1..4, W+ = 10; of the 2^4 = 16 sign assignments only all-positive
    # reaches 10, so P(W >= 10) = 1/16 and the two-sided p = 2/16 = 0.125
    assert signed_rank_test([0.1, 0.2, 0.3, 0.4]) == (10.0, 4, 0.125)
    assert signed_rank_test([-0.1, -0.2, -0.3, -0.4]) == (0.0, 4, 0.125)
    # ties: |d| = 1 1 2 3 take mean ranks 1.5 1.5 3 4; W+ = 1.5 + 1.5 + 4 = 7. The 16 subset sums of {1.5, 1.5, 3, 4}
    # are 0 1.5 1.5 3 3 4 4.5 4.5 5.5 5.5 6 7 7 8.5 8.5 10: five are >= 7, so p = 2 * 5/16 = 0.625
    assert signed_rank_test([1, 1, -2, 3]) == (7.0, 4, 0.625)
    # a zero difference is dropped (Wilcoxon's rule): the same test on the 4 others
    assert signed_rank_test([0, 1, 1, -2, 3]) == (7.0, 4, 0.625)
    assert signed_rank_test([0.0, 0.0]) == (0.0, 0, 1.0)  # nothing to rank: no evidence
    rng = np.random.default_rng(3)
    for n in (1, 3, 6, 9):  # without ties or zeros, scipy's exact test
        d = rng.normal(size=n)
        assert signed_rank_test(d)[2] == pytest.approx(stats.wilcoxon(d, method="exact").pvalue)
    with pytest.raises(ValueError, match="finite"):
        signed_rank_test([1.0, np.nan])


def test_min_signed_rank_p_is_what_that_many_seeds_can_reach():
    # 2 / 2^n: 4 seeds 0.125, 5 seeds 0.0625; one seed or none cannot go below 1
    assert [min_signed_rank_p(n) for n in (0, 1, 2, 4, 5)] == [1.0, 1.0, 0.5, 0.125, 0.0625]
    assert signed_rank_test(np.arange(1.0, 6.0))[2] == min_signed_rank_p(5)
    with pytest.raises(ValueError, match="seeds"):
        min_signed_rank_p(-1)


def _episode(variant, damage, seed, replicate, actions):
    """One record: `actions` None is a failure (the cap, 80)."""
    return {"variant": variant, "damage": damage, "seed": seed, "replicate": replicate,
            "actions": 80 if actions is None else actions, "reached": actions is not None, "broken": False}


def _three_variants():
    """'a' reaches 6 of 8 (d0: seed 0 10, 20; seed 1 30, fail. d1: seed 0 12, fail; seed 1 14, 16), 'b' 1 of 8
    (seed 1, d0: 40 actions), 'c' none; 2 damages x 2 seeds x 2 replicates each."""
    a = {("d0", 0): (10, 20), ("d0", 1): (30, None), ("d1", 0): (12, None), ("d1", 1): (14, 16)}
    b = {("d0", 0): (None, None), ("d0", 1): (40, None), ("d1", 0): (None, None), ("d1", 1): (None, None)}
    c = {key: (None, None) for key in a}
    return [_episode(v, d, s, r, x) for v, cells in (("a", a), ("b", b), ("c", c))
            for (d, s), pair in cells.items() for r, x in enumerate(pair)]


def test_success_rates_pooled_per_damage_and_per_seed():
    rates = success_rates(_three_variants())
    a = rates["a"]
    assert list(rates) == ["a", "b", "c"] and list(a["damages"]) == ["d0", "d1"] and list(a["seeds"]) == ["0", "1"]
    # pooled: 6 of 8; Wilson: scale = 1 + z^2/8 = 1.480182, centre = (0.75 + z^2/16) / scale = 0.668898, half =
    # z / scale * sqrt(0.75 * 0.25 / 8 + z^2 / 256) = 1.324137 * 0.196069 = 0.259623 -> [0.409275, 0.928521]
    assert (a["pooled"]["episodes"], a["pooled"]["successes"], a["pooled"]["rate"]) == (8, 6, 0.75)
    assert a["pooled"]["ci95"] == [pytest.approx(0.409275, abs=1e-6), pytest.approx(0.928521, abs=1e-6)]
    assert a["pooled"]["actions"] == {"count": 6, "median": 15.0, "p25": 12.0, "p75": 20.0}
    # d0: 10 20 30 (3 of 4): median 20; p25 at position 0.5 -> 10 (halfway, the lower), p75 at 1.5 -> 20
    assert a["damages"]["d0"]["successes"] == 3 and a["damages"]["d0"]["actions"] == {
        "count": 3, "median": 20.0, "p25": 10.0, "p75": 20.0}
    assert a["damages"]["d1"]["actions"]["median"] == 14.0  # 12 14 16
    # seed 0: 10 20 12 (3 of 4), median 12; seed 1: 30 14 16, median 16
    assert a["seeds"]["0"]["rate"] == a["seeds"]["1"]["rate"] == 0.75
    assert (a["seeds"]["0"]["actions"]["median"], a["seeds"]["1"]["actions"]["median"]) == (12.0, 16.0)
    c = rates["c"]["pooled"]
    assert c["successes"] == 0 and c["rate"] == 0 and c["ci95"][0] == 0.0 and c["actions"]["median"] is None
    assert seed_values(_three_variants(), "median_actions") == {"a": {0: 12.0, 1: 16.0}, "b": {0: None, 1: 40.0},
                                                                "c": {0: None, 1: None}}


def test_episode_level_tests_by_hand():
    records = _three_variants()
    success = episode_success_tests(records)
    assert success["bonferroni_pairs"] == 3 and "Fisher" in success["test"]
    ab = success["pairs"][0]
    # a 6 of 8, b 1 of 8: margins 8, 8 and 7, 9 of 16. P(X = k successes of a) = C(8, k) C(8, 7 - k) / C(16, 7), the
    # terms k = 0..7 being 8 224 1568 3920 3920 1568 224 8 / 11440; observed k = 6 (224): the two-sided p sums the
    # terms no larger, k = 0, 1, 6, 7: 464 / 11440 = 0.04056
    terms = [math.comb(8, k) * math.comb(8, 7 - k) for k in range(8)]
    assert terms == [8, 224, 1568, 3920, 3920, 1568, 224, 8] and sum(terms) == math.comb(16, 7) == 11440
    assert (ab["a"], ab["b"], ab["successes_a"], ab["episodes_a"], ab["successes_b"]) == ("a", "b", 6, 8, 1)
    assert ab["p"] == pytest.approx(464 / 11440) and ab["p_bonferroni"] == pytest.approx(3 * 464 / 11440)
    actions = episode_action_tests(records)
    ab, ac, bc = actions["pairs"]
    # a's 6 successful episodes all need fewer actions than b's one (40): U = 0; of the 7 equally likely ranks of
    # b's value only the largest gives U = 0, so the two-sided p = 2/7
    assert ab["u"] == 0 and ab["p"] == pytest.approx(2 / 7) and ab["p_bonferroni"] == pytest.approx(6 / 7)
    assert (ab["n_a"], ab["n_b"], ab["median_a"], ab["median_b"]) == (6, 1, 15.0, 40.0)
    # c has no successful episode: no test, still one of the 3 pairs corrected for
    assert ac["p"] is None and ac["p_bonferroni"] is None and ac["n_b"] == 0 and bc["u"] is None
    assert actions["bonferroni_pairs"] == 3


def test_seed_level_tests_on_the_seed_as_the_unit():
    records = _three_variants()
    rates = seed_level_tests(records, "success_rate")
    ab, ac, bc = rates["pairs"]
    # a - b per seed: 0.75 - 0 and 0.75 - 0.25, both positive: W+ = 1 + 2 = 3, p = 2 * 1/4 = 0.5 = the 2 seeds' min p
    assert (ab["seeds"], ab["seed_ids"], ab["w_plus"], ab["p"], ab["min_p"]) == (2, [0, 1], 3.0, 0.5, 0.5)
    assert ab["values_a"] == [0.75, 0.75] and ab["values_b"] == [0.0, 0.25] and ab["p_bonferroni"] == 1.0
    assert ab["min_p_bonferroni"] == 1.0  # 2 seeds over 3 pairs cannot reach significance
    # b - c: 0 on seed 0 (a tie, dropped), 0.25 on seed 1: one ranked seed, p = 1 = its min p
    assert (bc["seeds"], bc["zero_differences"], bc["p"], bc["min_p"]) == (2, 1, 1.0, 1.0)
    medians = seed_level_tests(records, "median_actions")
    ab, ac, bc = medians["pairs"]
    # b has no successful episode on seed 0: only seed 1 compared, 16 - 40 < 0: W+ = 0, p = 1
    assert (ab["seeds"], ab["seeds_without_success"], ab["w_plus"], ab["p"]) == (1, 1, 0.0, 1.0)
    # c never succeeds: no seed left, no test
    assert (ac["seeds"], ac["seeds_without_success"], ac["p"], ac["p_bonferroni"], ac["min_p"]) == (
        0, 2, None, None, 1.0)
    assert medians["bonferroni_pairs"] == 3 and "signed-rank" in medians["test"]
    with pytest.raises(ValueError, match="seed quantity"):
        seed_level_tests(records, "actions")


def test_four_seeds_all_favouring_one_variant_give_p_0_125():
    # per seed s, 'x' reaches 9 - s of 10 episodes and 'y' 5 - s: x is ahead on all 4 seeds, the exact p is 2/16
    records = [_episode(v, "d0", s, r, 20 if r < top - s else None)
               for v, top in (("x", 9), ("y", 5)) for s in range(4) for r in range(10)]
    (test,) = seed_level_tests(records, "success_rate")["pairs"]
    assert test["values_a"] == [0.9, 0.8, 0.7, 0.6] and test["values_b"] == [0.5, 0.4, 0.3, 0.2]
    assert (test["seeds"], test["w_plus"], test["p"], test["min_p"]) == (4, 10.0, 0.125, 0.125)
    assert test["p_bonferroni"] == 0.125  # one pair


def test_protocol_statistics_layout_and_summary_lines():
    statistics = protocol_statistics(_three_variants())
    assert set(statistics) == {"paper_method", "variants", "tests", "medians", "success", "episode_tests", "seed_tests"}
    assert "independent" in statistics["episode_tests"]["sample"] and "unit" in statistics["seed_tests"]["sample"]
    assert set(statistics["episode_tests"]) == {"sample", "success", "actions"}
    assert set(statistics["seed_tests"]) == {"sample", "success_rate", "median_actions"}
    assert [t["method"] for t in statistics["tests"]] == ["paper"] * 3
    assert statistics["success"]["a"]["pooled"]["successes"] == 6
    lines = success_lines(statistics)
    assert lines[0].split() == ["a", "success", "75.0", "%", "[40.9,", "92.9]", "6/8,", "actions", "15", "(12-20);",
                                "per", "seed", "75", "/", "75", "%"]
    assert "actions -;" in lines[2]  # c: no successful episode
    pairs = pair_lines(statistics)
    assert len(pairs) == 3 and pairs[0].startswith("  a vs b: paper U = ")
    assert "episodes: success 0.12, actions 0.86 | seeds: success 1 (2, min 1), actions 1 (1, min 1)" in pairs[0]
    assert "actions - (0, min 1)" in pairs[1] and "seed" in PAIR_LEGEND


def test_statistics_of_bad_records_say_what_is_wrong():
    with pytest.raises(ValueError, match="got none"):
        protocol_statistics([])
    with pytest.raises(ValueError, match="record 1 lacks reached"):
        protocol_statistics([_episode("a", "d0", 0, 0, 10),
                             {"variant": "a", "damage": "d0", "replicate": 1, "actions": 3}])
