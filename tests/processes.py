"""The environment of a test's subprocess that runs on N forced CPU devices."""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def cpu_devices_env(devices: int, **extra: str) -> dict[str, str]:
    """This process's environment (the session's XLA_FLAGS kept) with `devices` forced CPU devices, the CPU
    platform, this checkout first on PYTHONPATH, and `extra`."""
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}"
    path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    return {**os.environ, "XLA_FLAGS": flags.strip(), "JAX_PLATFORMS": "cpu", "PYTHONPATH": path, **extra}
