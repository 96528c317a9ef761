"""XLA's CPU thread pool, sized so that several CPU devices cannot deadlock it.

jaxlib's batched LAPACK kernels on the CPU (the Cholesky of MJX's Newton solver, the GPs' factor)
split a large batch over XLA's intra-op thread pool and block the calling thread until the pieces
are done. XLA runs each CPU device's program on that same pool, whose size defaults to the number
of cores: with as many forced devices as cores, every pool thread can end up waiting for pieces no
thread is left to run, and the process sleeps forever (`tests/test_cpu_pool.py` reproduces it).
XLA sizes the pool from the NPROC environment variable when it is set; `size_pool` raises it to the
cores plus the CPU devices before jax starts its CPU client, so however many devices wait, a core's
worth of threads stays free. Importing `hte_jax` calls it: import it before jax touches a device.
"""

from __future__ import annotations

import os
import re

POOL_VARIABLE = "NPROC"  # read by XLA when it makes its CPU client's intra-op pool
THREAD_NAME = "tf_XLAEigen"  # that pool's threads, as Linux names them


def cpu_device_count(environ=os.environ) -> int:
    """The CPU devices jax will make: `--xla_force_host_platform_device_count` in XLA_FLAGS or
    JAX_NUM_CPU_DEVICES (the larger), else 1."""
    forced = re.findall(r"--xla_force_host_platform_device_count=(\d+)", environ.get("XLA_FLAGS", ""))
    counts = [int(n) for n in forced[-1:]]
    if environ.get("JAX_NUM_CPU_DEVICES", "").strip().isdigit():
        counts.append(int(environ["JAX_NUM_CPU_DEVICES"]))
    return max([1, *counts])


def pool_size(cores: int, devices: int) -> int:
    """Threads that keep `devices` device programs from taking the whole pool: the cores plus one per device."""
    return cores + devices


def size_pool(environ=os.environ) -> int:
    """Raise NPROC in `environ` to `pool_size` for this machine's cores and the CPU devices asked for
    (a larger NPROC is kept); returns it. Takes effect only before jax starts its CPU client."""
    needed = pool_size(os.cpu_count() or 1, cpu_device_count(environ))
    current = environ.get(POOL_VARIABLE, "").strip()
    size = max(needed, int(current)) if current.isdigit() else needed
    environ[POOL_VARIABLE] = str(size)
    return size


def pool_threads() -> int | None:
    """The threads of XLA's CPU pool in this process (Linux; None where threads cannot be listed)."""
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return None
    count = 0
    for task in tasks:
        try:
            with open(f"/proc/self/task/{task}/comm") as comm:
                count += comm.read().strip() == THREAD_NAME
        except OSError:
            continue
    return count
