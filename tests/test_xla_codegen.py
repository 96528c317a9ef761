"""The suite's two XLA code generations (tests/xla_codegen.py) reach XLA: a test that is not marked
`exact_numerics` compiles as `compiler_options=FAST` compiles one program, one that is compiles as XLA's
defaults do, and a process started from a fast test reads FAST from XLA_FLAGS. If jax drops or changes the
private hook, these fail (the suite then compiles at the defaults throughout: correct, about 1.5x slower)."""

import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests import xla_codegen

ROOT = Path(__file__).resolve().parents[1]


def _f(x):
    """tanh and rsqrt: the fast options change the last bits of both (the elemental emitters, LLVM -O0)."""
    return jnp.tanh(x) + jax.lax.rsqrt(jnp.abs(x) + 1.0)


X = np.linspace(-20.0, 20.0, 100_001, dtype=np.float32)


def _public(options) -> np.ndarray:
    """`_f(X)` compiled with `options` through the public per-program argument alone (XLA's defaults for {})."""
    saved = xla_codegen.overrides()
    xla_codegen.set_overrides({})
    try:
        return np.asarray(jax.jit(_f).lower(X).compile(compiler_options=options)(X))
    finally:
        xla_codegen.set_overrides(saved)


def test_a_test_compiles_with_the_fast_options():
    assert xla_codegen.installed(), "jax's compile-options hook is gone: the suite compiles at XLA's defaults"
    fast, defaults = _public(xla_codegen.FAST), _public({})
    if np.array_equal(fast, defaults):
        pytest.skip("the fast options give XLA's default bits for tanh and rsqrt on this CPU: nothing tells them apart")
    np.testing.assert_array_equal(np.asarray(jax.jit(lambda x: _f(x))(X)), fast)
    assert xla_codegen.overrides() == xla_codegen.FAST
    assert xla_codegen.with_flags("", xla_codegen.FAST) in os.environ["XLA_FLAGS"]


@pytest.mark.exact_numerics
def test_an_exact_numerics_test_compiles_at_xla_defaults():
    defaults = _public({})
    assert xla_codegen.overrides() == {}
    if np.array_equal(defaults, _public(xla_codegen.FAST)):
        pytest.skip("the fast options give XLA's default bits for tanh and rsqrt on this CPU: nothing tells them apart")
    np.testing.assert_array_equal(np.asarray(jax.jit(lambda x: _f(x))(X)), defaults)
    assert "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", "")


def test_a_started_process_compiles_with_the_fast_flags():
    """XLA_FLAGS, what a command started by a test reads, gives what the fast options give."""
    script = "import sys, jax; from tests.test_xla_codegen import X, _f; sys.stdout.buffer.write(jax.jit(_f)(X).tobytes())"
    child = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=300, cwd=ROOT,
                           env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert child.returncode == 0, child.stderr.decode()[-2000:]
    np.testing.assert_array_equal(np.frombuffer(child.stdout, np.float32), _public(xla_codegen.FAST))
