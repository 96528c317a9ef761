"""The simulation, QD and online benchmark scripts run end to end at tiny sizes and write well-formed
results. These check that the scripts work, not how fast anything is (speed lives in benchmarks/results).
Each script's `main` runs in this process (tests/benchmark_runner.py), render_speed.py in its own.
"""

import json
import sys

import pytest

from hte_jax.flat.store import shipped_flat_path
from hte_jax.sim.robot import RobotConfig
from tests.benchmark_runner import benchmark_module, run_benchmark, run_benchmark_process

# With test_replay, which runs the adaptation benchmark's episode: one worker compiles its programs once.
pytestmark = pytest.mark.xdist_group("adaptation_episode")

common = benchmark_module("common")


@pytest.mark.slow
def test_batch_size_benchmark(tmp_path):
    out = tmp_path / "bs.json"
    stdout = run_benchmark("batch_size.py", "--max-batch", "1", "--steps", "20", "--repeats", "1",
                  "--native-batches", "4", "--compare", "4/8", "--out", str(out))
    result = json.loads(out.read_text())
    engines = {row["engine"]: row for row in result["rows"]}
    settings = [row["setting"] for row in result["rows"] if row["engine"] == "mjx"]
    assert settings == [common.setting_label(RobotConfig()), "4/8"] and result["settings"]["compare"] == "4/8"
    assert result["summary"]["ratio_by_batch"]["1"] > 0 and f"{settings[0]} / 4/8" in stdout
    assert set(engines) == {"mjx", "native"} and not any("error" in r for r in result["rows"])
    assert engines["mjx"]["steps_per_s"] > 0 and engines["mjx"]["compile_s"] > 0
    assert engines["native"]["steps_per_s"] > 0 and engines["native"]["threads"] >= 1
    assert result["summary"]["mjx_over_native"] > 0
    assert result["environment"]["mujoco"] == "3.17.0"
    assert "best_mjx_batch" in stdout


@pytest.mark.slow
def test_qd_overhead_benchmark(tmp_path):
    out = tmp_path / "qd.json"
    run_benchmark("qd_overhead.py", "--min-batch", "64", "--max-batch", "64", "--eval-max-batch", "0",
         "--archive-capacity", "1024", "--repeats", "1", "--out", str(out))
    rows = json.loads(out.read_text())["rows"]
    assert [r["container"] for r in rows] == ["grid_2d_100x100", "grid_8d_640k", "archive_9d_1024"]
    for row in rows:
        assert row["batch"] == 64 and row["ask_s"] > 0 and row["insert_s"] > 0
        assert row["filled"] >= {"grid_2d_100x100": 5000, "grid_8d_640k": 320_000, "archive_9d_1024": 512}[row["container"]]


@pytest.mark.slow
def test_adaptation_benchmark(tmp_path):
    """One leg-1 HTE episode of 2 actions with a planner of 8 iterations x 1 tree: the episode of
    tests/test_replay.py's run without --video, so the two share their compiled programs."""
    out = tmp_path / "adapt.json"
    stdout = run_benchmark("adaptation.py", "--batch-sizes", "1", "--max-actions", "2", "--iterations", "8", "--roots", "1",
                           "--repeats", "1", "--out", str(out))
    result = json.loads(out.read_text())
    (row,) = result["rows"]
    assert row["episodes"] == 1 and row["plan_median_s"] > 0 and row["plan_p95_s"] >= row["plan_median_s"]
    assert row["actions_per_run"] == [2] and len(row["runs"][0]["plan_s"]) == 2
    assert result["settings"]["iterations"] == 8 and result["repertoire"]["kind"] == "hbr"
    assert "plan med s" in stdout


@pytest.mark.slow
def test_render_speed_benchmark(tmp_path, gl_env, monkeypatch):
    for name, value in gl_env.items():  # the backend that starts here (the test skips where none does)
        monkeypatch.setenv(name, value)
    out = tmp_path / "render.json"
    stdout = run_benchmark_process("render_speed.py", "--seconds", "1", "--fps", "10", "--width", "64", "--height", "48",
                           "--repeats", "2", "--out", str(out))
    (row,) = json.loads(out.read_text())["rows"]
    assert row["frames"] == 10 and len(row["render_s_all"]) == 2 and row["render_s_median"] > 0
    assert row["total_s_median"] >= row["render_s_median"] and row["frames_per_s"] > 0
    assert row["mujoco_gl"] == gl_env["MUJOCO_GL"] and "frames/s" in stdout


def test_setting_strings():
    assert common.parse_setting("2/4@dt=0.005@tol=1e-6") == {"solver_iterations": 2, "ls_iterations": 4,
                                                       "timestep": 0.005, "solver_tolerance": 1e-6}
    assert common.setting_label(RobotConfig(**common.parse_setting("3/6@tol=1e-4"))) == "3/6@tol=0.0001"
    for bad in ("2", "2/x", "2/4@iters=3"):
        with pytest.raises(ValueError, match="setting"):
            common.parse_setting(bad)


@pytest.mark.slow
def test_physics_frontier_benchmark(tmp_path):
    """One setting against itself (no errors by construction) and the repertoire check on two elites. Its
    speed rollout is test_batch_size_benchmark's (batch 1, 20 steps, the default robot): one compile for both."""
    out = tmp_path / "frontier.json"
    setting = common.setting_label(RobotConfig())
    stdout = run_benchmark("physics_frontier.py", "--settings", setting, "--reference", setting, "--reference-checks", "",
                           "--batch", "1", "--steps", "20", "--repeats", "1", "--fidelity-size", "4", "--skills", "0",
                           "--repertoires", setting, "--elites", "2", "--flat", str(shipped_flat_path("2d")),
                           "--out", str(out))
    result = json.loads(out.read_text())
    (row,) = result["rows"]
    assert row["setting"] == setting and row["steps_per_s"] > 0 and row["compile_s"] > 0
    assert set(row["fidelity"]) == {"pooled", "random-intact", "random-damaged"}
    pooled = row["fidelity"]["pooled"]
    assert pooled["rollouts"] == 8 and pooled["max_cm"] == 0.0 and pooled["new_invalid"] == 0
    assert pooled["penetration_max_mm"] == pooled["reference_penetration_max_mm"] > 0
    assert row["budget_misses"] == [] and result["summary"]["fastest_within_budget"] == setting
    assert (tmp_path / result["plot"]).stat().st_size > 10_000
    (check,) = result["repertoires"]
    for name in ("hbr-top", "flat-2d"):
        assert check[name]["trained"] == "4/8"  # both shipped sets predate the solver settings
        assert check[name]["elites"] == 2 and 0 <= check[name]["in_own_cell"] <= 1 and check[name]["max_cm"] >= 0
    assert "fastest_within_budget" in stdout and "own cell" in stdout


@pytest.mark.slow
def test_load_time_benchmark(tmp_path, xla_defaults):
    out = tmp_path / "load.json"
    stdout = run_benchmark("load_time.py", "--repeats", "1", "--whole", "--out", str(out))
    result = json.loads(out.read_text())
    (row,) = result["rows"]
    assert "error" not in row and row["whole_equal"] is True  # the filled-rows lookup equals the whole one
    assert 0 < row["middle_filled"] < row["middle_capacity"] and 0 < row["bottom_filled"] < row["bottom_capacity"]
    assert row["load_hbr_s"] > 0 and row["load_spare_s"] > 0 and row["whole_lookup_s"] > 0
    assert set(result["medians"]) == {"load_hbr_s", "load_spare_s", "whole_lookup_s"}
    assert "whole lookup equal bit for bit: True" in stdout


@pytest.mark.slow
def test_cpu_commands_benchmark(tmp_path):
    """Each chosen command runs in the work folder, in the README's order, and lands in the JSON."""
    out, work = tmp_path / "commands.json", tmp_path / "work"
    stdout = run_benchmark("cpu_commands.py", "--commands", "modulation,repertoire_stats", "--help-only",
                           "--work-dir", str(work), "--out", str(out))
    result = json.loads(out.read_text())
    assert [row["command"] for row in result["rows"]] == ["repertoire_stats", "modulation"]
    for row in result["rows"]:
        assert row["exit"] == 0 and row["wall_s"] > 0 and row["cpu_s"] > 0 and "reason" not in row
        assert row["argv"][-1] == "--help"
        assert "usage:" in (work / "logs" / f"{row['command']}.log").read_text()
    assert result["environment"]["cpu_model"] and result["environment"]["usable_cores"] >= 1
    assert result["settings"]["help_only"] and "python -m experiments.modulation --help" in stdout


def test_cpu_commands_record_why_a_command_failed(tmp_path):
    cpu_commands = benchmark_module("cpu_commands")
    fails = [sys.executable, "-c", "import sys; print('50%\\r100%'); sys.exit('no OpenGL context')"]
    row = cpu_commands.run_command("render", fails, tmp_path, 60, tmp_path / "render.log")
    assert row["exit"] == 1 and row["reason"] == "no OpenGL context"
    row = cpu_commands.run_command("slow", [sys.executable, "-c", "import time; time.sleep(60)"], tmp_path, 1,
                                   tmp_path / "slow.log")
    assert row["exit"] is None and row["reason"] == "timeout after 1 s"
