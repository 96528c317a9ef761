"""Grid and unstructured-archive insertion against brute-force NumPy references (acceptance 1)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.qd import Archive, Evaluation, Grid
from tests import reference_qd as ref


def _as_numpy(rep):
    return {
        "genotypes": np.array(rep.genotypes),
        "descriptors": np.array(rep.descriptors),
        "fitnesses": np.array(rep.fitnesses),
        "filled": np.array(rep.filled),
    }


def _assert_same(rep, expected):
    got = _as_numpy(rep)
    for name in ("filled", "fitnesses", "genotypes", "descriptors"):
        np.testing.assert_array_equal(got[name], expected[name], err_msg=name)


def _random_batch(rng, batch, dim, low, high, fitness_levels):
    """Descriptors partly outside the bounds, quantised fitness (ties), some invalid or NaN."""
    span = np.asarray(high) - np.asarray(low)
    desc = (np.asarray(low) - 0.05 * span + rng.uniform(size=(batch, dim)) * 1.1 * span).astype(np.float32)
    fit = rng.integers(0, fitness_levels, size=batch).astype(np.float32) / fitness_levels - 1.0
    valid = rng.uniform(size=batch) > 0.1
    fit[rng.uniform(size=batch) < 0.03] = np.nan
    desc[rng.uniform(size=batch) < 0.03, 0] = np.nan
    genotypes = rng.uniform(size=(batch, 3)).astype(np.float32)
    return genotypes, desc, fit, valid


@pytest.mark.parametrize(
    "bins,low,high", [((5, 4), (0.0, -1.0), (1.0, 1.0)), ((3, 2, 2), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))]
)
def test_grid_matches_reference(bins, low, high):
    grid = Grid(bins=bins, low=low, high=high)
    add = jax.jit(grid.add)
    rng = np.random.default_rng(0)
    rep = grid.empty(3)
    expected = _as_numpy(rep)
    for _ in range(12):
        genotypes, desc, fit, valid = _random_batch(rng, 40, len(bins), low, high, fitness_levels=4)
        rep, insertion = add(rep, jnp.asarray(genotypes), Evaluation(jnp.asarray(fit), jnp.asarray(desc), jnp.asarray(valid)))
        expected, slots = ref.grid_add(bins, low, high, expected, genotypes, desc, fit, valid)
        _assert_same(rep, expected)
        np.testing.assert_array_equal(np.asarray(insertion.slot), slots)
        np.testing.assert_array_equal(np.asarray(insertion.accepted), slots >= 0)
    assert expected["filled"].sum() == grid.capacity  # the test reached a full grid


def test_grid_ties_go_to_the_first_in_the_batch_and_need_strict_improvement():
    grid = Grid(bins=(2,), low=(0.0,), high=(1.0,))
    rep = grid.empty(1)
    same_cell = Evaluation(jnp.asarray([0.5, 0.5, 0.2]), jnp.asarray([[0.1], [0.2], [0.3]]), jnp.ones(3, bool))
    rep, ins = grid.add(rep, jnp.asarray([[1.0], [2.0], [3.0]]), same_cell)
    assert np.asarray(ins.slot).tolist() == [0, -1, -1]
    assert float(rep.genotypes[0, 0]) == 1.0 and float(rep.descriptors[0, 0]) == pytest.approx(0.1)
    rep, ins = grid.add(rep, jnp.asarray([[4.0]]), Evaluation(jnp.asarray([0.5]), jnp.asarray([[0.4]]), jnp.ones(1, bool)))
    assert not bool(ins.accepted[0])  # equal fitness does not replace the elite


def test_grid_cell_index_bounds():
    grid = Grid(bins=(100, 100), low=(-1.5, -1.5), high=(1.5, 1.5))
    desc = jnp.asarray([[-1.5, -1.5], [1.5, 1.5], [0.0, 0.0], [1.6, 0.0], [jnp.nan, 0.0], [-1.46, -1.5]])
    np.testing.assert_array_equal(np.asarray(grid.cell_index(desc)), [0, 9999, 5050, -1, -1, 100])
    assert grid.capacity == 10_000
    flat8d = Grid(bins=(100, 100, 2, 2, 2, 2, 2, 2), low=(-1.5, -1.5) + (0.0,) * 6, high=(1.5, 1.5) + (1.0,) * 6)
    assert flat8d.capacity == 640_000
    index = flat8d.cell_index(jnp.asarray([[1.5, 1.5, 1, 1, 1, 1, 1, 1], [-1.5, -1.5, 0, 0, 0, 0, 0, 1]]))
    np.testing.assert_array_equal(np.asarray(index), [639_999, 1])


@pytest.mark.exact_numerics
def test_grid_cell_index_on_the_host_agrees_with_jax():
    """NumPy (xp=np: `cell_matches` on the host) finds jax's cells, in a batch and row by row, at the bin edges
    too (XLA divides by a broadcast span as a product with its inverse, by a single row's exactly)."""
    grid = Grid(bins=(100, 100, 2), low=(-1.5, -1.5, 0.0), high=(1.5, 1.5, 1.0))
    rng = np.random.default_rng(5)
    desc = rng.uniform(-1.6, 1.6, (4000, 3)).astype(np.float32)
    desc[:1000, :2] = rng.choice(np.arange(101) * 0.03 - 1.5, (1000, 2))  # on the bin edges
    desc[:1000, :2] += rng.choice([-1e-6, 0.0, 1e-6], (1000, 2))  # and beside them
    desc = desc.astype(np.float32)
    np.testing.assert_array_equal(grid.cell_index(desc, xp=np), np.asarray(grid.cell_index(jnp.asarray(desc))))
    assert grid.cell_index(desc, xp=np).dtype == np.int32
    one_by_one = [int(grid.cell_index(row[None], xp=np)[0]) for row in desc[:300]]
    assert one_by_one == [int(grid.cell_index(jnp.asarray(row[None]))[0]) for row in desc[:300]]


@pytest.mark.parametrize("kwargs", [{"bins": (0,)}, {"bins": (3,), "low": (1.0,), "high": (0.0,)}, {"bins": (3, 3)}])
def test_grid_bad_config(kwargs):
    args = {"bins": (3,), "low": (0.0,), "high": (1.0,), **kwargs}
    with pytest.raises(ConfigError):
        Grid(**args)


@pytest.mark.parametrize("capacity,k,levels", [(40, 3, 3), (200, 15, 5)])
def test_archive_matches_reference(capacity, k, levels):
    low, high, l, eps = (0.0, 0.0), (1.0, 1.0), 0.12, 0.1
    archive = Archive(capacity=capacity, low=low, high=high, l=l, k=k, eps=eps, chunk_size=16)
    add = jax.jit(archive.add)
    rng = np.random.default_rng(capacity)
    rep = archive.empty(3)
    expected = _as_numpy(rep)
    replaced = added = 0
    for step in range(15):
        genotypes, desc, fit, valid = _random_batch(rng, 48, 2, low, high, fitness_levels=levels)
        if step % 3 == 2:  # copies of current elites and of each other: same places, ties
            filled = np.flatnonzero(expected["filled"])
            desc[:8] = expected["descriptors"][rng.choice(filled, 8)] if len(filled) else desc[:8]
            desc[8:12] = desc[12]
        rep, insertion = add(rep, jnp.asarray(genotypes), Evaluation(jnp.asarray(fit), jnp.asarray(desc), jnp.asarray(valid)))
        before = expected["filled"].sum()
        expected, slots = ref.archive_add(capacity, low, high, l, k, eps, expected, genotypes, desc, fit, valid)
        _assert_same(rep, expected)
        np.testing.assert_array_equal(np.asarray(insertion.slot), slots)
        added += expected["filled"].sum() - before
        replaced += int((slots >= 0).sum()) - (expected["filled"].sum() - before)
    assert added > 20 and replaced > 0  # both rules were exercised
    filled = expected["filled"]
    assert filled[: filled.sum()].all()  # filled slots form a prefix
    desc = expected["descriptors"][filled].astype(np.float64)
    gaps = np.linalg.norm(desc[:, None] - desc[None], axis=-1) + 9 * np.eye(len(desc))
    assert gaps.min() >= (1 - eps) * l - 1e-6  # elites stay (1 - eps) l apart


def test_archive_full_drops_additions_in_batch_order():
    archive = Archive(capacity=3, low=(0.0,), high=(1.0,), l=0.1)
    rep = archive.empty(1)
    desc = jnp.asarray([[0.0], [0.3], [0.6], [0.9], [0.45]])
    rep, ins = archive.add(rep, jnp.arange(5.0)[:, None], Evaluation(jnp.zeros(5), desc, jnp.ones(5, bool)))
    assert np.asarray(ins.slot).tolist() == [0, 1, 2, -1, -1]
    assert int(rep.size) == 3


def test_archive_close_additions_keep_the_best_then_the_first():
    archive = Archive(capacity=10, low=(0.0,), high=(1.0,), l=0.1)
    rep = archive.empty(1)
    desc = jnp.asarray([[0.50], [0.55], [0.52], [0.9]])
    fit = jnp.asarray([0.1, 0.3, 0.3, 0.0])
    rep, ins = archive.add(rep, jnp.arange(4.0)[:, None], Evaluation(fit, desc, jnp.ones(4, bool)))
    assert np.asarray(ins.slot).tolist() == [-1, 0, -1, 1]


def test_archive_nearest_neighbour_ties_go_to_the_lower_slot():
    # Elites at 0.625 (slot 0) and 0.375 (slot 1), candidate at 0.5: both at exactly 0.125.
    archive = Archive(capacity=4, low=(0.0,), high=(1.0,), l=0.25, k=1, eps=0.6)
    rep = archive.empty(1).replace(
        descriptors=jnp.asarray([[0.625], [0.375], [0.0], [0.0]]),
        fitnesses=jnp.asarray([0.0, 0.0, -jnp.inf, -jnp.inf]),
        filled=jnp.asarray([True, True, False, False]),
    )
    better = Evaluation(jnp.asarray([1.0]), jnp.asarray([[0.5]]), jnp.ones(1, bool))
    rep, ins = archive.add(rep, jnp.ones((1, 1)), better)
    assert int(ins.slot[0]) == 0 and not bool(ins.new_slot[0])
    assert float(rep.descriptors[0, 0]) == 0.5 and float(rep.descriptors[1, 0]) == 0.375


@pytest.mark.parametrize(
    "kwargs,match",
    [({"capacity": 0}, "capacity"), ({"l": 0.0}, " l "), ({"eps": 1.0}, "eps"), ({"k": 0}, " k "), ({"low": (1.0,)}, "low")],
)
def test_archive_bad_config(kwargs, match):
    args = {"capacity": 10, "low": (0.0,), "high": (1.0,), "l": 0.1, **kwargs}
    with pytest.raises(ConfigError, match=match):
        Archive(**args)
