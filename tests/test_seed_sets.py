"""Seed sets through their commands: `train_set` (parts, resume, the budget-matched Flat-2D) and
`maze_eval` over a `--repertoire-dir` of seeds (a resumed run equals the whole run; a run of some seeds, `--seeds`,
its batches of those seeds)."""

import json
import os
import shutil
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from experiments.cli import EXIT_BAD_INPUT
from experiments.maze_eval import _batch_meshes, _check_warp_spread, run_batches
from experiments.maze_eval import main as maze_main
from hte_jax import sharding
from hte_jax.errors import ConfigError
from experiments.train_set import main as set_main
from hte_jax.flat.store import load_flat, shipped_flat_path
from hte_jax.qd.io import read_checkpoint, write_json
from tests.benchmark_runner import run_benchmark
from tests.processes import ROOT, cpu_devices_env

# With test_protocol, which runs these 2D-RTE episodes: one worker compiles their programs once.
pytestmark = pytest.mark.xdist_group("rte_episodes")


def test_train_set_refuses_bad_input_in_one_line(tmp_path, capsys):
    out = tmp_path / "seed1"
    args = ["--seed", "1", "--preset", "tiny", "--out", str(out), "--no-progress"]
    assert set_main([*args, "--parts", "2d,bogus"]) == EXIT_BAD_INPUT
    assert set_main([*args, "--impl", "cuda"]) == EXIT_BAD_INPUT
    assert set_main([*args, "--resume"]) == EXIT_BAD_INPUT  # no set there yet
    err = capsys.readouterr().err.splitlines()
    assert err == ["error: unknown part(s) bogus; choose among hbr, spare, 2d, 8d, aprol, matched",
                   "error: --impl must be jax or warp, got 'cuda'",
                   f"error: --resume: {out} holds no set to resume"]
    assert not out.exists()


@pytest.mark.slow
def test_train_set_parts_resume_and_matched_budget(tmp_path, capsys):
    out = tmp_path / "seed1"
    args = ["--seed", "1", "--preset", "tiny", "--out", str(out), "--no-progress"]
    assert set_main([*args, "--parts", "2d"]) == 0
    flat, _ = load_flat(out / "flat2d.npz")
    assert flat.damages == ("none",) and int(np.asarray(flat.repertoire.filled).sum()) > 0
    assert set_main([*args, "--parts", "2d"]) == EXIT_BAD_INPUT  # a set is there: --resume or another --out
    assert set_main([*args, "--resume", "--parts", "matched"]) == EXIT_BAD_INPUT  # needs the HBR's budget
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith(f"error: {out} is not empty")
    assert err[1] == "error: the matched Flat-2D needs the evaluations of part(s) hbr, spare: train them first"

    # the budgets an HBR and its spare archive report (their runs are the commands' own tests)
    for part in ("hbr", "spare"):
        (out / "runs" / part).mkdir(parents=True)
    write_json(out / "runs" / "hbr" / "part.json", {"evaluations": 192})
    write_json(out / "runs" / "spare" / "part.json", {"evaluations": 96})
    before = os.stat(out / "flat2d.npz").st_mtime_ns
    assert set_main([*args, "--resume", "--parts", "2d,matched"]) == 0
    assert os.stat(out / "flat2d.npz").st_mtime_ns == before  # a finished part is kept, not trained again
    parts = json.loads((out / "set.json").read_text())["parts"]
    assert parts["matched"]["evaluations"] == 288 == parts["hbr"]["evaluations"] + parts["spare"]["evaluations"]
    assert parts["2d"]["evaluations"] < parts["matched"]["evaluations"] and parts["2d"]["impl"] == "jax"
    assert (out / "matched" / "flat2d.npz").is_file()


def _seed_folders(seeds):
    """Two seed folders holding one flat file each (the shipped 2D repertoire): two batches of the same shapes."""
    for name in ("a", "b"):
        (seeds / name).mkdir(parents=True)
        shutil.copyfile(shipped_flat_path("2d"), seeds / name / "flat2d.npz")
    return seeds


@pytest.fixture(scope="module")
def two_seed_run(tmp_path_factory):
    """maze_eval's 2D-RTE episodes over two seed folders: its arguments (without --out) and its run folder."""
    seeds = _seed_folders(tmp_path_factory.mktemp("two_seeds") / "seeds")
    # test_protocol.py's 2D-RTE batches (4 episodes of 2 actions, its planner): their compiled programs serve both
    args = ["--variant", "2d-rte", "--damage", "none,leg1", "--replicates", "2", "--max-actions", "2", "--iterations", "50",
            "--roots", "1", "--repertoire-dir", str(seeds), "--no-progress"]
    whole = seeds.parent / "whole"
    assert maze_main([*args, "--out", str(whole)]) == 0
    return SimpleNamespace(args=args, whole=whole)


def _records(run):
    return json.loads((run / "episodes.json").read_text())["episodes"]


@pytest.mark.slow
def test_maze_eval_resumes_a_killed_run_to_the_same_results(two_seed_run, tmp_path, capsys):
    args, whole, resumed = two_seed_run.args, two_seed_run.whole, tmp_path / "resumed"
    shutil.copytree(whole, resumed)
    for name in ("episodes_1.npz", "episodes.json", "statistics.json", "summary.json"):  # killed in batch 1
        (resumed / name).unlink()
    capsys.readouterr()
    assert maze_main([*args, "--out", str(resumed), "--resume"]) == 0
    assert f"batch 0 (2d-rte on seed 0): read from {resumed / 'episodes_0.npz'}" in capsys.readouterr().out
    for name in ("episodes.json", "statistics.json", "summary.json"):
        assert json.loads((resumed / name).read_text()) == json.loads((whole / name).read_text()), name
    assert {r["seed"] for r in _records(resumed)} == {0, 1}

    assert maze_main([*args, "--out", str(tmp_path / "none"), "--resume"]) == EXIT_BAD_INPUT
    assert maze_main([*args[:-1], "--damage", "leg2", "--out", str(resumed), "--resume"]) == EXIT_BAD_INPUT
    assert maze_main([*args, "--spread", "rows", "--out", str(tmp_path / "never")]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith(f"error: --resume: {tmp_path / 'none'} holds no run to resume")
    assert err[1] == f"error: {resumed} was started with a different configuration (differs in: damages)"
    assert err[2] == "error: --spread must be one of episodes, batches, got 'rows'" and len(err) == 3
    assert not (tmp_path / "never").exists()

    # On 2 forced CPU devices, --spread batches runs the two batches at once, each whole on one device: the
    # programs and results of one device, bit for bit.
    spread = tmp_path / "spread"
    done = subprocess.run([sys.executable, "-m", "experiments.maze_eval", *args, "--devices", "2", "--spread", "batches",
                           "--out", str(spread)], cwd=ROOT, env=cpu_devices_env(2), capture_output=True, text=True,
                          timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    for name in ("episodes.json", "statistics.json", "summary.json"):
        assert json.loads((spread / name).read_text()) == json.loads((whole / name).read_text()), name
    for k in (0, 1):
        ours, theirs = (read_checkpoint(run / f"episodes_{k}.npz")[0] for run in (spread, whole))
        assert all(np.array_equal(ours[name], theirs[name]) for name in theirs), k


@pytest.mark.slow
def test_maze_eval_runs_some_seeds_as_the_run_over_all_does(two_seed_run, tmp_path):
    """--seeds runs only those seed folders, each keeping its index: seed 1 alone is the whole run's seed-1 batch,
    bit for bit; the runs of seed 0 and of seed 1 joined by & (benchmarks/pool_statistics.py) pool to the
    whole run's statistics."""
    args, whole = two_seed_run.args, two_seed_run.whole
    parts = {seed: tmp_path / f"seed{seed}" for seed in (1, 0)}
    for seed, out in parts.items():
        assert maze_main([*args, "--seeds", str(seed), "--out", str(out)]) == 0
    alone = _records(parts[1])
    assert len(alone) == 4 and alone == [r for r in _records(whole) if r["seed"] == 1]
    assert json.loads((parts[1] / "config.json").read_text())["seeds"] == "1"
    ours, header = read_checkpoint(parts[1] / "episodes_0.npz")
    theirs = read_checkpoint(whole / "episodes_1.npz")[0]
    assert header["metadata"]["seed"] == 1 and not (parts[1] / "episodes_1.npz").exists()
    assert (parts[1] / "plots" / "maze_2d-rte.png").is_file()  # the trajectories of the run's first seed
    assert all(np.array_equal(ours[name], theirs[name]) for name in theirs)
    # the seeds' episodes differ (their PRNG keys do): the comparison tells the seeds apart
    assert not np.array_equal(read_checkpoint(whole / "episodes_0.npz")[0]["trajectory"], theirs["trajectory"])

    pooled = tmp_path / "pooled.json"
    run_benchmark("pool_statistics.py", "--out", str(pooled), "--key", "parts", "--run", f"x={parts[0]}&{parts[1]}")
    run_benchmark("pool_statistics.py", "--out", str(pooled), "--key", "whole", "--run", f"x={whole}")
    statistics = json.loads(pooled.read_text())
    assert statistics["parts"] == statistics["whole"]
    assert statistics["whole"]["variants"]["x"]["seeds_per_median"] == 2 and statistics["whole"]["seed_tests"]


def test_maze_eval_refuses_bad_seeds_in_one_line(tmp_path, capsys):
    """--seeds: integers, each once, among the seed folders of --repertoire-dir, which it needs; else one line, exit
    status 2, nothing written."""
    seeds = _seed_folders(tmp_path / "seeds")
    out = tmp_path / "never"
    cases = {"1,x": "error: seeds: '1,x' is not comma-separated seed indices (integers >= 0, e.g. 1,2,3)",
             "-1": "error: seeds: '-1' is not comma-separated seed indices (integers >= 0, e.g. 1,2,3)",
             "0,1,0": "error: seeds: '0,1,0' names seed 0 twice",
             "1,2": f"error: seeds: repertoire_dir {seeds} has no seed 2 (its subfolders are seeds 0 to 1)"}
    for value, line in cases.items():
        assert maze_main(["--variant", "2d-rte", "--repertoire-dir", str(seeds), "--seeds", value, "--out", str(out)]) \
            == EXIT_BAD_INPUT, value
        assert capsys.readouterr().err.splitlines() == [line]
    assert maze_main(["--variant", "2d-rte", "--seeds", "0", "--out", str(out)]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err.splitlines() == [
        "error: seeds picks seed folders of repertoire_dir: give repertoire_dir too"]
    assert not out.exists()


def test_spread_batches_is_one_mesh_per_device_and_one_process():
    """`--spread batches` runs a batch on each device's own mesh, dealt in turn; a multi-process run is refused."""
    mesh = sharding.batch_mesh()
    meshes = _batch_meshes("batches", mesh, distributed=False)
    assert [m.devices.tolist() for m in meshes] == [[d] for d in mesh.devices.flat]
    assert _batch_meshes("episodes", mesh, distributed=False) == [mesh]
    with pytest.raises(ConfigError, match="--spread batches runs in one process"):
        _batch_meshes("batches", mesh, distributed=True)
    first, second = object(), object()  # stand-ins for two devices' meshes
    ran = run_batches([0, 2, 3], lambda k, on: (k, on), [first, second])
    assert [ran(k) for k in (0, 2, 3)] == [(0, first), (2, second), (3, first)]  # dealt in turn
    assert run_batches([4], lambda k, on: (k, on), [mesh])(4) == (4, mesh)  # one mesh: run when asked


def test_warp_splits_no_batch_over_several_gpus():
    """Several GPUs under one batch with --impl warp: a one-line ConfigError (XLA crashed compiling it); one GPU per
    batch, CPU devices (where it runs) and the JAX backend pass."""
    gpu, cpu = SimpleNamespace(platform="gpu"), SimpleNamespace(platform="cpu")

    def mesh(*devices):
        return SimpleNamespace(devices=np.array(devices, dtype=object), axis_sizes=(len(devices),))

    with pytest.raises(ConfigError, match=r"^--impl warp splits no batch over several GPUs .* --spread batches"):
        _check_warp_spread("warp", [mesh(gpu, gpu)])
    _check_warp_spread("warp", [mesh(gpu), mesh(gpu)])
    _check_warp_spread("warp", [mesh(cpu, cpu)])
    _check_warp_spread("jax", [mesh(gpu, gpu)])


def test_a_failed_batch_raises_when_its_turn_comes():
    """With several meshes a batch's exception reaches the caller when it asks for that batch."""
    meshes = [object(), object()]

    def run(k, on):
        if k == 1:
            raise ValueError("batch 1 broke")
        return k, on

    ran = run_batches([0, 1, 2, 3], run, meshes)
    assert ran(0) == (0, meshes[0])
    with pytest.raises(ValueError, match="batch 1 broke"):
        ran(1)
    assert ran(2) == (2, meshes[0])  # batch 2 is the first mesh's second: it ran
