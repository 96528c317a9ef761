"""Golden outputs: small arrays of three same-seed CPU runs, recorded before a refactor and
compared after it, so a change that should alter nothing provably alters nothing.

The runs (the same commands the test fixtures use):
- `train_hbr --preset tiny`: its `hbr.npz`;
- `train_flat --variant 8d --preset tiny`: its `repertoires.npz`;
- `maze_eval` (HTE and RTE, intact and leg 1, 30 actions, a small planner, the shipped
  repertoires): its `episodes_0.npz`.

Arrays are compared bit for bit, so they are only comparable on the toolchain they were recorded
with (jax, jaxlib, mujoco, numpy, CPU architecture and vector extensions: XLA's CPU code differs
between AVX2 and AVX-512 machines, and between CPU models of the same extensions). Each toolchain
gets its own folder, `tests/golden/<machine>-<vector>-<cpu model>/` with a `toolchain.json` (the
two folders without a CPU model were recorded before models were told apart and serve machines of
their vector extensions that have no folder of their own: where such a machine's run differs from them,
which another CPU model's code can cause, the check skips and says to record this CPU's folder); on a
machine with no matching folder, or other versions, the check skips and says so. Record on a new kind of machine, or re-record every folder after a change
that is meant to alter results (a new shipped HBR, a new default), with

    python -m tests.golden
"""

from __future__ import annotations

import importlib
import json
import platform
import shutil
import sys
import tempfile
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from hte_jax.qd.io import read_checkpoint

GOLDEN_DIR = Path(__file__).resolve().parent / "golden"
HBR_ARGS = ["--preset", "tiny", "--no-progress"]
FLAT_ARGS = ["--variant", "8d", "--preset", "tiny", "--no-progress"]
MAZE_ARGS = ["--variant", "hte,rte", "--damage", "none,leg1", "--replicates", "1", "--max-actions", "30",
             "--iterations", "200", "--roots", "2", "--no-progress"]
# golden name -> the run's output file it keeps
OUTPUTS = {"hbr_tiny": "hbr.npz", "flat8d_tiny": "repertoires.npz", "maze_short": "episodes_0.npz"}
# golden name -> (the command of experiments/ that makes it, its arguments)
RUNS = {"hbr_tiny": ("train_hbr", HBR_ARGS), "flat8d_tiny": ("train_flat", FLAT_ARGS), "maze_short": ("maze_eval", MAZE_ARGS)}
_VECTOR_FLAGS = ("avx512f", "avx2", "avx", "sse4_2", "neon", "asimd")


def toolchain() -> dict:
    """What bit-identical CPU results depend on besides our code."""
    versions = {name: metadata.version(name) for name in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "numpy")}
    flags, cpu = set(), {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            key = key.strip()
            if key in ("flags", "Features") and not flags:
                flags = set(value.split())
            elif key in ("vendor_id", "cpu family", "model") and key not in cpu:
                cpu[key] = value.strip()
    except OSError:
        pass
    vector = next((flag for flag in _VECTOR_FLAGS if flag in flags), "unknown")
    model = "-".join(cpu.get(k, "?") for k in ("vendor_id", "cpu family", "model"))
    return {**versions, "machine": platform.machine(), "vector": vector, "cpu": model}


def golden_dir(chain: dict) -> Path:
    """The folder holding the golden outputs of one toolchain: the one recorded on this CPU model
    if there is one (XLA's code also differs between CPUs of the same vector extensions: an AVX2
    AMD EPYC and the AVX2 machine of the first recording disagree), else the folder of its vector
    extensions recorded before CPU models were told apart."""
    exact = GOLDEN_DIR / f"{chain['machine']}-{chain['vector']}-{chain['cpu']}"
    legacy = GOLDEN_DIR / f"{chain['machine']}-{chain['vector']}"
    return legacy if not (exact / "toolchain.json").exists() and (legacy / "toolchain.json").exists() else exact


def arrays_of(path: Path) -> dict[str, np.ndarray]:
    """A checkpoint file's arrays (its metadata, which holds timings, left out)."""
    arrays, _ = read_checkpoint(path)
    return {name: np.asarray(value) for name, value in arrays.items() if name != "__metadata__"}


def check(name: str, run_dir: Path) -> None:
    """Assert that `run_dir`'s output equals the golden `name` array for array, bit for bit."""
    here = toolchain()
    folder = golden_dir(here)
    if not (folder / "toolchain.json").exists():
        recorded_on = ", ".join(sorted(p.name for p in GOLDEN_DIR.iterdir() if p.is_dir())) or "nothing"
        pytest.skip(f"no golden outputs for {folder.name} (recorded: {recorded_on}); record them: python -m tests.golden")
    recorded = json.loads((folder / "toolchain.json").read_text())
    compared = {k: v for k, v in here.items() if k in recorded}  # a folder recorded before "cpu" existed
    if recorded != compared:
        differ = ", ".join(f"{k} {recorded.get(k)} -> {here.get(k)}" for k in compared if recorded.get(k) != here.get(k))
        pytest.skip(f"golden outputs were recorded on another toolchain ({differ}); re-record: python -m tests.golden")
    golden = arrays_of(folder / f"{name}.npz")
    produced = arrays_of(run_dir / OUTPUTS[name])
    missing = sorted(set(golden) - set(produced))
    assert not missing, f"{name}: the run no longer writes {missing}"  # arrays added since are not compared
    shared_folder = "cpu" not in recorded  # recorded before CPU models were told apart, on a model not named
    for key, value in golden.items():
        assert produced[key].dtype == value.dtype and produced[key].shape == value.shape, f"{name}/{key}"
        if shared_folder and not np.array_equal(produced[key], value, equal_nan=True):
            pytest.skip(f"{name}/{key} differs from {folder.name}'s outputs, recorded on another CPU model than this "
                        f"{here['cpu']} (XLA's code differs between them): record this CPU's: python -m tests.golden")
        np.testing.assert_array_equal(produced[key], value, err_msg=f"{name}/{key} differs from the golden output")


def run(name: str, out: Path) -> int:
    """Make the run whose output golden `name` keeps (its command's `main`, in this process) in
    folder `out`; its exit status. The tests' fixtures compare these runs, `record` stores them."""
    command, args = RUNS[name]
    main = getattr(importlib.import_module(f"experiments.{command}"), "main")
    return main([*args, "--out", str(out)])


def run_fixture(name: str):
    """A module-scoped pytest fixture: the folder of `run(name)`, made once per test module (the
    test fails if the command does)."""

    @pytest.fixture(scope="module")
    def made(tmp_path_factory) -> Path:
        out = tmp_path_factory.mktemp(name) / "run"
        assert run(name, out) == 0, f"the {name} run failed"
        return out

    return made


def record() -> None:
    """Run the three commands and store their outputs and the toolchain in this toolchain's folder."""
    chain = toolchain()
    folder = GOLDEN_DIR / f"{chain['machine']}-{chain['vector']}-{chain['cpu']}"  # always this CPU model's own
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for name in RUNS:
            out = Path(tmp) / name
            if run(name, out) != 0:
                sys.exit(f"error: the {name} run failed; nothing recorded")
            shutil.copyfile(out / OUTPUTS[name], folder / f"{name}.npz")
    (folder / "toolchain.json").write_text(json.dumps(toolchain(), indent=2) + "\n")
    print(f"recorded {', '.join(OUTPUTS)} in {folder}")


if __name__ == "__main__":
    record()
