"""Arithmetic written once for jax and NumPy (`xp`) whose host (NumPy) values agree bit for bit with XLA's."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def quotient(x, y, xp=jnp):
    """x / y as XLA computes it: where y is broadcast to more elements, x times y's inverse (XLA's rewrite of a
    division by a broadcast value); else the plain division. Jax (xp=jnp) writes the plain division and leaves
    the rewrite to XLA; NumPy (xp=np) follows XLA, so the host and jax agree."""
    if xp is jnp or np.size(y) == np.prod(np.broadcast_shapes(np.shape(x), np.shape(y))):
        return x / y
    return x * (1 / y)
