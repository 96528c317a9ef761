"""Shared pieces of the benchmark scripts: the machine description and result paths."""

from __future__ import annotations

import datetime as dt
import os
import platform
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def environment() -> dict:
    """Date, device, core count and library versions, recorded with every result."""
    import jax
    import mujoco

    device = jax.devices()[0]
    return {
        "date": dt.date.today().isoformat(),
        "device": device.device_kind,
        "platform": device.platform,
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "mujoco": mujoco.__version__,
    }


def result_path(name: str, env: dict) -> Path:
    """benchmarks/results/<name>_<platform>_<device>_<date>.json"""
    return RESULTS / f"{name}_{env['platform']}_{env['device'].replace(' ', '_')}_{env['date']}.json"
