"""README.md runs as written: its set-up commands come first, and every ```python block, in order,
runs on its own in a fresh interpreter from the repository root (what a reader who pastes it does)
and prints what the README says it prints. Bash blocks are not run here (the CLIs have their own
tests). The subprocesses share the session's compilation cache (tests/conftest.py)."""

import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
NUMBER = r"(\d+(?:\.\d+)?)"


def run_block(index: int) -> str:
    """stdout of README block `index` run alone with `python -c`; fails the test on a non-zero exit."""
    proc = subprocess.run([sys.executable, "-c", BLOCKS[index]], cwd=ROOT, capture_output=True, text=True,
                          timeout=1200)
    assert proc.returncode == 0, f"README block {index + 1} failed:\n{proc.stderr[-4000:]}"
    return proc.stdout


def test_readme_commands_come_first():
    text = README.read_text()
    first_block = re.search(r"```bash\n(.*?)```", text, re.S).group(1).split("\n")
    assert first_block[:2] == ['pip install -e ".[dev]"', "pytest"]
    assert text.index("```bash") < text.index("```python")


def test_every_python_block_is_checked():
    # One test below per block: a block added to the README needs its own check here.
    assert len(BLOCKS) == 3


@pytest.mark.slow
def test_block_1_simulates_a_damaged_population():
    out = run_block(0)
    line = re.search(r"valid \(7,\) base_pos \(7, 4, 3\) foot_contacts \(7, 300, 6\) \| metres walked: \[(.*)\]", out)
    assert line, out
    walked = [float(w) for w in line.group(1).split(",")]
    assert len(walked) == 7 and all(0 <= w < 5 for w in walked)  # 3 s of walking: metres, not kilometres


@pytest.mark.slow
def test_block_2_runs_and_resumes_map_elites():
    began = time.time()
    out = run_block(1)
    line = re.search(r"generation 50: (\d+) of 1024 cells filled; the checkpoint resumes at generation 50", out)
    assert line, out
    assert 0 < int(line.group(1)) <= 1024
    for name in ("metrics.csv", "checkpoint.npz"):  # written by this run, under runs/ (ignored by git)
        path = ROOT / "runs" / "arm" / name
        assert path.stat().st_size > 0 and path.stat().st_mtime >= began - 1


@pytest.mark.slow
def test_block_3_executes_the_shipped_skills(xla_defaults):
    out = run_block(2)
    assert re.search(r"skills [1-9]\d* \| displacement \(7, 3\) \| middle elite per second \(3, 7\)", out), out
    intact = re.search(rf"intact robots end a median {NUMBER} m from the stored end", out)
    damaged = re.search(rf"damaged robots end a median {NUMBER} m from the stored end", out)
    assert intact and damaged, out
    # The skills replay where training stored them; the paper's damages push them off.
    assert float(intact.group(1)) < float(damaged.group(1))

