"""The commands' shared error handling (`experiments.cli`)."""

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
    assert hbr_main(["--preset", "tiny", "--show-config", "--set", "top.parents.selection=density"]) == 0
    assert json.loads(capsys.readouterr().out)["top"]["selection"] == "density"
    assert maze_main(["--show-config", "--set", "planner.colour=1"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err == "error: unknown setting 'planner.colour'\n"
