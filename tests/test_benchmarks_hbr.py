"""The HBR benchmark scripts run end to end on the tiny preset and write well-formed results (a
separate module so that pytest-xdist runs it beside the other benchmark tests).
"""

import json

import pytest

from tests.benchmark_runner import run_benchmark, run_benchmark_process
from tests.processes import cpu_devices_env

# Runs the tiny HBR's programs, as test_hbr_training does: the same options and group, so they are compiled once.
pytestmark = [pytest.mark.exact_numerics, pytest.mark.slow, pytest.mark.xdist_group("hbr_tiny")]


def test_hbr_layer_benchmark(tmp_path):
    out = tmp_path / "layers.json"
    # the tiny preset's batch: its generation is the tiny HBR's (tests/test_hbr_training.py), compiled before
    stdout = run_benchmark("hbr_layers.py", "--preset", "tiny", "--batch-sizes", "16", "--repeats", "1",
                           "--layers", "bottom", "--out", str(out))
    result = json.loads(out.read_text())
    (row,) = result["rows"]
    assert (row["layer"], row["batch"]) == ("bottom", 16)
    assert row["evaluations_per_s"] > 0 and abs(row["steps_per_s"] / row["evaluations_per_s"] - 100) < 1e-6
    assert result["settings"]["preset"] == "tiny" and "eval/s" in stdout


def test_hbr_layer_benchmark_parts_and_trace(tmp_path):
    """--parts times ask, evaluate and tell apart; --trace records a generation and sums each traced process."""
    out = tmp_path / "layers.json"
    stdout = run_benchmark("hbr_layers.py", "--preset", "tiny", "--batch-sizes", "16", "--repeats", "1",
                           "--layers", "bottom", "--devices", "1", "--parts", "--trace", str(tmp_path / "trace"),
                           "--out", str(out))
    result = json.loads(out.read_text())
    (row,) = result["rows"]
    assert row["devices"] == 1 and result["settings"]["parts"] and "evaluate s" in stdout
    assert all(row[f"{part}_s"] > 0 for part in ("ask", "evaluate", "tell"))
    assert row["evaluate_s"] > row["tell_s"]  # 16 rollouts of 100 steps against 16 insertions
    processes = row["trace"]["processes"]
    assert processes and all(p["seconds"] > 0 and p["events"] > 0 and p["longest"] for p in processes.values())
    assert list(tmp_path.joinpath("trace", "bottom_16_1dev").rglob("perfetto_trace.json.gz"))


def test_hbr_layer_benchmark_on_two_devices(tmp_path):
    """--devices 2 spreads the batch over 2 forced CPU devices (its own process: the count is set at start)."""
    out = tmp_path / "layers.json"
    run_benchmark_process("hbr_layers.py", "--preset", "tiny", "--batch-sizes", "16", "--repeats", "1",
                          "--layers", "bottom", "--devices", "2", "--parts", "--out", str(out), env=cpu_devices_env(2))
    result = json.loads(out.read_text())
    (row,) = result["rows"]
    assert result["settings"]["devices"] == row["devices"] == 2 and row["evaluations_per_s"] > 0
    assert all(row[f"{part}_s"] > 0 for part in ("ask", "evaluate", "tell"))


def test_hbr_preset_benchmark(tmp_path):
    out = tmp_path / "preset.json"
    run_benchmark("hbr_preset.py", "--preset", "tiny", "--out", str(tmp_path / "run"), "--no-progress", "--json", str(out))
    result = json.loads(out.read_text())
    assert result["preset"] == "tiny" and result["total_wall_s"] > 0
    assert set(result["layers"]) == {"bottom", "middle", "top"}
    assert result["layers"]["top"]["evaluations"] == 64
    assert sum(layer["wall_time_s"] for layer in result["layers"].values()) <= result["total_wall_s"]
    assert (tmp_path / "run" / "hbr.npz").stat().st_size > 0


def test_determinism_benchmark(tmp_path):
    out = tmp_path / "det.json"
    stdout = run_benchmark("determinism.py", "--preset", "tiny", "--generations", "1", "--out", str(out))
    result = json.loads(out.read_text())
    assert result["identical"] is True  # on the CPU a seed is bit-reproducible
    assert result["elites"][0] == result["elites"][1] > 0 and len(result["wall_s"]) == 2
    assert "identical=True" in stdout


def test_scaling_benchmark_on_one_and_two_forced_devices(tmp_path):
    """benchmarks/scaling.py --cpu-devices 2: a top-layer generation on 1 and 2 devices (the tiny preset with --batch
    set through its overrides), each in its own process, with 1 device's efficiency 1 and a table."""
    out = tmp_path / "scaling.json"
    printed = run_benchmark_process("scaling.py", "--cpu-devices", "2", "--devices", "1,2", "--batch", "8",
                                    "--episodes", "0", "--repeats", "1", "--out", str(out))
    rows = json.loads(out.read_text())["rows"]
    assert [(r["devices"], r["impl"], r["batch"]) for r in rows] == [(1, "jax", 8), (2, "jax", 8)]
    assert all(r["evaluations_per_s"] > 0 and r["rollout_steps_per_s"] > 0 for r in rows)
    assert "evals/s" in printed and "wrote" in printed
