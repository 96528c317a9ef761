"""XLA's CPU pool sized against the batched-factorisation deadlock (hte_jax/cpu_pool.py): the sizing rule, the
pool a process gets, the reproduction (`tests/cpu_pool_script.py`) looping to its end on 1 and 2 CPU devices,
and the mesh's refusal where jax started before hte_jax could size the pool."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from hte_jax import cpu_pool
from tests.processes import ROOT, cpu_devices_env

LOOPS = 20  # the unsized pool hung within 20 loops in 2 of 3 tries on 2 cores with 2 devices (a race)


def _run(code_or_module: list[str], devices: int, timeout: float, **extra: str) -> subprocess.CompletedProcess:
    env = cpu_devices_env(devices)
    env.pop(cpu_pool.POOL_VARIABLE, None)  # the pool as a fresh shell would size it
    return subprocess.run([sys.executable, *code_or_module], cwd=ROOT, env={**env, **extra}, capture_output=True,
                          text=True, timeout=timeout)


def test_cpu_device_count_reads_the_forced_devices():
    assert cpu_pool.cpu_device_count({}) == 1
    assert cpu_pool.cpu_device_count({"XLA_FLAGS": "--xla_force_host_platform_device_count=4"}) == 4
    last = "--xla_force_host_platform_device_count=2 --xla_cpu_use_fusion_emitters=false " \
           "--xla_force_host_platform_device_count=3"
    assert cpu_pool.cpu_device_count({"XLA_FLAGS": last}) == 3  # XLA keeps the last
    assert cpu_pool.cpu_device_count({"JAX_NUM_CPU_DEVICES": "6", "XLA_FLAGS": ""}) == 6


def test_size_pool_adds_a_thread_per_device_and_keeps_a_larger_setting():
    cores = os.cpu_count()
    environ = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert cpu_pool.size_pool(environ) == cores + 2 and environ["NPROC"] == str(cores + 2)
    environ = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2", "NPROC": "1"}
    assert cpu_pool.size_pool(environ) == cores + 2  # a too small pool is raised
    environ = {"NPROC": str(cores + 40)}
    assert cpu_pool.size_pool(environ) == cores + 40  # a larger one is kept


def test_a_process_that_imports_hte_jax_gets_the_sized_pool():
    code = "import hte_jax, jax; jax.devices(); from hte_jax import cpu_pool; print(cpu_pool.pool_threads())"
    done = _run(["-c", code], devices=2, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout.split()[-1]) == os.cpu_count() + 2


@pytest.mark.parametrize("devices", [1, 2])
@pytest.mark.slow
def test_the_batched_factorisation_finishes_on_cpu_devices(devices):
    """The reproduction, looping: without the sizing, 2 devices on 2 cores hang here (measured, docs/design.md)."""
    done = _run(["-m", "tests.cpu_pool_script", "--loops", str(LOOPS)], devices=devices, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().endswith(f"finished {LOOPS}")


def test_the_mesh_refuses_a_pool_jax_made_before_hte_jax_could_size_it():
    code = ("import jax; jax.devices()\n"
            "from hte_jax import sharding\n"
            "from hte_jax.errors import ConfigError\n"
            "try:\n    sharding.batch_mesh(2)\nexcept ConfigError as error:\n    print(error)\n")
    done = _run(["-c", code], devices=2, timeout=120, NPROC="2")
    assert done.returncode == 0, done.stderr[-2000:]
    assert "XLA's CPU pool has 2 threads for 2 CPU devices and can deadlock" in done.stdout
    assert f"NPROC={os.cpu_count() + 2}" in done.stdout
