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
