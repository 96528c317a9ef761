"""Every command of `experiments/` end to end on 2 forced CPU devices (issue 36): `tests/commands_script.py`
runs them in ONE subprocess started with `XLA_FLAGS=--xla_force_host_platform_device_count=2` (so
every command uses both devices, as it would on a 2-GPU machine: a command that mixes arrays of one
device with arrays of the mesh fails here), each command's `main(argv)` in turn with tiny settings,
the later ones on what the earlier ones wrote; the tests below check each one's exit status and files.

Mostly XLA compiling the commands' MJX programs for 2 devices (in the suite's fast code generation,
tests/xla_codegen.py): about 6 minutes alone on a 2-core CPU (2026-11-27; train_hbr 1.7, maze_eval 1.2 with
its default cap of 80 actions per episode, in a maze built for it whose goal its episodes reach after
one action, train_flat aprol 0.8, modulation 0.6).
`render` runs only where a GL context starts (MUJOCO_GL egl, then osmesa); its test skips otherwise.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from hte_jax.online.evaluation import EvalConfig
from hte_jax.qd.io import read_checkpoint
from tests.commands_script import STEP_CHUNK
from tests.processes import ROOT, cpu_devices_env

# Its module fixture runs every command (minutes): the first test has more than the default 600 s. Group
# two_device_runs: test_distributed's one-process reference (2 forced devices) then loads this file's programs.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800), pytest.mark.xdist_group("two_device_runs")]
DEVICES = 2
# command -> files it writes, under the script's output folder
FLAT = ["config.json", "checkpoint.npz", "metrics.csv", "repertoires.npz", "summary.json", "plots"]
FILES = {
    "train_hbr": [f"train_hbr/{f}" for f in ("config.json", "summary.json", "hbr.npz", "bottom/checkpoint.npz",
                                             "middle/metrics.csv", "top/checkpoint.npz", "plots")],
    **{f"train_flat_{v}": [f"train_flat_{v}/{f}" for f in FLAT] for v in ("2d", "8d", "aprol")},
    "train_spare": [f"train_spare/{f}" for f in ("config.json", "middle/checkpoint.npz", "spare.npz", "summary.json")],
    "measure_steps": ["measure_steps/hbr.npz"],
    "maze_eval": [f"maze_eval/{f}" for f in ("config.json", "episodes.json", "summary.json", "statistics.json",
                                             "episodes_0.npz", "episodes_1.npz", "plots/fig6_actions.png")],
    "modulation": [f"modulation/{f}" for f in ("modulation.json", "modulation.npz", "modulation_map.png",
                                               "modulation_grid.png")],
    "repertoire_stats": ["repertoire_stats/table2.json", "repertoire_stats/table2.md"],
    "inspect_checkpoint": [],  # prints only
}


GL_PROBE = "import mujoco; c = mujoco.GLContext(8, 8); c.make_current(); c.free()"


def gl_backend() -> str | None:
    """The MUJOCO_GL under which a GL context starts here (egl, then osmesa), or None."""
    for backend in ("egl", "osmesa"):
        probe = subprocess.run([sys.executable, "-c", GL_PROBE], env=dict(os.environ, MUJOCO_GL=backend),
                               capture_output=True, timeout=120)
        if probe.returncode == 0:
            return backend
    return None


@pytest.fixture(scope="module")
def commands(tmp_path_factory):
    out = tmp_path_factory.mktemp("commands")
    backend = gl_backend()
    env = cpu_devices_env(DEVICES)
    if backend is not None:
        env["MUJOCO_GL"] = backend
    done = subprocess.run([sys.executable, "-m", "tests.commands_script", str(out), *(["--render"] if backend else [])],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=3600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-6000:]
    record = json.loads((out / "commands.json").read_text())
    assert record["devices"] == DEVICES
    return out, record["commands"], done.stdout + done.stderr


@pytest.mark.parametrize("name", list(FILES))
def test_the_command_runs_on_2_devices(commands, name):
    out, statuses, log = commands
    assert name in statuses, f"{name} did not run"
    assert statuses[name]["status"] == 0, f"{name} ended with {statuses[name]['status']}:\n{log[-4000:]}"
    for file in FILES[name]:
        assert (out / file).exists(), f"{name} wrote no {file}"


def test_render_runs_on_2_devices(commands):
    out, statuses, log = commands
    if "render" not in statuses:
        pytest.skip("no GL context starts here (MUJOCO_GL egl or osmesa: a GPU driver, Mesa's EGL or libosmesa6)")
    assert statuses["render"]["status"] == 0, log[-4000:]
    assert (out / "render" / "skills.gif").stat().st_size > 0


def test_the_hbr_was_trained_and_its_step_model_measured_in_several_blocks_on_2_devices(commands):
    out, _, _ = commands
    summary = json.loads((out / "train_hbr" / "summary.json").read_text())
    assert len(summary["devices"]) == DEVICES
    arrays, _ = read_checkpoint(out / "train_hbr" / "hbr.npz")
    samples = arrays["middle_slots"].size * summary["config"]["step_starts"]
    assert samples > 2 * STEP_CHUNK, f"{samples} step-model samples fit in fewer than 3 blocks of {STEP_CHUNK}"
    assert arrays["middle_step_mean"].shape == (arrays["middle_slots"].size, 3)
    measured = np.isfinite(arrays["middle_step_spread"])  # +inf: every start went invalid
    assert measured.any() and (arrays["middle_step_mean"][measured] != 0).any(axis=1).all()


def test_maze_eval_ran_several_episodes_under_the_default_action_cap(commands):
    """The shape that hung `maze_eval`'s defaults on 2 cores before their first action (issue 40):
    several episodes in one batch, each with the GP and planner sized by the default cap of 80
    actions, run to their end (in a maze whose goal holds the start: the first valid action reaches
    it, an invalid one ends the episode)."""
    out, _, _ = commands
    summary = json.loads((out / "maze_eval" / "summary.json").read_text())
    assert summary["max_actions"] == EvalConfig().max_actions == 80
    records = json.loads((out / "maze_eval" / "episodes.json").read_text())["episodes"]
    assert len(records) >= 3 and all(1 <= r["actions_taken"] <= 80 for r in records)
    assert {r["variant"] for r in records} == {"hte-spare", "rte-spare", "2d-rte"}
    assert all(r["reached"] or r["broken"] for r in records)
