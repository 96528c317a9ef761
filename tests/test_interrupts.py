"""Ctrl-C through the commands (`experiments.cli.interruptible`): a SIGINT ends a command within
seconds, also while its main thread waits in a long XLA call, with exit status 130 and exactly one
line on stderr saying what was saved and how to resume; the resume command it prints then works.

Each command runs in a subprocess (its own signal handling) with the session's compilation cache."""

import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from experiments.cli import EXIT_INTERRUPTED
from hte_jax.hbr.training import LAYERS
from hte_jax.qd.io import read_checkpoint
from tests.golden import HBR_ARGS, check

# Bit for bit: interrupted and resumed commands against the golden outputs; the tiny HBR's group (test_hbr_training).
pytestmark = [pytest.mark.exact_numerics, pytest.mark.xdist_group("hbr_tiny")]

ROOT = Path(__file__).resolve().parents[1]
PROMPTLY_S = 10.0  # "within a few seconds", with room for a loaded CI machine


# XLA's own C++ log lines (such as its slow-compile alarm on a loaded machine) would share stderr; added to
# the environment as it is when a command starts (XLA_FLAGS at XLA's defaults in this `exact_numerics` file)
QUIET_XLA = {"TF_CPP_MIN_LOG_LEVEL": "3"}


@pytest.fixture
def start():
    """start(module, *args): the command running in a subprocess; any still running at the end is killed."""
    started = []

    def run(module: str, *args: str) -> subprocess.Popen:
        started.append(subprocess.Popen([sys.executable, "-m", module, *args], cwd=ROOT, stdout=subprocess.PIPE,
                                        stderr=subprocess.PIPE, text=True, env={**os.environ, **QUIET_XLA}))
        return started[-1]

    yield run
    for process in started:
        if process.poll() is None:
            process.kill()
            process.communicate()


def interrupt(process: subprocess.Popen) -> tuple[float, str, str]:
    """Send SIGINT; (seconds until the process ended, stdout, stderr). Kills it after a minute."""
    sent = time.perf_counter()
    process.send_signal(signal.SIGINT)
    try:
        out, err = process.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
    return time.perf_counter() - sent, out, err


def wait_for(done, process: subprocess.Popen, what: str, timeout: float = 1800) -> None:
    began = time.perf_counter()
    while not done():
        assert process.poll() is None, f"ended before {what}: {process.communicate()}"
        assert time.perf_counter() - began < timeout, f"not {what} after {timeout} s"
        time.sleep(0.02)


@pytest.mark.slow
def test_ctrl_c_while_training_keeps_the_checkpoint_and_its_resume_command_finishes(tmp_path, start):
    """train_hbr --preset tiny, interrupted once the top layer has a checkpoint (while it trains or
    the step model compiles or runs: the main thread is in XLA); a leftover temporary file beside
    the checkpoint (what a kill mid-write leaves) does not disturb the resume, which finishes the
    run with the uninterrupted run's repertoires (bit for bit where golden outputs exist)."""
    out = tmp_path / "hbr"
    run = start("experiments.train_hbr", *HBR_ARGS, "--out", str(out))
    wait_for((out / "top" / "checkpoint.npz").exists, run, "the top layer's first checkpoint")
    seconds, stdout, stderr = interrupt(run)
    assert run.returncode == EXIT_INTERRUPTED, stderr
    assert seconds < PROMPTLY_S
    assert not (out / "hbr.npz").exists()
    layer = [name for name in LAYERS if (out / name / "checkpoint.npz").exists()][-1]
    arrays, _ = read_checkpoint(out / layer / "checkpoint.npz")  # complete: written whole, never in place
    resume = f"python -m experiments.train_hbr {' '.join(HBR_ARGS)} --out {out} --resume"
    assert stderr == (f"interrupted: checkpoint of layer {layer} at generation {int(arrays['generation'])} "
                      f"kept in {out}; resume with: {resume}\n")

    leftover = out / layer / f".checkpoint.npz.tmp-{_dead_pid()}"
    leftover.write_bytes((out / layer / "checkpoint.npz").read_bytes()[:1000])
    command = shlex.split(stderr.partition("resume with: ")[2])
    assert command[:3] == ["python", "-m", "experiments.train_hbr"]
    resumed = subprocess.run([sys.executable, *command[1:]], cwd=ROOT, capture_output=True, text=True, timeout=1800,
                             env={**os.environ, **QUIET_XLA})
    assert resumed.returncode == 0, resumed.stderr
    assert resumed.stdout.startswith(f"{out}: bottom ")
    check("hbr_tiny", out)


@pytest.mark.slow
def test_ctrl_c_in_a_long_xla_call_ends_the_command_at_once(tmp_path, start, monkeypatch):
    """modulation on 50 skills of the shipped HBR simulates them in one jitted call (minutes on a
    CPU). JAX's compile log says when the call has been lowered: from then on the main thread is
    inside XLA (compiling, then running), where no Python signal handler runs. A SIGINT then ends
    the command within seconds, with its one line after the log's and nothing written."""
    monkeypatch.setitem(QUIET_XLA, "JAX_LOG_COMPILES", "1")
    out = tmp_path / "modulation"
    run = start("experiments.modulation", "--skills", "50", "--no-progress", "--out", str(out))
    log = []
    while not (log and "Finished jaxpr to MLIR module conversion jit(run_chunk)" in log[-1]):
        log.append(run.stderr.readline())
        assert log[-1], f"ended before its simulation was lowered: {''.join(log[-20:])}"
    time.sleep(2)  # past the logging call, into XLA
    seconds, stdout, stderr = interrupt(run)
    assert run.returncode == EXIT_INTERRUPTED, stderr
    assert [line for line in stderr.splitlines() if not line.startswith("WARNING:jax")] == [
        "interrupted: nothing written"]
    assert stderr.splitlines()[-1] == "interrupted: nothing written" and stdout == ""
    assert seconds < PROMPTLY_S
    assert not out.exists()


@pytest.mark.slow
def test_ctrl_c_while_a_command_starts_writes_one_line(tmp_path, start):
    """A SIGINT while the command imports jax (before `interruptible` takes over)."""
    out = tmp_path / "flat"
    run = start("experiments.train_flat", "--preset", "tiny", "--no-progress", "--out", str(out))
    maps = Path(f"/proc/{run.pid}/maps")
    wait_for(lambda: "jaxlib" in maps.read_text(), run, "importing jax", timeout=120)
    seconds, stdout, stderr = interrupt(run)
    assert (run.returncode, stderr, stdout) == (EXIT_INTERRUPTED, "interrupted: nothing written\n", "")
    assert seconds < PROMPTLY_S
    assert not out.exists()


def test_a_checkpoint_write_removes_what_killed_writes_left(tmp_path):
    """An exit mid-write leaves `.<name>.tmp-<pid>` beside the checkpoint; the next write of that
    checkpoint removes those of ended processes, and keeps those of running ones."""
    from hte_jax.qd.io import save_checkpoint

    path = tmp_path / "checkpoint.npz"
    dead, alive = tmp_path / f".checkpoint.npz.tmp-{_dead_pid()}", tmp_path / f".checkpoint.npz.tmp-{os.getppid()}"
    other = tmp_path / f".other.npz.tmp-{_dead_pid()}"
    for leftover in (dead, alive, other):
        leftover.write_bytes(b"PK\x03\x04 half a checkpoint")
    save_checkpoint(path, {"generation": np.int32(3)})
    assert int(read_checkpoint(path)[0]["generation"]) == 3
    assert not dead.exists() and alive.exists() and other.exists()


def _dead_pid() -> int:
    """The id of a process that has ended."""
    child = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(child.stdout)
