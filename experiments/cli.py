"""What the command-line tools share: bad input becomes one `error: ...` line on stderr and exit status 2.

    with input_errors() as errors:  # ConfigError or CheckpointError; input_errors(OSError) catches OSError only
        ...
    if errors.failed:
        return 2

    return fail("--chunk must be >= 1, got 0")  # prints the line, returns 2

    add_set_flag(parser)  # --set KEY=VALUE, repeatable: any setting by its dotted key
    overrides.update(set_overrides(args.set))

Ctrl-C ends a command at once with one line on stderr, `interrupted: <what was saved>[; resume
with: <command>]` (or `interrupted: nothing written`), and exit status 130, also while the main
thread waits in a long XLA call. Every command's `main` runs inside `interruptible` and keeps
its `saved` up to date (text, or a function that reads the run folder when Ctrl-C comes):

    @interruptible()  # nothing is written before the end
    def main(argv=None) -> int: ...

    with interruptible(lambda: checkpoint_saved(out, {"checkpoint.npz": ""}),
                       resume_command("experiments.train_flat", argv, out)) as interrupt:
        ...  # interrupt.saved = "wrote ..." as files are written

    stored = resumable_run(out, ["checkpoint.npz"])  # --resume: ConfigError unless out holds a run
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shlex
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from hte_jax.errors import ConfigError
from hte_jax.qd.io import CheckpointError, read_header, stored_config

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for a command Ctrl-C ended
INPUT_ERRORS = (ConfigError, CheckpointError)


def fail(message) -> int:
    """Print `error: message` on stderr; the exit status of a run refused for bad input."""
    print(f"error: {message}", file=sys.stderr)
    return EXIT_BAD_INPUT


def input_errors(*types: type[BaseException]) -> InputErrors:
    """A context manager that reports an exception of `types` (default `INPUT_ERRORS`) with `fail`
    and swallows it; its `failed` then tells the caller to return `EXIT_BAD_INPUT`. Others propagate."""
    return InputErrors(types or INPUT_ERRORS)


class InputErrors:
    """See `input_errors`."""

    def __init__(self, types: tuple[type[BaseException], ...]):
        self.types = types
        self.failed = False

    def __enter__(self) -> InputErrors:
        return self

    def __exit__(self, kind, error, traceback) -> bool:
        if error is None or not isinstance(error, self.types):
            return False
        fail(error)
        self.failed = True
        return True


def add_set_flag(parser: argparse.ArgumentParser) -> None:
    """`--set KEY=VALUE` (repeatable): override any setting by its key, dotted through nested
    configurations (`config.with_overrides`); applied after the setting flags."""
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a setting by its key, dotted through nested configurations "
                             "(planner.iterations=50, solver.ls_iterations=8, top.parents.selection=density); repeatable")


def set_overrides(items: list[str]) -> dict[str, str]:
    """The overrides of `--set` items "KEY=VALUE" (ConfigError if one has no "=" or no key)."""
    overrides = {}
    for item in items:
        key, equals, value = item.partition("=")
        if not equals or not key.strip():
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. seed=3")
        overrides[key.strip()] = value
    return overrides


class Interruption:
    """What the line Ctrl-C prints says. saved: what the command has written so far, as text or a
    function giving it (called when Ctrl-C comes, from another thread: it must only read files);
    None: nothing. resume: the command that continues from what was saved, or None."""

    def __init__(self, saved: str | Callable[[], str | None] | None = None, resume: str | None = None):
        self.saved = saved
        self.resume = resume

    def line(self) -> str:
        try:
            saved = self.saved() if callable(self.saved) else self.saved
        except Exception as error:  # the line must come out, whatever the description's trouble
            saved = f"what was saved is unknown ({type(error).__name__}: {error})"
        if saved is None:
            return "interrupted: nothing written"
        return f"interrupted: {saved}" + (f"; resume with: {self.resume}" if self.resume else "")


@contextlib.contextmanager
def interruptible(
    saved: str | Callable[[], str | None] | None = None, resume: str | None = None
) -> Iterator[Interruption]:
    """Within the block, Ctrl-C (SIGINT) prints `Interruption.line()` on stderr and ends the process
    with `EXIT_INTERRUPTED` at once, without a traceback and without waiting for running XLA
    computations. A Python signal handler only runs when the main thread executes bytecode, so the
    signal wakes a watcher thread instead (`signal.set_wakeup_fd`), which also runs while the main
    thread waits inside a jitted call, and which ends the process with `os._exit`: checkpoints are
    written to a temporary file and renamed (`qd.io.save_checkpoint`), so an exit mid-write keeps
    the previous one. Outside the main thread (no signal handling there) the block runs unguarded."""
    interruption = Interruption(saved, resume)
    if threading.current_thread() is not threading.main_thread():
        yield interruption
        return
    woken, wake = os.pipe()  # the signal's number is written to `wake`, read from `woken`
    os.set_blocking(wake, False)
    handler = signal.signal(signal.SIGINT, lambda signum, frame: None)  # a Python handler: what the wakeup fd needs
    wakeup = signal.set_wakeup_fd(wake, warn_on_full_buffer=False)
    watcher = threading.Thread(target=_watch, args=(woken, interruption), name="ctrl-c", daemon=True)
    watcher.start()
    try:
        yield interruption
    finally:
        signal.set_wakeup_fd(wakeup)
        signal.signal(signal.SIGINT, handler)
        os.write(wake, b"\0")  # no signal has number 0: tells the watcher to end
        watcher.join()
        os.close(wake)
        os.close(woken)


def _watch(woken: int, interruption: Interruption) -> None:
    while (byte := os.read(woken, 1)) not in (b"", b"\0"):
        if byte[0] == signal.SIGINT:
            _stop(interruption)


def _stop(interruption: Interruption) -> None:
    """Print the interruption's line and end the process now (stdout flushed first, so that lines
    printed before Ctrl-C are not lost when it is a file or pipe)."""
    line = interruption.line()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    newline = "\n" if os.isatty(2) else ""  # after the progress bar or the terminal's ^C
    with contextlib.suppress(OSError):
        os.write(2, f"{newline}{line}\n".encode())
    os._exit(EXIT_INTERRUPTED)


def resume_command(module: str, argv: Sequence[str] | None, out: str | Path) -> str:
    """The shell command that continues the run in `out`: `python -m module` with the arguments it
    was given (`argv`, None: sys.argv's), `--out out` unless given, and `--resume` unless given."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not any(a == "--out" or a.startswith("--out=") for a in args):
        args += ["--out", str(out)]
    if "--resume" not in args:
        args.append("--resume")
    return shlex.join(["python", "-m", module, *args])


def resumable_run(out: str | Path, checkpoints: Sequence[str]) -> dict:
    """For `--resume`: the configuration of the run in `out` (ConfigError when out holds none),
    once each of its `checkpoints` (files under out) that exists has been found to be a checkpoint
    (CheckpointError naming the first that is not), before any time is spent starting the run."""
    stored = stored_config(out)
    if stored is None:
        raise ConfigError(f"--resume: {out} holds no run to resume (no config.json); leave out --resume to start one")
    for name in checkpoints:
        if (Path(out) / name).exists():
            read_header(Path(out) / name)
    return stored


def checkpoint_saved(out: str | Path, checkpoints: dict[str, str]) -> str | None:
    """What a training run folder holds, for `Interruption.saved`: the last of `checkpoints` ({file
    under out: what it holds, "" for the run itself}, in training order) that exists and its
    generation, or that the run has no checkpoint yet; None if `out` holds no run (config.json).
    Reads the files as they are: a checkpoint file is replaced whole, never written in place."""
    out = Path(out)
    if not (out / "config.json").is_file():
        return None
    for name, what in reversed(checkpoints.items()):
        if (out / name).is_file():
            with np.load(out / name) as data:
                generation = int(data["generation"])
            return f"checkpoint{' of ' + what if what else ''} at generation {generation} kept in {out}"
    return f"no checkpoint yet, the run's configuration kept in {out}"
