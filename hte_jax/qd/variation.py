"""Variation (sferes' operators): objects with `vary(key, draw_parents) -> (B, G)` children in [0, 1]."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp


def polynomial_mutation(key: jax.Array, genotypes: jax.Array, rate: float, eta: float) -> jax.Array:
    """sferes' polynomial mutation, gene-wise with probability `rate`, clipped to [0, 1]: the gene gets
    delta = (2r)^(1/(eta+1)) - 1 if r < 0.5 else 1 - (2(1-r))^(1/(eta+1)), r ~ U(0, 1) (range 1: no scaling)."""
    key_apply, key_r = jax.random.split(key)
    apply = jax.random.uniform(key_apply, genotypes.shape) < rate
    r = jax.random.uniform(key_r, genotypes.shape)
    power = 1.0 / (eta + 1.0)
    delta = jnp.where(r < 0.5, (2.0 * r) ** power - 1.0, 1.0 - (2.0 * (1.0 - r)) ** power)
    return jnp.clip(jnp.where(apply, genotypes + delta, genotypes), 0.0, 1.0)


def sbx_crossover(key: jax.Array, parents_a: jax.Array, parents_b: jax.Array, eta: float) -> jax.Array:
    """Simulated binary crossover (Deb & Agrawal), each gene with p = 0.5: (N, G) children in [0, 1]."""
    key_gene, key_u, key_side = jax.random.split(key, 3)
    u = jax.random.uniform(key_u, parents_a.shape)
    beta = jnp.where(u <= 0.5, (2.0 * u) ** (1.0 / (eta + 1.0)), (1.0 / (2.0 * (1.0 - u))) ** (1.0 / (eta + 1.0)))
    mean = 0.5 * (parents_a + parents_b)
    half_spread = 0.5 * beta * jnp.abs(parents_a - parents_b)
    side = jnp.where(jax.random.bernoulli(key_side, 0.5, parents_a.shape), 1.0, -1.0)
    child = mean + side * half_spread
    cross = jax.random.bernoulli(key_gene, 0.5, parents_a.shape)
    return jnp.clip(jnp.where(cross, child, parents_a), 0.0, 1.0)


@dataclasses.dataclass(frozen=True)
class SbxPolynomial:
    """MAP-Elites' variation (`MapElitesConfig`): a share `crossover_rate` of SBX crossovers (`eta_c`) of two
parents, then polynomial mutation (`mutation_rate`, `eta_m`) of every child."""

    mutation_rate: float
    eta_m: float
    crossover_rate: float
    eta_c: float

    @classmethod
    def from_config(cls, config) -> SbxPolynomial:
        return cls(config.mutation_rate, config.eta_m, config.crossover_rate, config.eta_c)

    def vary(self, key: jax.Array, draw_parents: Callable[[jax.Array], jax.Array]) -> jax.Array:
        key_sel, key_mate, key_cross, key_use, key_mut = jax.random.split(key, 5)
        parents = draw_parents(key_sel)
        if self.crossover_rate > 0:
            mates = draw_parents(key_mate)
            children = sbx_crossover(key_cross, parents, mates, self.eta_c)
            use = jax.random.uniform(key_use, (parents.shape[0], 1)) < self.crossover_rate
            parents = jnp.where(use, children, parents)
        return polynomial_mutation(key_mut, parents, self.mutation_rate, self.eta_m)
