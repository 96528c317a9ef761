"""Python's garbage collector paused while Warp's calls run: `warp_calls()` around device work that may call MJX's
Warp backend, and `waited(fn, ...)`: a call whose device work is waited for inside it.

Each call of Warp's JAX FFI wraps XLA's CUDA stream in a `warp.Stream` (registering the stream) and captures a
graph on it. A wrapper left in a reference cycle by an earlier call is finalised by whichever collection comes
next, which unregisters the stream; a collection inside a later call, between its registration and its capture,
fails the capture ("Warp error: unknown stream": seen on first runs with Warp's kernels being built, and gone
with the pause; docs/design.md). Inside `warp_calls()` no collection runs; outside, collections run as usual.
Kept free of MuJoCo so that the QD loop can use it."""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Callable, Iterator
from typing import Any

import jax

_started = False


def started() -> bool:
    """Whether Warp's backend started in this process."""
    return _started


def mark_started() -> None:
    """Warp's backend started in this process (`sim.mjx_import.require_impl`): `warp_calls()` pauses collection."""
    global _started
    _started = True


@contextlib.contextmanager
def warp_calls() -> Iterator[None]:
    """The cyclic garbage collector off inside once Warp's backend started (a no-op before); wait for the device
    work inside."""
    pause = _started and gc.isenabled()
    if pause:
        gc.disable()
    try:
        yield
    finally:
        if pause:
            gc.enable()


def waited(fn: Callable[..., Any], *args, **kwargs) -> Any:
    """`fn(*args, **kwargs)` (device work, which may run Warp's calls) with its result waited for inside
    `warp_calls()`."""
    with warp_calls():
        return jax.block_until_ready(fn(*args, **kwargs))
