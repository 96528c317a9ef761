"""Gaussian processes on fixed-capacity, masked observation buffers (`docs/design.md`, GPs).

Padded rows are decoupled (zero covariance, unit diagonal), so the posterior is the unpadded GP's and
adding points never retraces; a full buffer overwrites its oldest observation. Outputs share one kernel.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from hte_jax.errors import check_fields, choice, number, require_int

KERNELS = ("squared_exponential", "matern52")


@dataclasses.dataclass(frozen=True)
class Kernel:
    """A stationary kernel k(a, b) = variance * f(|a - b| / length_scale), observation noise `noise`. kind:
    "squared_exponential" (limbo Exp: exp(-r^2 / 2)) or "matern52" ((1 + sqrt5 r + 5 r^2 / 3) exp(-sqrt5 r))."""

    kind: str = choice(dataclasses.MISSING, KERNELS)
    length_scale: float = number(low=0.0, open_low=True)
    variance: float = number(low=0.0, open_low=True)
    noise: float = number(low=0.0)

    def __post_init__(self):
        check_fields(self, "kernel ")

    def __call__(self, a: jax.Array, b: jax.Array) -> jax.Array:
        """(A, D), (B, D) -> (A, B) covariances."""
        diff = a[:, None, :] - b[None, :, :]
        r2 = jnp.sum(diff * diff, axis=-1) / self.length_scale**2
        if self.kind == "squared_exponential":
            return self.variance * jnp.exp(-0.5 * r2)
        r = jnp.sqrt(jnp.maximum(r2, 1e-30)) * (r2 > 0)
        s5r = jnp.sqrt(5.0) * r
        return self.variance * (1.0 + s5r + 5.0 * r2 / 3.0) * jnp.exp(-s5r)


# The two GPs of the paper (`docs/original_code.md` §7.1, §7.3).
RTE_KERNEL = Kernel("squared_exponential", length_scale=0.03, variance=0.01, noise=0.001)
HTE_KERNEL = Kernel("matern52", length_scale=1.0, variance=0.05, noise=0.001)


@struct.dataclass
class GPData:
    """Observations of a GP with N = capacity slots. inputs: (N, D) float32. targets: (N, O) float32.
    prior: (N, O) float32 prior mean at each input (ignored under the data mean). mask: (N,) bool filled
    slots. count: () int32 observations ever added (next slot = count % N)."""

    inputs: jax.Array
    targets: jax.Array
    prior: jax.Array
    mask: jax.Array
    count: jax.Array

    @property
    def capacity(self) -> int:
        return self.mask.shape[-1]


def empty_gp(capacity: int, input_dim: int, output_dim: int) -> GPData:
    require_int("GP capacity", capacity)
    return GPData(inputs=jnp.zeros((capacity, input_dim), jnp.float32),
                  targets=jnp.zeros((capacity, output_dim), jnp.float32),
                  prior=jnp.zeros((capacity, output_dim), jnp.float32), mask=jnp.zeros((capacity,), bool),
                  count=jnp.int32(0))


def add_observation(data: GPData, x: jax.Array, y: jax.Array, prior: jax.Array | None = None) -> GPData:
    """Add one observation x (D,), y (O,) with prior mean `prior` (O,) at x (default 0)."""
    slot = data.count % data.capacity
    prior = jnp.zeros_like(y) if prior is None else prior
    return data.replace(inputs=data.inputs.at[slot].set(x.astype(jnp.float32)),
                        targets=data.targets.at[slot].set(y.astype(jnp.float32)),
                        prior=data.prior.at[slot].set(prior.astype(jnp.float32)), mask=data.mask.at[slot].set(True),
                        count=data.count + 1)


def _factor_and_solve(gram: jax.Array, rhs: jax.Array) -> jax.Array:
    """L^-1 rhs (N, M) for the Cholesky factor L of gram (N, N)."""
    return jax.scipy.linalg.solve_triangular(jnp.linalg.cholesky(gram), rhs, lower=True)


@jax.custom_batching.custom_vmap
def whitened(gram: jax.Array, rhs: jax.Array) -> jax.Array:
    """L^-1 rhs (N, M) for the Cholesky factor L of gram (N, N); batched, the CPU solves one matrix at a time
    (batched LAPACK calls can hang a 2-core machine: `docs/design.md`, GPs)."""
    return _factor_and_solve(gram, rhs)


@whitened.def_vmap
def _whitened_batched(axis_size: int, in_batched: list[bool], gram: jax.Array, rhs: jax.Array):
    gram, rhs = (x if batched else jnp.broadcast_to(x, (axis_size, *x.shape))
                 for x, batched in zip((gram, rhs), in_batched))
    return jax.lax.platform_dependent(gram, rhs, cpu=lambda *pair: jax.lax.map(lambda one: whitened(*one), pair),
                                      default=jax.vmap(_factor_and_solve)), True


def posterior(kernel: Kernel, data: GPData, queries: jax.Array,
              query_prior: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """Posterior mean (Q, O) and variance (Q,) at queries (Q, D). query_prior (Q, O): the prior mean at the
    queries (`data.prior` at the observations); None: the observed targets' mean everywhere."""
    with jax.default_matmul_precision("highest"):
        mask = data.mask
        if query_prior is None:
            weight = data.mask.astype(jnp.float32)[:, None]
            constant = jnp.sum(data.targets * weight, axis=0) / jnp.maximum(weight.sum(), 1.0)  # (O,) (0 if empty)
            residual = data.targets - constant
            query_prior = jnp.broadcast_to(constant, (queries.shape[0], constant.shape[0]))
        else:
            residual = data.targets - data.prior
        gram = jnp.where(mask[:, None] & mask[None, :], kernel(data.inputs, data.inputs), 0.0)
        gram = gram + jnp.diag(jnp.where(mask, kernel.noise, 1.0))
        residual = jnp.where(mask[:, None], residual, 0.0)
        cross = jnp.where(mask[None, :], kernel(queries.astype(jnp.float32), data.inputs), 0.0)  # (Q, N)
        # With L L^T = K, the mean is prior + (L^-1 k)^T (L^-1 r) and the variance s^2 - |L^-1 k|^2.
        solved = whitened(gram, jnp.concatenate([residual, cross.T], axis=1))
        w, v = solved[:, : residual.shape[1]], solved[:, residual.shape[1]:]  # (N, O), (N, Q)
        mean, variance = query_prior + v.T @ w, kernel.variance - jnp.sum(v * v, axis=0)
    return mean, jnp.maximum(variance, 0.0)
