"""benchmarks/protocol_time.py times whole maze_eval runs through the command and tests two runs' results; and
the commands' persistent compilation cache (`--compile-cache`)."""

import json
import os
import subprocess
import sys

import pytest

from tests.benchmark_runner import ROOT, benchmark_module, run_benchmark

# test_seed_sets.py's and test_protocol.py's tiny 2D-RTE batch: its programs may already be in the session's cache
TINY = "--variant 2d-rte --damage none,leg1 --replicates 2 --max-actions 2 --roots 1"


@pytest.mark.slow
def test_protocol_time_runs_maze_eval_and_compares_two_runs(tmp_path, capsys):
    out, work = tmp_path / "protocol_time.json", tmp_path / "work"
    stdout = run_benchmark("protocol_time.py", "--run", f"a={TINY} --iterations 50", "--run", f"b={TINY} --iterations 20",
                           "--compare", "a,b", "--work", str(work), "--out", str(out))
    result = json.loads(out.read_text())
    for label, iterations in (("a", 50), ("b", 20)):
        run = result["runs"][label]
        assert run["wall_s"] == float((work / label / "wall_s.txt").read_text()) > 0
        assert run["planner"] == {"iterations": iterations, "roots": 1} and run["impl"] == "jax"
        (batch,) = run["batches"]
        assert batch["episodes"] == 4 and batch["actions"] == 2 and batch["variants"] == ["2d-rte"]
        assert batch["setup_s"] > 0 and batch["first_action_s"] > 0 and batch["plan_median_s"] > 0
        assert batch["seconds"] > batch["setup_s"] + batch["first_action_s"] and batch["run_with"] == [0]
        assert run["batches_s"] == pytest.approx(batch["seconds"])
        episodes = json.loads((work / label / "episodes.json").read_text())["episodes"]
        assert run["variants"]["2d-rte"]["successes"] == sum(r["reached"] for r in episodes)
    row = result["comparisons"]["a,b"]["variants"]["2d-rte"]
    assert row["episodes"] == [4, 4] and 0 < row["success_p"] <= 1 and row["success_p_bonferroni"] == row["success_p"]
    assert "a vs b" in stdout and "2d-rte" in stdout

    # a finished run is read again (--read), not run; bad input is one line and exit status 2
    again = tmp_path / "again.json"
    run_benchmark("protocol_time.py", "--read", f"a={work / 'a'}", "--out", str(again))
    assert json.loads(again.read_text())["runs"]["a"]["batches"] == result["runs"]["a"]["batches"]
    protocol_time = benchmark_module("protocol_time")
    capsys.readouterr()
    assert protocol_time.main(["--read", f"a={work / 'a'}", "--compare", "a,c"]) == 2
    assert protocol_time.main(["--read", f"x={tmp_path}"]) == 2
    assert protocol_time.main(["--run", "nolabel"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "error: --compare a,c: name two of the runs (a)"
    assert err[1].startswith(f"error: {tmp_path}: not a finished maze_eval run")
    assert err[2] == "error: --run 'nolabel': expected LABEL=VALUE" and len(err) == 3


@pytest.mark.slow
def test_compile_cache_keeps_a_commands_programs_for_the_next_run(tmp_path):
    """--compile-cache DIR: the first run writes its programs there (small ones too), a second run of the same
    shapes adds none; 'none' writes nowhere (not even to the folder JAX_COMPILATION_CACHE_DIR names); a bad
    folder is one line and exit status 2."""
    cache, elsewhere = tmp_path / "cache", tmp_path / "elsewhere"
    env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": str(elsewhere)}
    env.pop("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", None)  # the commands' own default: every program kept

    def run(*args):
        command = [sys.executable, "-m", "experiments.train_flat", "--variant", "2d", "--preset", "tiny",
                   "--generations", "0", "--no-progress", *args]
        return subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)

    first = run("--compile-cache", str(cache), "--out", str(tmp_path / "a"))
    assert first.returncode == 0, first.stderr[-2000:]
    written = sorted(p.name for p in cache.iterdir())
    assert not elsewhere.exists()
    assert any(name.startswith("jit_rollout") for name in written)  # the simulation
    assert any(name.startswith("jit_broadcast_in_dim") for name in written)  # and a small op outside jit
    second = run("--compile-cache", str(cache), "--out", str(tmp_path / "b"))
    assert second.returncode == 0, second.stderr[-2000:]
    assert sorted(p.name for p in cache.iterdir()) == written  # every program read back, none compiled anew
    off = run("--compile-cache", "none", "--out", str(tmp_path / "c"))
    assert off.returncode == 0, off.stderr[-2000:]
    assert not elsewhere.exists() and sorted(p.name for p in cache.iterdir()) == written
    (tmp_path / "file").write_text("")
    bad = run("--compile-cache", str(tmp_path / "file" / "sub"), "--out", str(tmp_path / "d"))
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines()[-1].startswith(f"error: --compile-cache: cannot make {tmp_path / 'file' / 'sub'}")


def test_action_time_refuses_a_malformed_config_with_one_line():
    """benchmarks/action_time.py --config that is not KEY=VALUE items: one line on stderr, exit status 2, nothing run."""
    command = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "action_time.py"), "--config", "iterations"],
                             capture_output=True, text=True, timeout=120)
    assert command.returncode == 2
    assert command.stderr == "error: --config 'iterations': give KEY=VALUE items separated by commas\n"
