"""What the command-line tools share: bad input becomes one `error: ...` line on stderr and exit status 2.

    with input_errors() as errors:  # ConfigError or CheckpointError; input_errors(OSError) catches OSError only
        ...
    if errors.failed:
        return 2

    return fail("--chunk must be >= 1, got 0")  # prints the line, returns 2

    add_set_flag(parser)  # --set KEY=VALUE, repeatable: any setting by its dotted key
    overrides.update(set_overrides(args.set))
"""

from __future__ import annotations

import argparse
import sys

from hte_jax.errors import ConfigError
from hte_jax.qd.io import CheckpointError

EXIT_BAD_INPUT = 2
INPUT_ERRORS = (ConfigError, CheckpointError)


def fail(message) -> int:
    """Print `error: message` on stderr; the exit status of a run refused for bad input."""
    print(f"error: {message}", file=sys.stderr)
    return EXIT_BAD_INPUT


def input_errors(*types: type[BaseException]) -> InputErrors:
    """A context manager that reports an exception of `types` (default `INPUT_ERRORS`) with `fail`
    and swallows it; its `failed` then tells the caller to return `EXIT_BAD_INPUT`. Others propagate."""
    return InputErrors(types or INPUT_ERRORS)


class InputErrors:
    """See `input_errors`."""

    def __init__(self, types: tuple[type[BaseException], ...]):
        self.types = types
        self.failed = False

    def __enter__(self) -> InputErrors:
        return self

    def __exit__(self, kind, error, traceback) -> bool:
        if error is None or not isinstance(error, self.types):
            return False
        fail(error)
        self.failed = True
        return True


def add_set_flag(parser: argparse.ArgumentParser) -> None:
    """`--set KEY=VALUE` (repeatable): override any setting by its key, dotted through nested
    configurations (`config.with_overrides`); applied after the setting flags."""
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a setting by its key, dotted through nested configurations "
                             "(planner.iterations=50, solver.ls_iterations=8, top.parents.selection=density); repeatable")


def set_overrides(items: list[str]) -> dict[str, str]:
    """The overrides of `--set` items "KEY=VALUE" (ConfigError if one has no "=" or no key)."""
    overrides = {}
    for item in items:
        key, equals, value = item.partition("=")
        if not equals or not key.strip():
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. seed=3")
        overrides[key.strip()] = value
    return overrides
