"""The README's example runs as written and returns what it says."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_commands_come_first():
    text = README.read_text()
    first_block = re.search(r"```bash\n(.*?)```", text, re.S).group(1).split("\n")
    assert first_block[:2] == ['pip install -e ".[dev]"', "pytest"]


def test_readme_examples_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the examples write under ./runs
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert len(blocks) == 3
    namespace = {}
    for code in blocks:
        exec(compile(code, str(README), "exec"), namespace)
    result = namespace["result"]
    assert result.valid.shape == (7,)
    assert result.base_pos.shape == (7, 4, 3)
    assert result.foot_contacts.shape == (7, 300, 6)
    assert namespace["start"].qpos.shape == (7, 25)
    assert int(namespace["state"].generation) == 50
    assert namespace["skill"].displacement.shape == (7, 3)
    assert namespace["skill"].steps.middle_index.shape == (3, 7)
    assert namespace["intact"].shape == (7, 2)
    for name in ("metrics.csv", "checkpoint.npz", "grid.png", "metrics.png"):
        assert (tmp_path / "runs" / "arm" / name).stat().st_size > 0
