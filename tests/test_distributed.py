"""`--distributed` for real: two processes on the CPU (`jax.distributed`, a coordinator on 127.0.0.1, gloo
collectives, one device each) run `train_hbr` and then `maze_eval` to the end, and their files equal those of
one process on 2 forced devices (the same rows per device), within the tolerances of tests/test_sharding.py.

Each of the two processes runs in its own working folder with a relative `--out`: a filesystem that is not
shared. Process 0 writes the run, process 1 writes nothing and shows no progress; a resumed run whose folder
process 1 does not see is refused on both, one copied to both folders goes on. The two-process
runs run beside the one-process run: XLA compiling the MJX programs, in each of the three processes, is most
of the time. The HBR trains the tiny preset with the middle and top layers' initial batches only
(`*.generations=0`: a generation is one more program to compile per layer; the bottom layer's generations
run the blocks, their replica check across processes and checkpoints). Bad settings (no coordinator, a
process missing) end with one line and exit status 2.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hte_jax.qd.io import read_checkpoint, run_files_digest
from tests.commands_script import STEP_CHUNK, near_goal_maze
from tests.test_sharding import EPISODE_TOLERANCE, TRAINING_TOLERANCE

ROOT = Path(__file__).resolve().parent.parent
# After test_commands (its group): the one-process reference on 2 forced devices loads the programs it compiled.
pytestmark = pytest.mark.xdist_group("two_device_runs")
PHASE_S = 900  # a phase's processes must all end by then: a hang fails with their output, never blocks
TRAIN = ["experiments.train_hbr", "--preset", "tiny", "--set", f"step_chunk={STEP_CHUNK}",
         "--set", "middle.generations=0", "--set", "top.generations=0"]
MAZE = ["experiments.maze_eval", "--variant", "hte", "--damage", "leg1", "--replicates", "2", "--iterations", "10",
        "--roots", "1", "--depth", "3", "--candidates", "10"]
PROGRESS = "%|"  # in every tqdm bar
CLUSTER_ENV = ("JAX_COORDINATOR", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID", "SLURM_", "OMPI_", "PMI_")


def base_env(**extra: str) -> dict[str, str]:
    """The session's environment (compilation cache, XLA flags) without any cluster's settings, quiet C++ logs."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(CLUSTER_ENV)}
    return {**env, "JAX_PLATFORMS": "cpu", "TF_CPP_MIN_LOG_LEVEL": "3",
            "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])), **extra}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def two_processes(**extra: str) -> list[dict[str, str]]:
    """The environments of processes 0 and 1 of a run on a coordinator at 127.0.0.1."""
    address = f"127.0.0.1:{free_port()}"
    return [base_env(JAX_COORDINATOR_ADDRESS=address, JAX_COORDINATOR_BIND_ADDRESS=address, JAX_NUM_PROCESSES="2",
                     JAX_PROCESS_ID=str(i), **extra) for i in range(2)]


def run_together(commands: dict[str, tuple[list[str], dict, Path]], logs: Path,
                 limit_s: float) -> dict[str, SimpleNamespace]:
    """Start every command {name: (argv after `python -m`, env, working folder)} at once, its output to
    logs/<name>.out and .err, and wait for all; each result has status, out, err, seconds. Past `limit_s`
    every process still running is killed and the test fails."""
    started, began = {}, time.perf_counter()
    logs.mkdir(parents=True)
    for name, (argv, env, cwd) in commands.items():
        cwd.mkdir(parents=True, exist_ok=True)
        files = logs / f"{name}.out", logs / f"{name}.err"
        with open(files[0], "w") as out, open(files[1], "w") as err:
            process = subprocess.Popen([sys.executable, "-m", *argv], cwd=cwd, env=env, stdout=out, stderr=err)
        started[name] = process, files
    results, late = {}, []
    for name, (process, (out, err)) in started.items():
        try:
            status = process.wait(timeout=max(1.0, limit_s - (time.perf_counter() - began)))
        except subprocess.TimeoutExpired:
            process.kill()
            status = process.wait()
            late.append(name)
        results[name] = SimpleNamespace(status=status, out=out.read_text(), err=err.read_text(),
                                        seconds=time.perf_counter() - began)
    if late:
        pytest.fail(f"{', '.join(late)} still running after {limit_s:.0f} s, killed:\n"
                    + "\n".join(f"== {n}: {r.out[-1500:]}{r.err[-1500:]}" for n, r in results.items()))
    return results


def ended(results: dict[str, SimpleNamespace]) -> None:
    for name, r in results.items():
        assert r.status == 0, f"{name} ended with {r.status}:\n{r.out[-3000:]}\n{r.err[-5000:]}"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """train_hbr, then maze_eval on the one-process HBR: in one process (folder one/) beside two processes
    (folders p0/ and p1/, each its working folder: `--out` relative)."""
    root = tmp_path_factory.mktemp("distributed")
    one, p = root / "one", [root / "p0", root / "p1"]
    (root / "maze.json").write_text(json.dumps(near_goal_maze()))
    reference = base_env(XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2")
    envs = two_processes()
    distributed = ["--distributed", "--distributed-timeout", "300"]
    train = run_together({
        "one": ([*TRAIN, "--out", "train_hbr", "--no-progress"], reference, one),
        **{f"p{i}": ([*TRAIN, "--out", "train_hbr", *distributed], envs[i], p[i]) for i in range(2)}},
        root / "logs" / "train", PHASE_S)
    ended(train)
    maze = [*MAZE, "--repertoire", str(one / "train_hbr" / "hbr.npz"), "--maze", str(root / "maze.json"),
            "--out", "maze_eval"]
    envs = two_processes()
    evaluation = run_together({"one": ([*maze, "--no-progress"], reference, one),
                               **{f"p{i}": ([*maze, *distributed], envs[i], p[i]) for i in range(2)}},
                              root / "logs" / "maze_eval", PHASE_S)
    ended(evaluation)
    return SimpleNamespace(root=root, one=one, p=p, train=train, evaluation=evaluation, maze=maze)


def assert_same_arrays(got: Path, expected: Path, tolerance: float) -> None:
    """The arrays of two checkpoint files: floats within `tolerance`, the others exactly."""
    (a, _), (b, _) = read_checkpoint(got), read_checkpoint(expected)
    assert a.keys() == b.keys(), got
    for name, value in b.items():
        assert a[name].shape == value.shape and a[name].dtype == value.dtype, (got, name)
        if value.dtype.kind in "fc":
            np.testing.assert_allclose(a[name], value, rtol=0, atol=tolerance, err_msg=f"{got}: {name}")
        else:
            np.testing.assert_array_equal(a[name], value, err_msg=f"{got}: {name}")


def checkpoint_files(folder: Path) -> list[Path]:
    return sorted(path.relative_to(folder) for path in folder.rglob("*.npz"))


@pytest.mark.slow
@pytest.mark.timeout(1500)
def test_train_hbr_on_two_processes_writes_what_one_process_does(runs):
    one, two = runs.one / "train_hbr", runs.p[0] / "train_hbr"
    files = checkpoint_files(one)
    assert [str(f) for f in files] == ["bottom/checkpoint.npz", "hbr.npz", "middle/checkpoint.npz",
                                       "top/checkpoint.npz"]
    assert checkpoint_files(two) == files
    for name in files:
        assert_same_arrays(two / name, one / name, TRAINING_TOLERANCE)
    assert json.loads((two / "config.json").read_text()) == json.loads((one / "config.json").read_text())
    summaries = [json.loads((folder / "summary.json").read_text()) for folder in (one, two)]
    assert [len(s["devices"]) for s in summaries] == [2, 2]
    for layer in ("bottom", "middle", "top"):
        assert summaries[1]["layers"][layer]["filled"] == summaries[0]["layers"][layer]["filled"]
        assert summaries[1]["layers"][layer]["evaluations"] == summaries[0]["layers"][layer]["evaluations"]
    assert summaries[0]["layers"]["bottom"]["evaluations"] > summaries[0]["layers"]["middle"]["evaluations"]
    assert (two / "plots").is_dir()


@pytest.mark.slow
def test_maze_eval_on_two_processes_writes_what_one_process_does(runs):
    one, two = runs.one / "maze_eval", runs.p[0] / "maze_eval"
    assert checkpoint_files(two) == checkpoint_files(one) == [Path("episodes_0.npz")]
    assert_same_arrays(two / "episodes_0.npz", one / "episodes_0.npz", EPISODE_TOLERANCE)
    records = [json.loads((folder / "episodes.json").read_text())["episodes"] for folder in (one, two)]
    assert len(records[0]) == 2 and all(r["reached"] or r["broken"] for r in records[0])
    for got, expected in zip(records[1], records[0]):
        errors = [got.pop("prediction_error"), expected.pop("prediction_error")]
        assert got == expected
        np.testing.assert_allclose(errors[0], errors[1], rtol=0, atol=EPISODE_TOLERANCE)
    assert (json.loads((two / "summary.json").read_text()) == json.loads((one / "summary.json").read_text()))


@pytest.mark.slow
def test_only_process_0_writes_and_shows_progress(runs):
    """Process 1 runs in a folder of its own: it writes nothing there, draws no progress bar and prints
    no summary; process 0 draws the bars and prints the summaries."""
    assert list(runs.p[1].iterdir()) == []
    for phase, summary in ((runs.train, "primitives"), (runs.evaluation, "wrote maze_eval")):
        assert PROGRESS in phase["p0"].err and summary in phase["p0"].out
        assert PROGRESS not in phase["p1"].err + phase["p1"].out
        assert summary not in phase["p1"].out


@pytest.mark.slow
def test_a_resume_that_a_process_cannot_see_is_refused_on_every_process(runs):
    """Process 0 holds the HBR run (its folder), process 1's folder has none: both stop before any training,
    with one line and exit status 2. The maze_eval run copied to both folders resumes (its batches read, not
    run): process 0 writes the results again, process 1 leaves its copy as it was."""
    p = [runs.root / "resume0", runs.root / "resume1"]
    shutil.copytree(runs.p[0] / "train_hbr", p[0] / "train_hbr")
    resume = ["--resume", "--no-progress", "--distributed", "--distributed-timeout", "120"]
    envs = two_processes()
    refused = run_together({f"p{i}": ([*TRAIN, "--out", "train_hbr", *resume], envs[i], p[i]) for i in range(2)},
                           runs.root / "logs" / "refused", 300)
    line = "error: process 1 of 2 sees other files in train_hbr than process 0: every process reads the run folder"
    for r in refused.values():
        assert r.status == 2, r.err[-3000:]
        assert len(r.err.strip().splitlines()) == 1 and r.err.startswith(line), r.err
    finished = runs.p[0] / "maze_eval"
    for folder in p:
        shutil.copytree(finished, folder / "maze_eval")
    envs = two_processes()
    resumed = run_together({f"p{i}": ([*runs.maze, *resume], envs[i], p[i]) for i in range(2)},
                           runs.root / "logs" / "resumed", 300)
    ended(resumed)
    assert "batch 0 (hte on seed 0): read from maze_eval/episodes_0.npz" in resumed["p0"].out
    assert "read from" not in resumed["p1"].out
    assert (p[0] / "maze_eval" / "episodes.json").read_text() == (finished / "episodes.json").read_text()
    assert run_files_digest(p[1] / "maze_eval") == run_files_digest(finished)  # process 1 wrote nothing


def test_distributed_without_a_coordinator_is_one_line_and_status_2(tmp_path):
    done = run_together({"alone": (["experiments.maze_eval", "--distributed", "--show-config"], base_env(), tmp_path)},
                        tmp_path / "logs", 120)["alone"]
    assert done.status == 2
    assert done.err.strip().splitlines() == [
        "error: --distributed: coordinator_address should be defined. (under SLURM or Open MPI jax reads the "
        "settings from its environment; else set JAX_COORDINATOR_ADDRESS=host:port, JAX_NUM_PROCESSES and "
        "JAX_PROCESS_ID)"]


@pytest.mark.parametrize("present", [0, 1])
def test_a_missing_process_is_one_line_and_status_2_after_the_timeout(tmp_path, present):
    """Process 0 alone waits for process 1 at its coordinator; process 1 alone finds no coordinator."""
    env = two_processes()[present]
    done = run_together({"alone": (["experiments.train_hbr", "--distributed", "--distributed-timeout", "3",
                                    "--show-config"], env, tmp_path)}, tmp_path / "logs", 120)["alone"]
    assert done.status == 2
    assert done.err.strip().splitlines() == [
        f"error: --distributed: not every process joined {env['JAX_COORDINATOR_ADDRESS']} within 3 s (are all 2 "
        "processes started, each with its own process id?)"]
    assert done.seconds < 60  # the 3 s, process start and imports: not jax's default of 300 s


def test_bad_process_settings_are_input_errors(monkeypatch):
    from experiments import cli
    from hte_jax.errors import ConfigError

    with pytest.raises(ConfigError, match="--distributed-timeout must be an integer >= 1"):
        cli.join_processes(0)
    monkeypatch.setenv("JAX_PROCESS_ID", "first")
    with pytest.raises(ConfigError, match="JAX_PROCESS_ID must be an integer, got 'first'"):
        cli.join_processes(5)


def test_the_run_folder_digest_covers_the_files_a_resume_reads(tmp_path):
    (tmp_path / "config.json").write_text("{}")
    (tmp_path / "metrics.csv").write_text("block\n")
    first = run_files_digest(tmp_path)
    (tmp_path / "metrics.csv").write_text("block\n0\n")  # process 0 alone reads and appends it
    assert run_files_digest(tmp_path) == first
    (tmp_path / "bottom").mkdir()
    (tmp_path / "bottom" / "checkpoint.npz").write_bytes(b"1")
    second = run_files_digest(tmp_path)
    assert second != first
    (tmp_path / "bottom" / "checkpoint.npz").write_bytes(b"2")
    assert run_files_digest(tmp_path) not in (first, second)


def test_sigterm_ends_a_distributed_run_as_it_ends_a_lone_one(tmp_path):
    """A joined --distributed process (one of one) ends on SIGTERM, as a `kill` or a scheduler sends it: jax's
    preemption service, which catches SIGTERM, is off."""
    address = f"127.0.0.1:{free_port()}"
    env = base_env(JAX_COORDINATOR_ADDRESS=address, JAX_COORDINATOR_BIND_ADDRESS=address, JAX_NUM_PROCESSES="1",
                   JAX_PROCESS_ID="0")
    err = tmp_path / "err.txt"
    with open(err, "w") as stderr:
        process = subprocess.Popen([sys.executable, "-m", *TRAIN[:3], "--set", "bottom.generations=1000000",
                                    "--no-progress", "--out", "run", "--distributed", "--distributed-timeout", "60"],
                                   cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=stderr)
    try:
        deadline = time.monotonic() + 240
        while not (tmp_path / "run" / "config.json").exists():  # written once the process has joined
            assert process.poll() is None, err.read_text()[-3000:]
            assert time.monotonic() < deadline, "the run wrote no config.json in 240 s"
            time.sleep(0.5)
        process.terminate()
        assert process.wait(timeout=60) == -signal.SIGTERM
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
