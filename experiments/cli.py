"""What the command-line tools share. Bad input is one `error: ...` line on stderr and exit status 2:

    with input_errors() as errors:  # ConfigError or CheckpointError; input_errors(OSError) catches OSError only
        ...
    if errors.failed:
        return 2

Ctrl-C ends a command at once, also while the main thread waits in a long XLA call, with one line on
stderr, `interrupted: <what was saved>[; resume with: <command>]` (or `interrupted: nothing written`),
and exit status 130. Every command's `main` runs inside `interruptible` and keeps its `saved` up to
date (text, or a function that reads the run folder when Ctrl-C comes); the processes it starts with
`Interruption.start_child` end with it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shlex
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np
from jax.sharding import Mesh

from hte_jax import sharding
from hte_jax.errors import ConfigError
from hte_jax.qd.io import CheckpointError, read_header, require_same_run_folder, stored_config

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for a command Ctrl-C ended
INPUT_ERRORS = (ConfigError, CheckpointError)


def fail(message) -> int:
    """Print `error: message` on stderr; the exit status of a run refused for bad input."""
    print(f"error: {message}", file=sys.stderr)
    return EXIT_BAD_INPUT


@contextlib.contextmanager
def input_errors(*types: type[BaseException]) -> Iterator[SimpleNamespace]:
    """Reports an exception of `types` (default `INPUT_ERRORS`) with `fail` and swallows it, setting `failed`."""
    outcome = SimpleNamespace(failed=False)
    try:
        yield outcome
    except (types or INPUT_ERRORS) as error:
        fail(error)
        outcome.failed = True


def set_overrides(items: list[str]) -> dict[str, str]:
    """The overrides of `--set` items "KEY=VALUE" (ConfigError if one has no "=" or no key)."""
    overrides = {}
    for item in items:
        key, equals, value = item.partition("=")
        if not equals or not key.strip():
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. seed=3")
        overrides[key.strip()] = value
    return overrides


def add_setting_flags(parser: argparse.ArgumentParser, metavars: dict[str, str], aliases: dict | None = None) -> None:
    """A flag overriding each setting ({key: metavar}; `--middle-generations` for `middle.generations`
    unless `aliases` names another), then `--set KEY=VALUE` (repeatable): any setting by its dotted key."""
    for key, metavar in metavars.items():
        flag = (aliases or {}).get(key, "--" + key.replace(".", "-").replace("_", "-"))
        parser.add_argument(flag, dest=key, default=None, metavar=metavar, help=f"override {key}")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a setting by its key, dotted through nested configurations "
                             "(planner.iterations=50, solver.ls_iterations=8, middle.eta_m=20); repeatable")


def setting_overrides(args: argparse.Namespace, keys) -> dict[str, str]:
    """The settings the flags of `add_setting_flags` give, then those of `--set`."""
    overrides = {key: getattr(args, key) for key in keys if getattr(args, key) is not None}
    return {**overrides, **set_overrides(args.set)}


# The settings of a plain multi-process launch: jax reads JAX_COORDINATOR_ADDRESS (host:port of process 0)
# itself, and SLURM's or Open MPI's environment when these are not set.
PROCESS_ENV = ("JAX_NUM_PROCESSES", "JAX_PROCESS_ID")
JOIN_GRACE_S = 30  # jax's own deadline comes this much after ours: at its deadline it aborts the process


def add_device_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--devices", type=int, default=None, metavar="N",
                        help="spread every batch over the first N visible devices (default: all)")
    parser.add_argument("--distributed", action="store_true",
                        help="one of several processes (jax.distributed): the coordinator and this process's place "
                             "come from SLURM or Open MPI, else JAX_COORDINATOR_ADDRESS=host:port (of process 0), "
                             "JAX_NUM_PROCESSES and JAX_PROCESS_ID; only process 0 writes files and shows progress "
                             "(docs/design.md, \"Several processes\")")
    parser.add_argument("--distributed-timeout", type=int, default=120, metavar="S",
                        help="with --distributed: seconds to wait for every process to join (default 120)")
    parser.add_argument("--compile-cache", default=None, metavar="DIR",
                        help="keep the compiled programs in DIR, so a later run of the same shapes skips compiling "
                             f"(default: ${CACHE_ENV} if set, else {default_compile_cache()}; 'none': off)")


def device_mesh(args: argparse.Namespace) -> Mesh:
    """The mesh --devices and --distributed ask for (call it before anything touches jax's devices); turns on
    the compilation cache --compile-cache names."""
    use_compile_cache(getattr(args, "compile_cache", None))
    if args.distributed:
        join_processes(args.distributed_timeout)
    return sharding.batch_mesh(sharding.check_device_count(args.devices))


CACHE_ENV = "JAX_COMPILATION_CACHE_DIR"  # jax's own setting of its persistent compilation cache
MIN_COMPILE_ENV = "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"  # jax's: programs faster to compile are not kept


def default_compile_cache() -> Path:
    """$XDG_CACHE_HOME/hte_jax/xla, or ~/.cache/hte_jax/xla."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "hte_jax" / "xla"


def use_compile_cache(flag: str | None) -> Path | None:
    """jax's persistent compilation cache for this process, before its first compilation: in `flag`'s folder,
    off for "none", else in $JAX_COMPILATION_CACHE_DIR (jax reads it itself) or `default_compile_cache()`.
    Every program is kept, unless $JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS says otherwise (jax's default
    keeps those taking a second to compile; a maze_eval run compiles ~440 programs, ~430 of them small ops
    outside jit: 10 s of a warm run on 2 CPU cores). None leaves: delete the folder to empty it. Returns the
    folder (None: off)."""
    if flag is not None and flag.strip().lower() == "none":
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    if flag is not None and not flag.strip():
        raise ConfigError("--compile-cache: give a folder, or 'none'")
    folder = Path(flag) if flag is not None else Path(os.environ.get(CACHE_ENV) or default_compile_cache())
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ConfigError(f"--compile-cache: cannot make {folder} ({error.strerror}); name another or 'none'") from None
    if jax.config.jax_compilation_cache_dir != str(folder):
        jax.config.update("jax_compilation_cache_dir", str(folder))
    if MIN_COMPILE_ENV not in os.environ:  # every program: hundreds of small ones cost seconds to compile
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_enable_compilation_cache", True)
    return folder


def join_processes(timeout: int) -> None:
    """`jax.distributed.initialize()` with the process count and index of `PROCESS_ENV` if set; ConfigError
    when the settings are missing or wrong. If not every process has joined after `timeout` seconds, one
    line on stderr and exit status 2 (a watcher thread: at its own deadline jax aborts the process). SIGTERM
    ends a joined process as it ends a lone one (jax's preemption service, which would catch it, stays off)."""
    if isinstance(timeout, bool) or not isinstance(timeout, int) or timeout < 1:
        raise ConfigError(f"--distributed-timeout must be an integer >= 1 (seconds), got {timeout!r}")
    count, index = (_env_int(name) for name in PROCESS_ENV)
    where = os.environ.get("JAX_COORDINATOR_ADDRESS", "the coordinator")
    joined = threading.Event()
    late = (f"error: --distributed: not every process joined {where} within {timeout} s (are all "
            f"{count or 'the'} processes started, each with its own process id?)\n")

    def watch() -> None:
        if not joined.wait(timeout):
            with contextlib.suppress(OSError):
                os.write(2, late.encode())
            os._exit(EXIT_BAD_INPUT)

    threading.Thread(target=watch, name="distributed-timeout", daemon=True).start()
    # jax's preemption service catches SIGTERM (to agree on a checkpoint step across hosts, which these commands
    # do not use): left on, a `kill` or a scheduler's SIGTERM would not stop the run
    jax.config.update("jax_enable_preemption_service", False)
    try:
        jax.distributed.initialize(num_processes=count, process_id=index,
                                   initialization_timeout=timeout + JOIN_GRACE_S)
    except (RuntimeError, ValueError, TypeError) as error:
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ConfigError(f"--distributed: {first} (under SLURM or Open MPI jax reads the settings from its "
                          f"environment; else set JAX_COORDINATOR_ADDRESS=host:port, {' and '.join(PROCESS_ENV)})") \
            from None
    finally:
        joined.set()


def _env_int(name: str) -> int | None:
    text = os.environ.get(name)
    if text is None:
        return None
    try:
        return int(text)
    except ValueError:
        raise ConfigError(f"--distributed: {name} must be an integer, got {text!r}") from None


def is_writer() -> bool:
    """Whether this process writes files (process 0 of a multi-host run, or the only one)."""
    return jax.process_index() == 0


def show_progress(args: argparse.Namespace) -> bool:
    """Whether this process draws progress bars: unless --no-progress, process 0 only."""
    return not args.no_progress and is_writer()


def add_training_flags(parser: argparse.ArgumentParser, presets, out_help: str, progress_help: str,
                       metavars: dict[str, str]) -> None:
    parser.add_argument("--preset", default="cpu", help=f"one of {', '.join(presets)} (default cpu)")
    parser.add_argument("--out", default=None, help=out_help)
    parser.add_argument("--resume", action="store_true", help="continue the run in --out")
    parser.add_argument("--no-progress", action="store_true", help=progress_help)
    parser.add_argument("--show-config", action="store_true", help="print the resolved configuration and exit")
    add_device_flags(parser)
    add_setting_flags(parser, metavars)


def train_command(module: str, args, argv, out: str, checkpoints: dict[str, str], keys, preset: Callable,
                  with_overrides: Callable, train: Callable, report: Callable) -> int:
    """train_flat's and train_hbr's run, within `interruptible`: `preset()` with the flags of `keys` and --set
    (on --resume, the run's solver settings unless given), then --show-config, or `train` and `report(outcome)`."""
    from hte_jax.sim.robot import stored_solver  # imports mujoco: not before a command needs it

    with interruptible(lambda: checkpoint_saved(out, checkpoints), resume_command(module, argv, out)):
        with input_errors() as errors:
            mesh = device_mesh(args)  # first: --distributed must start before jax touches the devices
            config = preset()
            overrides = setting_overrides(args, keys)
            if args.resume:
                overrides = {**stored_solver(resumable_run(out, checkpoints)), **overrides}
            config = with_overrides(config, overrides)
            if args.show_config:
                print(json.dumps(config.to_dict(), indent=2))
                return 0
            outcome = train(config, out, resume_run=args.resume, progress=show_progress(args), mesh=mesh)
        if errors.failed:
            return EXIT_BAD_INPUT
        if is_writer():
            report(outcome)
        return 0


class Interruption:
    """What the line Ctrl-C prints says. saved: what was written so far (None: nothing), or a function
    giving it, called from another thread (it must only read files). resume: the command that continues.
    The processes started with `start_child` end with the command."""

    def __init__(self, saved: str | Callable[[], str | None] | None = None, resume: str | None = None):
        self.saved = saved
        self.resume = resume
        self._children: list[subprocess.Popen] = []
        self._starting = threading.Lock()

    def start_child(self, command: list[str], **popen) -> subprocess.Popen:
        """`subprocess.Popen(command, **popen)`, a process that Ctrl-C ends too."""
        with self._starting:  # Ctrl-C meanwhile waits for it, then ends it
            child = subprocess.Popen(command, **popen)
            self._children.append(child)
        return child

    def end_children(self) -> None:
        """Terminate the processes `start_child` started; none starts after this (the command is ending)."""
        self._starting.acquire()
        for child in self._children:
            with contextlib.suppress(OSError):
                child.terminate()

    def line(self) -> str:
        try:
            saved = self.saved() if callable(self.saved) else self.saved
        except Exception as error:  # the line must come out, whatever the description's trouble
            saved = f"what was saved is unknown ({type(error).__name__}: {error})"
        if saved is None:
            return "interrupted: nothing written"
        return f"interrupted: {saved}" + (f"; resume with: {self.resume}" if self.resume else "")


@contextlib.contextmanager
def interruptible(saved: str | Callable[[], str | None] | None = None,
                  resume: str | None = None) -> Iterator[Interruption]:
    """Within the block, Ctrl-C prints `Interruption.line()` on stderr and ends the process with
    `EXIT_INTERRUPTED` at once. A Python signal handler only runs between bytecodes of the main thread,
    so the signal wakes a watcher thread (`signal.set_wakeup_fd`) that calls `os._exit` even while the
    main thread waits in a jitted call (checkpoints are written whole and renamed: an exit mid-write
    keeps the previous one). Outside the main thread the block runs unguarded."""
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
    """End the interruption's child processes, print its line and end the process now (stdout flushed first: a
    file or pipe keeps its lines)."""
    interruption.end_children()
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
    """For `--resume`, before any time is spent starting the run: the configuration of the run in `out`
    (ConfigError when out holds none, or when another process sees other files there); CheckpointError if one of
    its `checkpoints` is not a checkpoint."""
    require_same_run_folder(out)
    stored = stored_config(out)
    if stored is None:
        raise ConfigError(f"--resume: {out} holds no run to resume (no config.json); leave out --resume to start one")
    for name in checkpoints:
        if (Path(out) / name).exists():
            read_header(Path(out) / name)
    return stored


def checkpoint_saved(out: str | Path, checkpoints: dict[str, str]) -> str | None:
    """For `Interruption.saved`: the last of `checkpoints` ({file under out: what it holds, "" for the
    run itself}, in training order) that exists and its generation; None if `out` holds no run."""
    out = Path(out)
    if not (out / "config.json").is_file():
        return None
    for name, what in reversed(checkpoints.items()):
        if (out / name).is_file():
            with np.load(out / name) as data:
                generation = int(data["generation"])
            return f"checkpoint{' of ' + what if what else ''} at generation {generation} kept in {out}"
    return f"no checkpoint yet, the run's configuration kept in {out}"
