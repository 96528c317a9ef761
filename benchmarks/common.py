"""Shared pieces of the benchmark scripts: the machine description, result paths, worker
subprocesses, earlier results and the random controllers the throughput benchmarks simulate."""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import subprocess
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def environment() -> dict:
    """Date, device, core count and library versions, recorded with every result."""
    import jax
    import mujoco

    device = jax.devices()[0]
    return {
        "date": dt.date.today().isoformat(),
        "device": device.device_kind,
        "platform": device.platform,
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "mujoco": mujoco.__version__,
    }


def run_worker(cmd: list[str], timeout: float, label: dict) -> dict:
    """Run a worker subprocess (no GPU preallocation) and return the last JSON line it printed;
    on a timeout or failure, `label` with an "error" saying what happened."""
    env = dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false")
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return {**label, "error": f"timeout after {timeout:.0f} s"}
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        return {**label, "error": f"exit {proc.returncode}: {' | '.join(tail)}"}
    return json.loads(lines[-1])


def earlier_result(path: str | Path, env: dict) -> dict:
    """An earlier result JSON measured on this run's device (SystemExit otherwise)."""
    earlier = json.loads(Path(path).read_text())
    if earlier["environment"]["device"] != env["device"]:
        raise SystemExit(f"{path} was measured on {earlier['environment']['device']}, not {env['device']}")
    return earlier


def result_path(name: str, env: dict) -> Path:
    """benchmarks/results/<name>_<platform>_<device>_<date>.json"""
    return RESULTS / f"{name}_{env['platform']}_{env['device'].replace(' ', '_')}_{env['date']}.json"


# A solver setting on the command line: "S/L" = solver_iterations/ls_iterations, then optional
# "@tol=T" (RobotConfig.solver_tolerance), "@dt=D" (RobotConfig.timestep) and "@impl=warp"
# (RobotConfig.impl, MJX's implementation; default jax), e.g. "2/4@dt=0.005", "4/4@impl=warp".
SETTING_KEYS = {"tol": "solver_tolerance", "dt": "timestep", "impl": "impl"}


def parse_setting(text: str) -> dict:
    """RobotConfig overrides of a setting string "S/L[@tol=T][@dt=D][@impl=I]" (ValueError if malformed)."""
    head, *extras = text.strip().split("@")
    solver, _, line_search = head.partition("/")
    if not solver.strip().isdigit() or not line_search.strip().isdigit():
        raise ValueError(f"setting {text!r}: expected S/L, e.g. 2/4, then optional @tol=T, @dt=D or @impl=I")
    overrides = {"solver_iterations": int(solver), "ls_iterations": int(line_search)}
    for extra in extras:
        key, _, value = extra.partition("=")
        if key.strip() not in SETTING_KEYS:
            raise ValueError(f"setting {text!r}: unknown key {key!r}; use {', '.join(SETTING_KEYS)}")
        name = SETTING_KEYS[key.strip()]
        overrides[name] = value.strip() if name == "impl" else float(value)
    return overrides


def setting_label(config) -> str:
    """The setting string of a RobotConfig: "S/L", with @tol / @dt / @impl where they differ from the defaults."""
    from hte_jax.sim.robot import RobotConfig

    label = f"{config.solver_iterations}/{config.ls_iterations}"
    for key, name in SETTING_KEYS.items():
        value = getattr(config, name)
        if value != getattr(RobotConfig, name):
            label += f"@{key}={value}" if isinstance(value, str) else f"@{key}={value:g}"
    return label


def random_params(batch: int, seed: int = 0):
    """(batch, 36) float32 controllers drawn uniformly: what batch_size.py and scaling.py simulate."""
    import numpy as np

    return np.random.default_rng(seed).uniform(size=(batch, 36)).astype(np.float32)
