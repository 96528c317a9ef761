"""Fitting a GP kernel's hyper-parameters by maximising the log marginal likelihood of masked buffers
(issue 22; `docs/design.md`, Kernel fit). A researchers' tool: the online loop keeps the paper's kernel.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from hte_jax.errors import require_int, require_number
from hte_jax.online.gp import GPData, Kernel, covariance

NOISE_FLOOR = 1e-6  # the smallest observation noise a fit may reach (keeps the Cholesky factor finite)


@struct.dataclass
class KernelParams:
    """A kernel's free hyper-parameters, unconstrained: () float32 each."""

    log_length_scale: jax.Array
    log_variance: jax.Array
    log_noise: jax.Array

    @property
    def noise(self) -> jax.Array:
        return jnp.maximum(jnp.exp(self.log_noise), NOISE_FLOOR)


def kernel_params(kernel: Kernel) -> KernelParams:
    """The free parameters of `kernel` (its noise raised to the floor first)."""
    return KernelParams(log_length_scale=jnp.float32(math.log(kernel.length_scale)),
                        log_variance=jnp.float32(math.log(kernel.variance)),
                        log_noise=jnp.float32(math.log(max(kernel.noise, NOISE_FLOOR))))


def kernel_of(params: KernelParams, kind: str) -> Kernel:
    """The `Kernel` (Python floats) of concrete parameters."""
    return Kernel(kind, length_scale=float(jnp.exp(params.log_length_scale)),
                  variance=float(jnp.exp(params.log_variance)), noise=float(params.noise))


def log_marginal_likelihood(params: KernelParams, data: GPData, kind: str = "squared_exponential") -> jax.Array:
    """() log p(targets | inputs) of the filled rows of `data`, summed over its O outputs:
    sum_o -1/2 r_o^T K^-1 r_o - 1/2 log|K| - n/2 log 2 pi, r_o = targets_o - prior_o, K = k(X, X) + noise I."""
    with jax.default_matmul_precision("highest"):
        mask = data.mask
        length, variance, noise = jnp.exp(params.log_length_scale), jnp.exp(params.log_variance), params.noise
        pair = mask[:, None] & mask[None, :]
        gram = jnp.where(pair, covariance(kind, length, variance, data.inputs, data.inputs), 0.0)
        gram = gram + jnp.diag(jnp.where(mask, noise, 1.0))
        chol = jnp.linalg.cholesky(gram)
        residual = jnp.where(mask[:, None], data.targets - data.prior, 0.0)  # (N, O)
        whitened = jax.scipy.linalg.solve_triangular(chol, residual, lower=True)
        outputs = residual.shape[1]
        log_det = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))  # padded rows: log 1 = 0
        count = mask.sum().astype(jnp.float32)
        return -0.5 * jnp.sum(whitened * whitened) - 0.5 * outputs * (log_det + count * math.log(2.0 * math.pi))


def total_log_likelihood(params: KernelParams, data_batch: GPData, kind: str) -> jax.Array:
    """() the summed log marginal likelihood of E buffers (every field with a leading (E,) axis)."""
    return jax.vmap(log_marginal_likelihood, in_axes=(None, 0, None))(params, data_batch, kind).sum()


@functools.partial(jax.jit, static_argnames=("kind", "steps", "learning_rate"))
def _ascend(params: KernelParams, data_batch: GPData, kind: str, steps: int,
            learning_rate: float) -> tuple[KernelParams, jax.Array]:
    """`steps` Adam steps on the negative summed likelihood; the parameters and the likelihood trace (steps + 1,)."""
    optimizer = optax.adam(learning_rate)
    loss_and_grad = jax.value_and_grad(lambda p: -total_log_likelihood(p, data_batch, kind))

    def step(carry, _):
        params, state = carry
        loss, grad = loss_and_grad(params)
        updates, state = optimizer.update(grad, state, params)
        return (optax.apply_updates(params, updates), state), -loss

    (params, _), trace = jax.lax.scan(step, (params, optimizer.init(params)), None, length=steps)
    final = total_log_likelihood(params, data_batch, kind)
    return params, jnp.concatenate([trace, final[None]])


def fit_kernel(data_batch: GPData, initial: Kernel, steps: int = 200,
               learning_rate: float = 0.05) -> tuple[Kernel, np.ndarray]:
    """The kernel of `initial`'s kind maximising the summed log marginal likelihood of the E buffers
    `data_batch` (fields (E, N, ...)) after `steps` Adam steps, and the trace (steps + 1,) from `initial` on."""
    require_int("fit steps", steps)
    require_number("fit learning_rate", learning_rate, 0.0, open_low=True)
    if data_batch.mask.ndim != 2:
        raise ValueError(f"fit_kernel needs GPData with a leading batch axis (E, N); mask has shape {data_batch.mask.shape}")
    params, trace = _ascend(kernel_params(initial), data_batch, initial.kind, steps, float(learning_rate))
    return kernel_of(params, initial.kind), np.asarray(trace)
