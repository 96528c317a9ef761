"""tests/golden.py's check on made-up folders: bit for bit against this CPU model's own folder; against a folder
recorded before CPU models were told apart, a difference skips (another CPU model's code can cause it) and names
the fix."""

import json

import numpy as np
import pytest

from hte_jax.qd.io import save_checkpoint
from tests import golden

CHAIN = {"jax": "1", "jaxlib": "1", "mujoco": "1", "mujoco-mjx": "1", "numpy": "1", "machine": "x86_64",
         "vector": "avx512f", "cpu": "Vendor-9-9"}


def _folder(root, name, chain, value):
    folder = root / name
    save_checkpoint(folder / "maze_short.npz", {"taken": np.array([value, 2.0], np.float32)})
    (folder / "toolchain.json").write_text(json.dumps(chain))


def _run(tmp_path, value):
    run = tmp_path / f"run{value}"
    save_checkpoint(run / golden.OUTPUTS["maze_short"], {"taken": np.array([value, 2.0], np.float32)})
    return run


def test_a_shared_folder_skips_on_a_difference_and_an_exact_folder_fails(tmp_path, monkeypatch):
    root = tmp_path / "golden"
    monkeypatch.setattr(golden, "GOLDEN_DIR", root)
    monkeypatch.setattr(golden, "toolchain", lambda: dict(CHAIN))
    shared = {k: v for k, v in CHAIN.items() if k != "cpu"}
    _folder(root, "x86_64-avx512f", shared, 1.0)
    golden.check("maze_short", _run(tmp_path, 1.0))  # the same bits: passes
    with pytest.raises(pytest.skip.Exception, match=r"maze_short/taken differs from x86_64-avx512f's outputs, "
                                                    r"recorded on another CPU model than this Vendor-9-9 .*"
                                                    r"record this CPU's: python -m tests.golden"):
        golden.check("maze_short", _run(tmp_path, 1.5))
    _folder(root, "x86_64-avx512f-Vendor-9-9", CHAIN, 1.0)  # this CPU model's own folder: a difference fails
    golden.check("maze_short", _run(tmp_path, 1.0))
    with pytest.raises(AssertionError, match="maze_short/taken differs from the golden output"):
        golden.check("maze_short", _run(tmp_path, 1.5))
