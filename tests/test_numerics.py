"""Host (NumPy) arithmetic that agrees with XLA's bit for bit (hte_jax/numerics.py)."""

import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.numerics import quotient

pytestmark = pytest.mark.exact_numerics  # compares NumPy's bits with XLA's at its default code generation


@pytest.mark.parametrize("x_shape,y_shape", [((4000, 5), (4000, 1)), ((3, 4000), (4000,)), ((4000, 2), (2,)),
                                             ((4000,), (4000,)), ((1, 4000), (4000,)), ((4000, 1, 2), (4000, 1, 2))])
def test_quotient_on_the_host_is_xla_s_division(x_shape, y_shape):
    """XLA divides by a value broadcast to more elements as a product with its inverse, else exactly; `quotient`
    gives the same bits on the host, and jax's own division under xp=jnp."""
    rng = np.random.default_rng(0)
    x = rng.uniform(-5, 5, x_shape).astype(np.float32)
    y = rng.uniform(0.1, 5, y_shape).astype(np.float32)
    device = np.asarray(jnp.asarray(x) / jnp.asarray(y))
    host = quotient(x, y, np)
    assert host.dtype == device.dtype == np.float32 and host.tobytes() == device.tobytes()
    assert np.asarray(quotient(jnp.asarray(x), jnp.asarray(y))).tobytes() == device.tobytes()
