"""Cheap analytic QD tasks for tests and demos. planar_arm (Cully et al. 2015): n joint angles, links 1/n long;
descriptor: the hand's position mapped to [0, 1]^2; fitness: minus the angles' standard deviation, in [-pi, 0]."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from hte_jax.qd.repertoire import Evaluation


def planar_arm(genotypes: jax.Array) -> Evaluation:
    """(B, n) genotypes in [0, 1] -> Evaluation with (B, 2) descriptors in [0, 1]."""
    angles = (genotypes - 0.5) * 2.0 * jnp.pi
    cumulative = jnp.cumsum(angles, axis=-1)
    length = 1.0 / genotypes.shape[-1]
    x = length * jnp.cos(cumulative).sum(axis=-1)
    y = length * jnp.sin(cumulative).sum(axis=-1)
    descriptors = (jnp.stack([x, y], axis=-1) + 1.0) / 2.0
    return Evaluation(fitnesses=-jnp.std(angles, axis=-1), descriptors=jnp.clip(descriptors, 0.0, 1.0),
                      valid=jnp.ones(genotypes.shape[0], bool))


def planar_arm_evaluate(key: jax.Array, genotypes: jax.Array) -> Evaluation:
    """`planar_arm` with the `evaluate(key, genotypes)` signature of the MAP-Elites loop."""
    del key  # deterministic task
    return planar_arm(genotypes)
