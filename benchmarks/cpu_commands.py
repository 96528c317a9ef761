"""How long do the README's CPU commands take, as a newcomer runs them?

Runs each command in order as its own subprocess with its defaults (`python -m experiments.<name>`
from a fresh working folder, so every `runs/...` default lands there, and this checkout's code
on PYTHONPATH), one after the other, and times it from start to exit, compilation included:

    maze_eval          python -m experiments.maze_eval
    train_hbr          python -m experiments.train_hbr                  (cpu preset)
    train_flat         python -m experiments.train_flat --variant 2d    (cpu preset)
    repertoire_stats   python -m experiments.repertoire_stats
    modulation         python -m experiments.modulation                 (cpu preset)
    render             python -m experiments.render skills

A command that exits non-zero (e.g. `render` where no OpenGL context starts) is recorded with its
exit status and the last line it printed, and the next one runs. Measure on a quiet machine: other
work on the cores lengthens every time (the load averages before and after each command are
recorded).

    python benchmarks/cpu_commands.py                                # all six, in a temporary folder
    python benchmarks/cpu_commands.py --commands modulation,render   # a subset
    python benchmarks/cpu_commands.py --work-dir runs/newcomer       # keep what the commands write
    python benchmarks/cpu_commands.py --help-only                    # each command's --help (a quick check)

Prints a table (command, wall seconds, CPU seconds of all its threads, exit status) and writes
JSON to benchmarks/results/ with the CPU model, core count and date.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import environment, result_path  # noqa: E402

# (name, arguments after `python -m`), in the README's order
COMMANDS = [
    ("maze_eval", ["experiments.maze_eval"]),
    ("train_hbr", ["experiments.train_hbr"]),
    ("train_flat", ["experiments.train_flat", "--variant", "2d"]),
    ("repertoire_stats", ["experiments.repertoire_stats"]),
    ("modulation", ["experiments.modulation"]),
    ("render", ["experiments.render", "skills"]),
]
NAMES = [name for name, _ in COMMANDS]


def _parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--commands", default=",".join(NAMES),
                   help=f"comma-separated subset, run in the order above (default: all of {', '.join(NAMES)})")
    p.add_argument("--work-dir", type=Path, default=None,
                   help="folder the commands run in and write to (default: a temporary folder, removed after)")
    p.add_argument("--help-only", action="store_true", help="run each command with --help instead (a quick check)")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds allowed per command (default 3600)")
    p.add_argument("--out", type=Path, default=None,
                   help="JSON path (default: results/cpu_commands_<device>_<date>.json)")
    args = p.parse_args(argv)
    chosen = [name.strip() for name in args.commands.split(",") if name.strip()]
    unknown = [name for name in chosen if name not in NAMES]
    if unknown or not chosen:
        p.error(f"--commands: unknown {unknown}; choose from {', '.join(NAMES)}")
    args.chosen = [name for name in NAMES if name in chosen]
    return args


def cpu_description() -> dict:
    """The CPU model and the cores this process may use."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.partition(":")[2].strip()
                break
    except OSError:
        pass
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu_model": model, "cpu_count": os.cpu_count(), "usable_cores": usable}


def last_line(text: str) -> str:
    """The last non-empty line a command printed (progress-bar redraws split at carriage returns)."""
    lines = [line.strip() for line in text.replace("\r", "\n").splitlines() if line.strip()]
    return lines[-1] if lines else ""


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_command(name: str, argv: list[str], cwd: Path, timeout: float, log: Path) -> dict:
    """Run argv in cwd with this checkout on PYTHONPATH, stdout and stderr into `log`; its wall time,
    CPU time (user + system, all threads), exit status (None on a timeout) and, when it failed, the
    last line it printed. The commands share a compilation cache in cwd/xla-cache, empty at first: a
    newcomer's cache."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
               JAX_COMPILATION_CACHE_DIR=str(cwd / "xla-cache"))
    load_before = os.getloadavg()[0]
    cpu_before = _children_cpu_s()
    began = time.perf_counter()
    with open(log, "w") as sink:
        proc = subprocess.Popen(argv, cwd=cwd, env=env, stdout=sink, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
        try:
            status = proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            status = None
    wall = time.perf_counter() - began
    cpu = _children_cpu_s() - cpu_before
    row = {"command": name, "argv": argv[1:], "wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "exit": status,
           "load_before": round(load_before, 2), "load_after": round(os.getloadavg()[0], 2)}
    if status is None:
        row["reason"] = f"timeout after {timeout:.0f} s"
    elif status != 0:
        row["reason"] = last_line(log.read_text(errors="replace")) or f"exit status {status}"
    return row


def main(argv=None):
    args = _parse(argv)
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # leave the device to the commands
    env = {**environment(), **cpu_description()}
    temporary = None
    if args.work_dir is None:
        temporary = tempfile.TemporaryDirectory(prefix="cpu_commands_")
        work = Path(temporary.name)
    else:
        work = args.work_dir.resolve()
    (work / "logs").mkdir(parents=True, exist_ok=True)
    print(f"{env['cpu_model']}, {env['usable_cores']} cores; commands run in {work}", flush=True)
    rows = []
    commands = dict(COMMANDS)
    for name in args.chosen:
        command = [sys.executable, "-m", *commands[name], *(["--help"] if args.help_only else [])]
        print(f"{name}: python {' '.join(command[1:])} ...", flush=True)
        rows.append(run_command(name, command, work, args.timeout, work / "logs" / f"{name}.log"))
        row = rows[-1]
        print(f"{name}: {row['wall_s']:.0f} s, exit {row['exit']}" + (f" ({row['reason']})" if "reason" in row else ""),
              flush=True)
    width = max(len("python " + " ".join(row["argv"])) for row in rows)
    print(f"\n{'command':<{width}} {'wall s':>8} {'cpu s':>8} {'exit':>5}  (load average before -> after)")
    for row in rows:
        command = "python " + " ".join(row["argv"])
        print(f"{command:<{width}} {row['wall_s']:>8.1f} {row['cpu_s']:>8.1f} {str(row['exit']):>5}  "
              f"({row['load_before']:.1f} -> {row['load_after']:.1f})" + (f"  {row['reason']}" if "reason" in row else ""))
    settings = {"commands": args.chosen, "help_only": args.help_only, "timeout_s": args.timeout,
                "work_dir": None if temporary else str(work)}
    out = args.out or result_path("cpu_commands" + ("_help" if args.help_only else ""), env)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"environment": env, "settings": settings, "rows": rows}, indent=2) + "\n")
    print(f"wrote {out}")
    if temporary is not None:
        temporary.cleanup()


if __name__ == "__main__":
    main()
