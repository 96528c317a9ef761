"""`mujoco.mjx`, imported without its warp notice.

MJX 3.17 prints "Failed to import warp: ..." and "Failed to import mujoco_warp: ..." on stdout
whenever the optional warp-lang package is absent. We use MJX's JAX implementation only, so the
notice is noise a user cannot act on: those two lines are dropped; anything else the import prints
is passed on unchanged.
"""

from __future__ import annotations

import contextlib
import io
import sys

WARP_NOTICES = ("Failed to import warp:", "Failed to import mujoco_warp:")

with contextlib.redirect_stdout(io.StringIO()) as _captured:
    from mujoco import mjx  # noqa: E402

_other = [line for line in _captured.getvalue().splitlines() if not line.startswith(WARP_NOTICES)]
if _other:
    print("\n".join(_other), file=sys.stdout)

__all__ = ["mjx"]
