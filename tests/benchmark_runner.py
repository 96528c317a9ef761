"""Runs a benchmark script at tiny sizes (shared by the benchmark-script tests): in this process
(`run_benchmark`: its `main(argv)`, as `python benchmarks/<script> <args>` runs it, without starting
another interpreter and with this process's compiled programs), or in a subprocess where the script
must start its own process (`run_benchmark_process`: `render_speed.py` sets MUJOCO_GL before mujoco
is imported). Scripts that time a fresh process (a batch size, a setting, a load) start their own
workers either way."""

import contextlib
import importlib.util
import io
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"


def run_benchmark(script, *args):
    """stdout of benchmarks/<script>'s `main([*args])` run in this process; fails the test with the
    script's output if it exits non-zero. The environment is restored afterwards (scripts set
    defaults such as XLA_PYTHON_CLIENT_PREALLOCATE for their workers)."""
    module = benchmark_module(Path(script).stem)
    environ = dict(os.environ)
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                status = module.main(list(args))
            except SystemExit as stop:
                status = stop.code
    finally:
        os.environ.clear()
        os.environ.update(environ)
    assert status in (None, 0), f"{script} exited with {status}:\n{out.getvalue()[-2000:]}\n{err.getvalue()[-2000:]}"
    return out.getvalue()


def run_benchmark_process(script, *args, env=None):
    """stdout of `python benchmarks/<script> <args>` (this environment updated with `env`); fails the test with
    its stderr if it exits non-zero."""
    proc = subprocess.run([sys.executable, str(BENCHMARKS / script), *args], cwd=ROOT, env={**os.environ, **(env or {})},
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def benchmark_module(name):
    """benchmarks/<name>.py imported as a module (the scripts are not a package; they import their
    shared `common` module from their own folder, which is put on sys.path as running them does)."""
    if str(BENCHMARKS) not in sys.path:
        sys.path.append(str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(f"benchmarks_{name}", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
