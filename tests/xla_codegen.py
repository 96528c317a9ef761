"""XLA's CPU code generation for the tests: `FAST`, the cheapest (the elemental fusion emitters and LLVM
without optimisation), or XLA's defaults.

Compiling MJX programs is most of the suite's time, and `FAST` takes about a third of it (a 300-step
batch rollout: 21 -> 8 CPU s on 2 cores) for code that runs up to ~4x slower, which tests at tiny sizes
barely feel. It changes the bits of floating-point results (~1e-5 in a rollout), so tests that compare
bits with golden outputs or between two differently compiled paths compile at XLA's defaults (the
`exact_numerics` marker: tests/conftest.py calls `use` before each test).

Processes the tests start read the choice from XLA_FLAGS (public, read once per process). Within the
pytest process XLA keeps the flags it started with (the user's), so the choice is made per program: the
options `jax.jit(...).lower(...).compile(compiler_options=...)` gives one program, given to every program
compiled. That needs jax's private compile-options hook, used here alone (`install`);
`tests/test_xla_codegen.py` checks that it still applies.
"""

from __future__ import annotations

import contextlib
import os

import jax
import jax.numpy as jnp

FAST = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 0}
USER_FLAGS = os.environ.get("XLA_FLAGS", "")  # as this process started: XLA's own flags here
_overrides: dict = {}  # what every program compiled in this process gets, beside its own options
_installed = False
_fast: bool | None = None  # what `use` last chose


def with_flags(flags: str, options: dict) -> str:
    """XLA_FLAGS `flags` plus `options` as flags."""
    return " ".join([*flags.split(), *(f"--{name}={str(value).lower()}" for name, value in options.items())])


def set_overrides(options: dict) -> None:
    """Every program this process compiles from now on gets the XLA `options` (after `install`)."""
    global _overrides
    _overrides = dict(options)


def overrides() -> dict:
    """The options of `set_overrides`."""
    return dict(_overrides)


def installed() -> bool:
    """Whether `install` has wrapped jax's hook in this process."""
    return _installed


def install() -> bool:
    """Wrap jax's private `jax._src.compiler.get_compile_options` (what every compilation of this process
    asks for its options) so that the options of `set_overrides` join each program's own (a program's own
    options, `compiler_options=`, win). Done once; False, changing nothing, where this jax has no such
    function or its XLA rejects an option of `FAST` (checked through the public per-program options)."""
    from jax._src import compiler

    global _installed
    get = getattr(compiler, "get_compile_options", None)
    if get is None:
        return False
    if _installed:
        return True
    try:
        jax.jit(lambda x: x + 1).lower(jnp.ones(2)).compile(compiler_options=FAST)
    except Exception:  # an option this XLA does not know
        return False

    def get_compile_options(*args, **kwargs):
        options = get(*args, **kwargs)
        own = dict(options.env_option_overrides)  # a program's own options come first
        options.env_option_overrides = [*own.items(), *((k, v) for k, v in _overrides.items() if k not in own)]
        return options

    compiler.get_compile_options = get_compile_options
    _installed = True
    return True


def use(fast: bool) -> None:
    """Compile from now on, in this process and in the processes it starts, with `FAST` (where `install`
    worked) or at XLA's defaults. Programs held in memory are dropped on a change, so that none compiled
    one way runs where the other is asked for (the persistent cache keys them apart)."""
    global _fast
    fast = fast and _installed
    if _fast == fast:
        return
    jax.clear_caches()
    set_overrides(FAST if fast else {})
    os.environ["XLA_FLAGS"] = with_flags(USER_FLAGS, FAST if fast else {})
    _fast = fast


@contextlib.contextmanager
def at_defaults():
    """XLA's default code generation within, whatever the running test's: for a computation at a real size
    in a fast test, where the fast code's run time costs more than its compile time saves."""
    saved = _fast
    use(False)
    try:
        yield
    finally:
        if saved is not None:
            use(saved)
