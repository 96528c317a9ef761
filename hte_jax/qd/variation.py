"""Parent selection and variation operators on genotypes in [0, 1] (sferes conventions)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from hte_jax.qd.repertoire import Repertoire


def uniform_selection(key: jax.Array, repertoire: Repertoire, num: int) -> jax.Array:
    """(num,) slots drawn uniformly, with replacement, among the filled ones.

    Draws a rank r in [0, filled count) and returns the slot of the r-th filled slot
    (O(capacity + num log capacity), whatever the capacity). An empty repertoire has nothing
    to select: the caller must fill it first (MAP-Elites' initial random batch does).
    """
    return _uniform_among(key, repertoire.filled, num)


def _uniform_among(key: jax.Array, mask: jax.Array, num: int) -> jax.Array:
    """(num,) slots drawn uniformly, with replacement, among those where `mask` (C,) is True."""
    cumulative = jnp.cumsum(mask, dtype=jnp.int32)
    rank = jax.random.randint(key, (num,), 0, jnp.maximum(cumulative[-1], 1))
    return jnp.searchsorted(cumulative, rank + 1, side="left").astype(jnp.int32)


def density_selection(
    key: jax.Array, repertoire: Repertoire, num: int, low: jax.Array, high: jax.Array, bins: int, dims: int
) -> jax.Array:
    """(num,) filled slots drawn with replacement, each with probability proportional to 1 / (the
    number of elites in its coarse cell): every occupied cell of a `bins`^`dims` grid over the
    first `dims` descriptor dimensions (bounds low, high) is equally likely, then an elite within it.

    Elites in sparsely filled regions, such as the frontier of what the layer can do, are picked
    more often than under uniform selection, where densely filled regions (many elites with the
    same primary descriptor and other secondary ones) take most offspring.
    """
    low, high = jnp.asarray(low, jnp.float32)[:dims], jnp.asarray(high, jnp.float32)[:dims]
    scaled = (repertoire.descriptors[:, :dims] - low) / (high - low)
    index = jnp.clip(jnp.floor(scaled * bins), 0, bins - 1).astype(jnp.int32)
    cell = jnp.ravel_multi_index(tuple(index.T), (bins,) * dims, mode="clip")
    counts = jax.ops.segment_sum(repertoire.filled.astype(jnp.float32), cell, num_segments=bins**dims)
    weight = jnp.where(repertoire.filled, 1.0 / jnp.maximum(counts[cell], 1.0), 0.0)
    cumulative = jnp.cumsum(weight)
    draw = jax.random.uniform(key, (num,)) * cumulative[-1]
    slot = jnp.searchsorted(cumulative, draw, side="right")  # the first slot whose weight covers the draw
    last = repertoire.filled.shape[0] - 1 - jnp.argmax(repertoire.filled[::-1])  # float round-up guard
    return jnp.minimum(slot, last).astype(jnp.int32)


def frontier_elites(
    repertoire: Repertoire, low: jax.Array, high: jax.Array, angle_bins: int, level_bins: int
) -> jax.Array:
    """(C,) bool: the elites farthest from the centre of the plane of descriptor dimensions 0 and 1.

    Descriptors are scaled to [0, 1] by (low, high); the plane around (0.5, 0.5) is cut into
    `angle_bins` equal sectors and, when the container has a third dimension, its range into
    `level_bins` equal levels. In every occupied (sector, level) cell the elite at the largest
    distance from the centre is marked (ties to the lowest slot). For displacement descriptors
    (x, y[, yaw]) these are the fastest motions in every direction [at every turn rate]: the
    outer shell of what the repertoire can do.
    """
    low, high = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
    scaled = (repertoire.descriptors - low) / (high - low)
    offset = scaled[:, :2] - 0.5
    radius = jnp.linalg.norm(offset, axis=-1)
    angle = jnp.arctan2(offset[:, 1], offset[:, 0])  # (-pi, pi]
    sector = jnp.clip(jnp.floor((angle + jnp.pi) / (2 * jnp.pi) * angle_bins), 0, angle_bins - 1).astype(jnp.int32)
    if scaled.shape[1] > 2 and level_bins > 1:
        level = jnp.clip(jnp.floor(scaled[:, 2] * level_bins), 0, level_bins - 1).astype(jnp.int32)
    else:
        level = jnp.zeros_like(sector)
    cell = sector * level_bins + level
    cells = angle_bins * level_bins
    radius = jnp.where(repertoire.filled, radius, -1.0)
    farthest = jax.ops.segment_max(radius, cell, num_segments=cells)
    slots = jnp.arange(radius.shape[0], dtype=jnp.int32)
    is_max = repertoire.filled & (radius == farthest[cell])
    first = jax.ops.segment_min(jnp.where(is_max, slots, radius.shape[0]), cell, num_segments=cells)
    return repertoire.filled & (slots == first[cell])


def frontier_selection(
    key: jax.Array,
    repertoire: Repertoire,
    num: int,
    low: jax.Array,
    high: jax.Array,
    angle_bins: int,
    level_bins: int,
    fraction: float,
) -> jax.Array:
    """(num,) filled slots: the first round(fraction * num) drawn uniformly among the
    `frontier_elites`, the rest uniformly among all elites (with replacement).

    Uniform selection gives the few elites on the edge of the descriptor space a tiny share of
    the offspring, so the edge moves outwards by novelty alone, slowly. Here a fixed share of
    every batch is spent on exactly those elites; the rest keeps filling the interior.
    """
    edge = min(num, int(round(fraction * num)))
    key_edge, key_rest = jax.random.split(key)
    mask = frontier_elites(repertoire, low, high, angle_bins, level_bins)
    return jnp.concatenate(
        [_uniform_among(key_edge, mask, edge), _uniform_among(key_rest, repertoire.filled, num - edge)]
    )


def polynomial_mutation(key: jax.Array, genotypes: jax.Array, rate: float, eta: float) -> jax.Array:
    """sferes' polynomial mutation, gene-wise with probability `rate`, then clipped to [0, 1].

    delta = (2r)^(1/(eta+1)) - 1 if r < 0.5 else 1 - (2(1-r))^(1/(eta+1)), r ~ U(0, 1),
    added to the gene (the genes' range is 1, so delta needs no scaling).
    """
    key_apply, key_r = jax.random.split(key)
    apply = jax.random.uniform(key_apply, genotypes.shape) < rate
    r = jax.random.uniform(key_r, genotypes.shape)
    power = 1.0 / (eta + 1.0)
    delta = jnp.where(r < 0.5, (2.0 * r) ** power - 1.0, 1.0 - (2.0 * (1.0 - r)) ** power)
    return jnp.clip(jnp.where(apply, genotypes + delta, genotypes), 0.0, 1.0)


def sbx_crossover(key: jax.Array, parents_a: jax.Array, parents_b: jax.Array, eta: float) -> jax.Array:
    """Simulated binary crossover (Deb & Agrawal), one child per pair, each gene with p = 0.5.

    Args: parents (N, G) in [0, 1]. Returns: (N, G) children clipped to [0, 1].
    """
    key_gene, key_u, key_side = jax.random.split(key, 3)
    u = jax.random.uniform(key_u, parents_a.shape)
    beta = jnp.where(u <= 0.5, (2.0 * u) ** (1.0 / (eta + 1.0)), (1.0 / (2.0 * (1.0 - u))) ** (1.0 / (eta + 1.0)))
    mean = 0.5 * (parents_a + parents_b)
    half_spread = 0.5 * beta * jnp.abs(parents_a - parents_b)
    side = jnp.where(jax.random.bernoulli(key_side, 0.5, parents_a.shape), 1.0, -1.0)
    child = mean + side * half_spread
    cross = jax.random.bernoulli(key_gene, 0.5, parents_a.shape)
    return jnp.clip(jnp.where(cross, child, parents_a), 0.0, 1.0)
