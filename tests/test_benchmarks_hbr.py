"""The HBR benchmark scripts run end to end on the tiny preset and write well-formed results (a
separate module so that pytest-xdist runs it beside the other benchmark tests).
"""

import json

import pytest

from tests.benchmark_runner import run_benchmark

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
