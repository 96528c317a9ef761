"""The commands' shared error handling and Ctrl-C line (`experiments.cli`); `--resume` and
unreadable checkpoints through the commands."""

import numpy as np
import pytest

from experiments.cli import EXIT_BAD_INPUT, fail, input_errors
from hte_jax.errors import ConfigError
from hte_jax.qd.io import CheckpointError


def test_input_errors_become_one_line_and_exit_2(capsys):
    assert fail("--chunk must be >= 1, got 0") == EXIT_BAD_INPUT == 2
    for error in (ConfigError("seed must be an integer >= 0, got -1"),
                  CheckpointError("x.npz: no such checkpoint file")):
        with input_errors() as errors:
            raise error
        assert errors.failed
    with input_errors() as errors:
        pass
    assert not errors.failed
    assert capsys.readouterr() == ("", "error: --chunk must be >= 1, got 0\nerror: seed must be an integer >= 0, "
                                       "got -1\nerror: x.npz: no such checkpoint file\n")


def test_only_the_named_types_are_caught(capsys):
    with input_errors(OSError) as errors:
        open("/nonexistent/file")
    assert errors.failed and capsys.readouterr().err.startswith("error: [Errno 2]")
    with pytest.raises(ConfigError):
        with input_errors(CheckpointError):
            raise ConfigError("not caught")
    with pytest.raises(KeyError):
        with input_errors():
            raise KeyError("not input")
    assert capsys.readouterr().err == ""


def test_set_overrides_any_setting_by_its_dotted_key(capsys):
    """`--set KEY=VALUE` reaches nested settings by their dotted keys, as the flat flags reach them."""
    import json

    from experiments.cli import set_overrides
    from experiments.maze_eval import main as maze_main
    from experiments.train_hbr import main as hbr_main

    assert set_overrides(["planner.iterations=50", "variants=hte,rte", "spare="]) == {
        "planner.iterations": "50", "variants": "hte,rte", "spare": ""}
    with pytest.raises(ConfigError, match="expected KEY=VALUE"):
        set_overrides(["planner.iterations"])
    printed = []
    for args in (["--iterations", "50", "--solver-iterations", "2", "--reflex-tilt", "0.3"],
                 ["--set", "planner.iterations=50", "--set", "solver.solver_iterations=2", "--set", "reflex_tilt=0.3"]):
        assert maze_main([*args, "--show-config"]) == 0
        printed.append(json.loads(capsys.readouterr().out))
    assert printed[0] == printed[1] and printed[0]["iterations"] == 50 and printed[0]["solver_iterations"] == 2
    assert hbr_main(["--preset", "tiny", "--show-config", "--set", "top.eta_m=20"]) == 0
    assert json.loads(capsys.readouterr().out)["top"]["eta_m"] == 20.0
    assert maze_main(["--show-config", "--set", "planner.colour=1"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err == "error: unknown setting 'planner.colour'\n"


# --- Ctrl-C (the process-level behaviour: tests/test_interrupts.py) --------------------------


def test_the_interrupted_line_says_what_was_saved_and_how_to_resume():
    from experiments.cli import Interruption

    assert Interruption().line() == "interrupted: nothing written"
    assert Interruption(None, "python -m x --resume").line() == "interrupted: nothing written"  # nothing to resume
    assert Interruption("wrote a.json", None).line() == "interrupted: wrote a.json"
    saved = Interruption(lambda: "checkpoint at generation 3 kept in runs/x", "python -m x --out runs/x --resume")
    assert saved.line() == ("interrupted: checkpoint at generation 3 kept in runs/x; "
                            "resume with: python -m x --out runs/x --resume")

    def broken():
        raise OSError("disk gone")

    assert Interruption(broken).line() == "interrupted: what was saved is unknown (OSError: disk gone)"


def test_the_interruption_ends_the_processes_it_started():
    """What Ctrl-C does before its line: every process `start_child` started is terminated (one that ended
    already is left alone)."""
    import signal
    import subprocess
    import sys

    from experiments.cli import Interruption

    interruption = Interruption()
    done = interruption.start_child([sys.executable, "-c", "pass"])
    assert done.wait(timeout=60) == 0
    sleeping = interruption.start_child([sys.executable, "-c", "import time; time.sleep(600)"],
                                        stdout=subprocess.DEVNULL)
    interruption.end_children()
    assert sleeping.wait(timeout=60) == -signal.SIGTERM and done.returncode == 0


def test_the_resume_command_repeats_the_arguments_it_was_given():
    from experiments.cli import resume_command

    assert resume_command("experiments.train_hbr", [], "runs/hbr-cpu") == (
        "python -m experiments.train_hbr --out runs/hbr-cpu --resume")
    assert resume_command("experiments.train_hbr", ["--preset", "tiny", "--out", "my runs/a", "--resume"], "x") == (
        "python -m experiments.train_hbr --preset tiny --out 'my runs/a' --resume")
    assert resume_command("experiments.train_flat", ["--out=r", "--seed", "3"], "r") == (
        "python -m experiments.train_flat --out=r --seed 3 --resume")


def test_checkpoint_saved_reads_the_newest_checkpoint_of_a_run_folder(tmp_path):

    from experiments.cli import checkpoint_saved
    from hte_jax.qd.io import save_checkpoint

    checkpoints = {"bottom/checkpoint.npz": "layer bottom", "middle/checkpoint.npz": "layer middle"}
    assert checkpoint_saved(tmp_path / "absent", checkpoints) is None
    assert checkpoint_saved(tmp_path, checkpoints) is None  # no config.json: no run
    (tmp_path / "config.json").write_text("{}")
    assert checkpoint_saved(tmp_path, checkpoints) == f"no checkpoint yet, the run's configuration kept in {tmp_path}"
    save_checkpoint(tmp_path / "bottom" / "checkpoint.npz", {"generation": np.int32(8)})
    assert checkpoint_saved(tmp_path, checkpoints) == f"checkpoint of layer bottom at generation 8 kept in {tmp_path}"
    save_checkpoint(tmp_path / "middle" / "checkpoint.npz", {"generation": np.int32(2)})
    assert checkpoint_saved(tmp_path, checkpoints) == f"checkpoint of layer middle at generation 2 kept in {tmp_path}"
    assert checkpoint_saved(tmp_path, {"middle/checkpoint.npz": ""}) == f"checkpoint at generation 2 kept in {tmp_path}"


def test_interruptible_puts_the_signal_handling_back():
    import signal

    from experiments.cli import interruptible

    before, wakeup = signal.getsignal(signal.SIGINT), signal.set_wakeup_fd(-1)
    signal.set_wakeup_fd(wakeup)
    with interruptible("x") as interrupt:
        assert signal.getsignal(signal.SIGINT) is not before
        interrupt.saved = "y"
    assert signal.getsignal(signal.SIGINT) is before
    assert signal.set_wakeup_fd(wakeup) == wakeup


# --- --resume and unreadable checkpoints ----------------------------------------------------


@pytest.mark.parametrize("command", ["train_hbr", "train_flat", "train_spare"])
def test_resume_of_a_folder_without_a_run_is_refused(command, tmp_path, capsys):
    import importlib

    main = importlib.import_module(f"experiments.{command}").main
    for folder in (tmp_path / "absent", tmp_path):  # missing, and existing without a run
        assert main(["--preset", "tiny", "--out", str(folder), "--resume", "--no-progress"]) == EXIT_BAD_INPUT
        assert capsys.readouterr().err == (f"error: --resume: {folder} holds no run to resume (no config.json); "
                                           "leave out --resume to start one\n")
    assert not (tmp_path / "absent").exists() and not any(tmp_path.iterdir())
    (tmp_path / "config.json").write_bytes(b"\x00garbage")  # a damaged run folder
    assert main(["--preset", "tiny", "--out", str(tmp_path), "--resume", "--no-progress"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err.startswith(f"error: {tmp_path / 'config.json'} is not a run's configuration (not JSON")


def test_a_file_of_random_bytes_is_not_a_checkpoint(tmp_path, capsys):
    from experiments.inspect_checkpoint import main as inspect_main
    from experiments.train_hbr import main as hbr_main
    from hte_jax.hbr.training import preset
    from hte_jax.qd.io import save_checkpoint, write_json

    rng = np.random.default_rng(0)
    noise = tmp_path / "noise.npz"
    noise.write_bytes(rng.bytes(4096))
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    whole = tmp_path / "whole.npz"
    save_checkpoint(whole, {"a": np.arange(1000, dtype=np.float32)})
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(whole.read_bytes()[:600])
    expected = {noise: "not an hte-jax checkpoint (not an .npz archive)",
                empty: "not an hte-jax checkpoint (an empty file)",
                truncated: "not an hte-jax checkpoint, or a truncated or corrupt one (File is not a zip file)"}
    for path, message in expected.items():
        assert inspect_main([str(path)]) == EXIT_BAD_INPUT
        assert capsys.readouterr().err == f"error: {path}: {message}\n"

    run = tmp_path / "run"  # a tiny run whose bottom layer's checkpoint is noise
    (run / "bottom").mkdir(parents=True)
    write_json(run / "config.json", preset("tiny").to_dict())
    (run / "bottom" / "checkpoint.npz").write_bytes(noise.read_bytes())
    assert hbr_main(["--preset", "tiny", "--out", str(run), "--resume", "--no-progress"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err == (f"error: {run / 'bottom' / 'checkpoint.npz'}: "
                                       "not an hte-jax checkpoint (not an .npz archive)\n")
