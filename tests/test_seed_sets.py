"""Seed sets through their commands: `train_set` (parts, resume, the budget-matched Flat-2D) and
`maze_eval` over a `--repertoire-dir` of seeds (a resumed run equals the whole run; a run of some seeds, `--seeds`,
its batches of those seeds; `--spread batches`, a worker process per device, equals the one-process run)."""

import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from experiments.cli import EXIT_BAD_INPUT, EXIT_INTERRUPTED
from experiments.batch_workers import plan_workers
from experiments.maze_eval import _check_warp_spread, _worker_devices
from experiments.maze_eval import main as maze_main
from hte_jax.errors import ConfigError
from experiments.train_set import main as set_main
from hte_jax.flat.store import load_flat, shipped_flat_path
from hte_jax.qd.io import PAUSE_BEFORE_RENAME, read_checkpoint, write_json
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


def _seed_folders(seeds, names=("a", "b")):
    """Seed folders (two by default) holding one flat file each (the shipped 2D repertoire): batches of the same
    shapes."""
    for name in names:
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


def _spread_batches(args, out, **env):
    """`maze_eval ARGS --spread batches` on 2 forced CPU devices, in a subprocess (started, not waited for)."""
    return subprocess.Popen([sys.executable, "-m", "experiments.maze_eval", *args, "--devices", "2", "--spread",
                             "batches", "--out", str(out)], cwd=ROOT, env=cpu_devices_env(2, **env),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _same_batch(ours, theirs):
    """Whether two batch files hold the same arrays, bit for bit."""
    return all(np.array_equal(a, read_checkpoint(theirs)[0][name]) for name, a in read_checkpoint(ours)[0].items())


@pytest.mark.slow
def test_spread_batches_runs_a_worker_per_device_as_one_process_would(two_seed_run, tmp_path):
    """On 2 forced CPU devices, --spread batches runs each of the two batches in a worker process of its own
    device: the batch files, bit for bit, and the summaries of the one-process run; each worker's batch line."""
    args, whole, spread = two_seed_run.args, two_seed_run.whole, tmp_path / "spread"
    run = _spread_batches(args, spread)
    stdout, stderr = run.communicate(timeout=900)
    assert run.returncode == 0, stderr[-3000:]
    for name in ("episodes.json", "statistics.json", "summary.json"):
        assert json.loads((spread / name).read_text()) == json.loads((whole / name).read_text()), name
    assert all(_same_batch(spread / f"episodes_{k}.npz", whole / f"episodes_{k}.npz") for k in (0, 1))
    batch_lines = sorted(line for line in stdout.splitlines() if line.startswith("batch "))
    assert [line.split(":")[0] for line in batch_lines] == ["batch 0 (2d-rte on seed 0", "batch 1 (2d-rte on seed 1"]
    assert "4 episodes in" in batch_lines[1] and "read from" not in stdout
    assert not list(spread.glob("worker_*.stderr"))


@pytest.mark.slow
def test_spread_batches_stops_at_a_failed_worker_and_resumes(two_seed_run, tmp_path):
    """Three seed folders, the second's file broken: worker 1 (batch 1) fails, the command ends with one line naming
    it, its device and its error, exit status 2; worker 0 finishes batch 0 (its file kept, as the one-process run's)
    and stops before batch 2. Its resume command, the file mended, runs batches 1 and 2 and summarises all three."""
    seeds = _seed_folders(tmp_path / "seeds", ("a", "b", "c"))
    broken = seeds / "b" / "flat2d.npz"
    broken.write_text("not a repertoire")
    args = list(two_seed_run.args)  # the fixture's flags over these seeds
    args[args.index("--repertoire-dir") + 1] = str(seeds)
    out = tmp_path / "run"
    # batch 0's file waits before its rename: worker 1 has failed long before worker 0 could start batch 2
    run = _spread_batches(args, out, **{PAUSE_BEFORE_RENAME: "10"})
    stdout, stderr = run.communicate(timeout=900)
    assert run.returncode == EXIT_BAD_INPUT, stderr[-3000:]
    [line] = stderr.splitlines()
    assert line.startswith(f"error: worker 1 (cpu device 1; batch 1) failed (exit status 2): {broken}: not an "
                           f"hte-jax checkpoint (not an .npz archive) (its stderr: {out / 'worker_1.stderr'}); the "
                           f"finished batches stay in {out}; resume with: python -m experiments.maze_eval "), line
    assert str(broken) in (out / "worker_1.stderr").read_text()
    assert (out / "episodes_0.npz").is_file() and not (out / "episodes_1.npz").exists()
    assert not (out / "episodes_2.npz").exists() and not (out / "summary.json").exists()
    assert _same_batch(out / "episodes_0.npz", two_seed_run.whole / "episodes_0.npz")

    shutil.copyfile(seeds / "a" / "flat2d.npz", broken)
    command = shlex.split(line.partition("resume with: ")[2])
    resumed = subprocess.run([sys.executable, *command[1:]], cwd=ROOT, env=cpu_devices_env(2), capture_output=True,
                             text=True, timeout=900)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"batch 0 (2d-rte on seed 0): read from {out / 'episodes_0.npz'}" in resumed.stdout
    assert _same_batch(out / "episodes_1.npz", two_seed_run.whole / "episodes_1.npz")
    assert sorted({r["seed"] for r in _records(out)}) == [0, 1, 2] and len(_records(out)) == 12
    assert not list(out.glob("worker_*.stderr"))  # the earlier failure's, removed when workers start again


@pytest.mark.slow
def test_ctrl_c_ends_the_workers_of_spread_batches(two_seed_run, tmp_path):
    """A SIGINT to the command alone (not to its workers) ends it with the line saying how to resume, and ends
    both workers."""
    out = tmp_path / "run"
    run = _spread_batches(two_seed_run.args, out)
    children = Path(f"/proc/{run.pid}/task/{run.pid}/children")
    began = time.perf_counter()
    while len(children.read_text().split()) < 2:
        assert run.poll() is None and time.perf_counter() - began < 120, run.communicate()
        time.sleep(0.05)
    workers = [int(pid) for pid in children.read_text().split()]
    run.send_signal(signal.SIGINT)
    stdout, stderr = run.communicate(timeout=60)
    assert run.returncode == EXIT_INTERRUPTED
    assert stderr.startswith(f"interrupted: wrote 0 of 2 batch files (episodes_<k>.npz) in {out}, no summary; "
                             "resume with: python -m experiments.maze_eval "), stderr
    assert stderr.rstrip("\n").endswith("--resume") and len(stderr.splitlines()) == 1

    def ended(pid):
        try:
            return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] in "ZX"  # a zombie has ended
        except FileNotFoundError:
            return True

    while not all(ended(pid) for pid in workers):
        assert time.perf_counter() - began < 180, "a worker outlived its command"
        time.sleep(0.05)


def test_spread_batches_deals_the_batches_to_a_process_per_device():
    """`--spread batches` over several devices: a worker per device, the i-th batch to run on device i mod N, on that
    device alone (a GPU's entry of CUDA_VISIBLE_DEVICES; a CPU worker takes --devices 1); one device, --spread
    episodes and a worker itself run here; --distributed and a bad --spread are one-line errors."""
    def device(platform, index):
        return SimpleNamespace(platform=platform, id=index, local_hardware_id=index)

    def mesh(*devices):
        return SimpleNamespace(devices=np.array(devices, dtype=object))

    gpus = [device("gpu", 0), device("gpu", 1)]
    assert _worker_devices("batches", mesh(*gpus), False, None) == gpus
    assert _worker_devices("batches", mesh(gpus[0]), False, None) == []
    assert _worker_devices("episodes", mesh(*gpus), False, None) == []
    assert _worker_devices("batches", mesh(*gpus), False, [0, 2]) == []  # a worker runs its batches itself
    with pytest.raises(ConfigError, match=r"^--spread batches starts a process per device itself: leave out "):
        _worker_devices("batches", mesh(*gpus), True, None)
    with pytest.raises(ConfigError, match=r"^--spread must be one of episodes, batches, got 'rows'$"):
        _worker_devices("rows", mesh(*gpus), False, None)

    argv = ["--variant", "2d-rte", "--devices", "2", "--spread", "batches"]
    workers = plan_workers("experiments.maze_eval", gpus, [[0], [2], [3]], argv,
                           {"CUDA_VISIBLE_DEVICES": "5,7", "PATH": "/bin"})
    assert [w.batches for w in workers] == [[0, 3], [2]]
    assert [w.env["CUDA_VISIBLE_DEVICES"] for w in workers] == ["5", "7"]  # the parent's list, entry by entry
    assert workers[1].name == "worker 1 (gpu 1, CUDA_VISIBLE_DEVICES=7; batch 2)"
    assert workers[0].command[1:] == ["-m", "experiments.maze_eval", *argv, "--resume", "--devices", "1",
                                      "--no-progress", "--worker-batches", "0,3"]
    assert workers[0].env["PATH"] == "/bin" and workers[0].env["PYTHONPATH"].split(os.pathsep)[0] == str(ROOT)
    assert [w.env["CUDA_VISIBLE_DEVICES"] for w in plan_workers("experiments.maze_eval", gpus, [[0], [1]], argv, {})] \
        == ["0", "1"]
    [alone] = plan_workers("experiments.maze_eval", gpus, [[4]], argv, {})  # fewer batches than devices
    assert alone.batches == [4] and alone.index == 0
    # a unit (a seed's batches, run together) goes to one worker whole
    assert [w.batches for w in plan_workers("experiments.maze_eval", gpus, [[0, 1], [2, 3], [4]], argv, {})] \
        == [[0, 1, 4], [2, 3]]
    cpus = plan_workers("experiments.maze_eval", [device("cpu", 0), device("cpu", 1)], [[0], [1]], argv,
                        {"XLA_FLAGS": "--x"})
    assert cpus[1].name == "worker 1 (cpu device 1; batch 1)" and "CUDA_VISIBLE_DEVICES" not in cpus[1].env
    assert cpus[1].env["XLA_FLAGS"] == "--x" and cpus[1].command[-5:-2] == ["--devices", "1", "--no-progress"]


def test_worker_batches_are_checked_in_one_line(tmp_path, capsys):
    """The hidden --worker-batches (a --spread batches worker's batches): indices of this run's batches, each once,
    with --resume; else one line, exit status 2, nothing written."""
    seeds = _seed_folders(tmp_path / "seeds")
    out = tmp_path / "never"
    args = ["--variant", "2d-rte", "--repertoire-dir", str(seeds), "--out", str(out)]
    cases = {"1,x": "error: --worker-batches must be comma-separated batch indices (integers >= 0), got '1,x'",
             "-1": "error: --worker-batches must be comma-separated batch indices (integers >= 0), got '-1'",
             "0,0": "error: --worker-batches names a batch twice: '0,0'",
             "1,2": "error: --worker-batches: this run has batches 0 to 1, not 2"}
    for value, line in cases.items():
        assert maze_main([*args, "--resume", "--worker-batches", value]) == EXIT_BAD_INPUT, value
        assert capsys.readouterr().err.splitlines() == [line]
    assert maze_main([*args, "--worker-batches", "1"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err.splitlines() == [
        "error: --worker-batches runs batches of a started run: give --resume too"]
    assert not out.exists()


def test_warp_splits_no_batch_over_several_gpus():
    """Several GPUs under one batch with --impl warp: a one-line ConfigError (XLA crashed compiling it); one GPU,
    CPU devices (where it runs) and the JAX backend pass."""
    gpu, cpu = SimpleNamespace(platform="gpu"), SimpleNamespace(platform="cpu")

    def mesh(*devices):
        return SimpleNamespace(devices=np.array(devices, dtype=object), axis_sizes=(len(devices),))

    with pytest.raises(ConfigError, match=r"^--impl warp splits no batch over several GPUs .* --spread batches"):
        _check_warp_spread("warp", mesh(gpu, gpu))
    _check_warp_spread("warp", mesh(gpu))
    _check_warp_spread("warp", mesh(cpu, cpu))
    _check_warp_spread("jax", mesh(gpu, gpu))
