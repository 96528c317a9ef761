"""`mujoco.mjx` without MJX's missing-warp notices (kept: `WARP_IMPORT_ERRORS`), and Warp's backend started quietly."""

from __future__ import annotations

import contextlib
import io
import os
import sys
import tempfile

from hte_jax import warp_calls
from hte_jax.errors import ConfigError, require_choice

WARP_NOTICES = ("Failed to import warp:", "Failed to import mujoco_warp:")
# The physics implementations MJX offers that the project runs (`RobotConfig.impl`).
IMPLS = ("jax", "warp")
WARP_EXTRA = 'pip install -e ".[warp]"'
# What Warp prints when it starts (device list, kernel cache, a CPU-only machine's missing CUDA driver).
_WARP_START = ("Warp ", "   ", "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver")

with contextlib.redirect_stdout(io.StringIO()) as _captured:
    from mujoco import mjx  # noqa: E402

WARP_IMPORT_ERRORS = tuple(line for line in _captured.getvalue().splitlines() if line.startswith(WARP_NOTICES))
_other = [line for line in _captured.getvalue().splitlines() if not line.startswith(WARP_NOTICES)]
if _other:
    print("\n".join(_other), file=sys.stdout)


def warp_installed() -> bool:
    """Whether MJX can run its Warp backend here (warp-lang and MJX's MuJoCo Warp both imported)."""
    from mujoco.mjx import warp as mjx_warp
    return bool(mjx_warp.WARP_INSTALLED) and mjx_warp.mujoco_warp is not None


def require_impl(impl: str) -> None:
    """ConfigError unless MJX's `impl` ("jax" or "warp") can run here; starts Warp quietly."""
    require_choice("impl", impl, IMPLS)
    if impl != "warp":
        return
    if not warp_installed():
        reason = WARP_IMPORT_ERRORS[0] if WARP_IMPORT_ERRORS else "MJX's Warp backend did not import"
        raise ConfigError(f"impl='warp' needs MJX's Warp backend, the warp extra: {WARP_EXTRA} ({reason})")
    _start_warp()


def _start_warp() -> None:
    """`warp.init()` with Warp's informational output off and its start notices dropped."""
    if warp_calls.started():
        return
    import warp
    warp.config.log_level = warp.LOG_WARNING  # no banner, no line per kernel module loaded
    with _native_output() as lines:
        warp.init()
    kept = [line for line in lines if line.strip() and not line.startswith(_WARP_START)]
    if kept:
        print("\n".join(kept), file=sys.stderr)
    warp_calls.mark_started()


@contextlib.contextmanager
def _native_output():
    """Collects the lines written to file descriptors 1 and 2 inside (native printf included)."""
    lines: list[str] = []
    sys.stdout.flush()
    sys.stderr.flush()
    saved = (os.dup(1), os.dup(2))
    with tempfile.TemporaryFile(mode="w+b") as sink:
        try:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            yield lines
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            for fd, saved_fd in zip((1, 2), saved):
                os.dup2(saved_fd, fd)
                os.close(saved_fd)
            sink.seek(0)
            lines.extend(sink.read().decode(errors="replace").splitlines())


__all__ = ["IMPLS", "WARP_EXTRA", "mjx", "require_impl", "warp_installed"]
