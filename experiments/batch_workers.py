"""Worker processes that run a command's batches, one process per device (`maze_eval --spread batches`).

A parent process plans the batches and starts, per device, the same command with `--resume --devices 1
--worker-batches K,K,...`: each worker sees its device alone (CUDA_VISIBLE_DEVICES on a GPU; one of the host's
CPU devices otherwise), writes its batches' files and no summary; the parent waits, counting the files, and
stops every worker when one fails or on Ctrl-C. Processes, not threads: MuJoCo Warp's CUDA-graph capture is not
safe with several threads, and the planner's host round trips overlap without sharing one interpreter.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import select
import signal
import stat
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

from tqdm.auto import tqdm

from experiments.cli import EXIT_BAD_INPUT, Interruption

POLL_S = 0.5  # how often the parent looks at its workers and counts their batch files
ROOT = Path(__file__).resolve().parents[1]


@contextlib.contextmanager
def gpu_memory_left_free(free: bool) -> Iterator[None]:
    """Within the block (where jax starts its backends), jax claims no GPU memory in advance if `free`: the
    worker processes of --spread batches take it, this process only reads their batch files."""
    name = "XLA_PYTHON_CLIENT_PREALLOCATE"
    if not free:
        yield
        return
    before = os.environ.get(name)
    os.environ[name] = "false"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = before


@dataclasses.dataclass
class Worker:
    """A process of --spread batches: `command` runs `batches` of the run on one device."""
    index: int
    name: str  # in messages: "worker 1 (gpu 1, CUDA_VISIBLE_DEVICES=3; batches 1, 3)"
    batches: list[int]
    command: list[str]
    env: dict[str, str]


class WorkerFailed(Exception):
    """A worker process of --spread batches failed; `status` is the exit status the command ends with."""

    def __init__(self, message: str, status: int):
        super().__init__(message)
        self.status = status


def plan_workers(module: str, devices: list, units: list[list[int]], argv: list[str],
                 env: dict[str, str]) -> list[Worker]:
    """A worker per device, the i-th unit of `units` (batches that run together) on device i mod N (a device left
    without one gets no worker): this command with the same flags, --resume, on its device alone, no progress
    bar."""
    workers = []
    for i, device in enumerate(devices):
        share = [k for unit in units[i::len(devices)] for k in unit]
        if not share:
            continue
        where, visible = device_env(device, env)
        command = [sys.executable, "-m", module, *argv, "--resume", "--devices", "1", "--no-progress",
                   "--worker-batches", ",".join(map(str, share))]
        path = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))  # this checkout's code
        workers.append(Worker(i, f"worker {i} ({where}; batch{'es' * (len(share) > 1)} {', '.join(map(str, share))})",
                              share, command, {**env, **visible, "PYTHONPATH": path, "PYTHONUNBUFFERED": "1"}))
    return workers


def device_env(device, env: dict[str, str]) -> tuple[str, dict[str, str]]:
    """How messages name `device`, and the environment that shows a worker that device alone: on a GPU,
    CUDA_VISIBLE_DEVICES set to its entry of `env`'s list, or its index where `env` has none; CPU devices share
    the host's cores, the worker takes one (--devices 1) and keeps XLA_FLAGS."""
    if device.platform != "gpu":
        return f"cpu device {device.id}", {}
    listed = [entry.strip() for entry in env.get("CUDA_VISIBLE_DEVICES", "").split(",") if entry.strip()]
    index = device.local_hardware_id
    entry = listed[index] if listed else str(index)
    return f"gpu {device.id}, CUDA_VISIBLE_DEVICES={entry}", {"CUDA_VISIBLE_DEVICES": entry}


def run_workers(workers: list[Worker], out: Path, progress: bool, interrupt: Interruption) -> None:
    """Run the workers at once and wait for all, printing their lines (above a bar counting their batch files
    if `progress`); Ctrl-C ends them (`interrupt.start_child`). WorkerFailed naming the first that fails (the
    others stop after their current batch: their standard input closes) or ends without its batch files."""
    files = [out / f"episodes_{k}.npz" for w in workers for k in w.batches]
    for old in out.glob("worker_*.stderr"):  # an earlier attempt's failure
        old.unlink()
    bar = tqdm(total=len(files), desc="batches", unit="batch", disable=not progress)
    with contextlib.ExitStack() as stack:
        stack.callback(bar.close)
        started = []

        @stack.callback
        def end_all() -> None:  # none left running, whatever ends the block (a no-op for those that ended)
            for _, process, _, _ in started:
                process.terminate()

        for worker in workers:
            stderr = stack.enter_context(tempfile.TemporaryFile("w+"))
            with no_fork_warning():
                process = interrupt.start_child(worker.command, env=worker.env, stdin=subprocess.PIPE,
                                                stdout=subprocess.PIPE, stderr=stderr, text=True)
            relay = threading.Thread(target=_relay, args=(process.stdout,), name=f"{worker.name} stdout")
            relay.start()
            started.append((worker, process, stderr, relay))
        failed = None
        running = list(started)
        while running:
            time.sleep(POLL_S)
            _show_count(bar, files)
            for entry in [entry for entry in running if entry[1].poll() is not None]:
                running.remove(entry)
                worker, process, stderr, _ = entry
                if process.returncode != 0 and failed is None:
                    failed = WorkerFailed(_failure(worker, process.returncode, stderr, out),
                                          EXIT_BAD_INPUT if process.returncode == EXIT_BAD_INPUT else 1)
                    for _, other, _, _ in running:
                        other.stdin.close()
        for _, process, _, relay in started:
            relay.join()
            process.stdin.close()
        _show_count(bar, files)
    if failed is not None:
        raise failed
    for worker in workers:
        missing = [k for k in worker.batches if not (out / f"episodes_{k}.npz").is_file()]
        if missing:
            raise WorkerFailed(f"{worker.name} ended without writing episodes_{missing[0]}.npz", 1)


def _show_count(bar: tqdm, files: list[Path]) -> None:
    """The bar at the number of `files` written, redrawn only when it grows."""
    written = sum(f.is_file() for f in files)
    if written > bar.n:
        bar.update(written - bar.n)


def _relay(stream) -> None:
    """Print a worker's lines as they come, above the progress bar."""
    for line in stream:
        tqdm.write(line.rstrip("\n"))


def _failure(worker: Worker, status: int, stderr, out: Path) -> str:
    """The line saying `worker` failed: how, the last line of its stderr (all of it kept in out as
    worker_<i>.stderr), and what is kept."""
    stderr.seek(0)
    text = stderr.read()
    lines = [line for line in text.splitlines() if line.strip()]
    last = lines[-1].removeprefix("error: ") if lines else "nothing on stderr"
    if status < 0:
        try:
            how = f"killed by {signal.Signals(-status).name}"
        except ValueError:
            how = f"killed by signal {-status}"
    else:
        how = f"exit status {status}"
    log = out / f"worker_{worker.index}.stderr"
    log.write_text(text)
    return f"{worker.name} failed ({how}): {last} (its stderr: {log}); the finished batches stay in {out}"


def parent_gone() -> bool:
    """In a worker of --spread batches: whether its standard input, the pipe from the process that started it,
    has closed (that process ended, or asks it to stop after its current batch)."""
    try:
        if not stat.S_ISFIFO(os.fstat(0).st_mode):
            return False
        return bool(select.select([0], [], [], 0)[0]) and os.read(0, 1) == b""
    except OSError:
        return False


@contextlib.contextmanager
def no_fork_warning() -> Iterator[None]:
    """JAX's os.fork() warning does not apply to a subprocess that execs at once."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        yield
