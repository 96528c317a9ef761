"""The simulation, QD and online benchmark scripts run end to end at tiny sizes and write well-formed
results. These check that the scripts work, not how fast anything is (speed lives in benchmarks/results).
"""

import json

from tests.benchmark_runner import run_benchmark


def test_batch_size_benchmark(tmp_path):
    out = tmp_path / "bs.json"
    stdout = run_benchmark("batch_size.py", "--max-batch", "1", "--steps", "20", "--repeats", "1",
                  "--native-batches", "4", "--out", str(out))
    result = json.loads(out.read_text())
    engines = {row["engine"]: row for row in result["rows"]}
    assert set(engines) == {"mjx", "native"} and not any("error" in r for r in result["rows"])
    assert engines["mjx"]["steps_per_s"] > 0 and engines["mjx"]["compile_s"] > 0
    assert engines["native"]["steps_per_s"] > 0 and engines["native"]["threads"] >= 1
    assert result["summary"]["mjx_over_native"] > 0
    assert result["environment"]["mujoco"] == "3.17.0"
    assert "best_mjx_batch" in stdout


def test_qd_overhead_benchmark(tmp_path):
    out = tmp_path / "qd.json"
    run_benchmark("qd_overhead.py", "--min-batch", "64", "--max-batch", "64", "--eval-max-batch", "0",
         "--archive-capacity", "1024", "--repeats", "1", "--out", str(out))
    rows = json.loads(out.read_text())["rows"]
    assert [r["container"] for r in rows] == ["grid_2d_100x100", "grid_8d_640k", "archive_9d_1024"]
    for row in rows:
        assert row["batch"] == 64 and row["ask_s"] > 0 and row["insert_s"] > 0
        assert row["filled"] >= {"grid_2d_100x100": 5000, "grid_8d_640k": 320_000, "archive_9d_1024": 512}[row["container"]]


def test_adaptation_benchmark(tmp_path):
    out = tmp_path / "adapt.json"
    stdout = run_benchmark("adaptation.py", "--batch-sizes", "2", "--max-actions", "2", "--iterations", "10", "--roots", "1",
                  "--repeats", "1", "--out", str(out))
    result = json.loads(out.read_text())
    (row,) = result["rows"]
    assert row["episodes"] == 2 and row["plan_median_s"] > 0 and row["plan_p95_s"] >= row["plan_median_s"]
    assert row["actions_per_run"] == [2] and len(row["runs"][0]["plan_s"]) == 2
    assert result["settings"]["iterations"] == 10 and result["repertoire"]["kind"] == "hbr"
    assert "plan med s" in stdout
