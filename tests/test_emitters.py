"""Emitters: the default one is the config's, stateless emitters leave checkpoints as they were,
an emitter's state is checkpointed and resumed (alone and in batched runs)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from hte_jax.errors import ConfigError
from hte_jax.qd import (
    BatchedMapElites,
    CheckpointError,
    Grid,
    MapElites,
    MapElitesConfig,
    UniformSelection,
    VariationEmitter,
    resume,
    run,
)
from hte_jax.qd import io as qd_io
from hte_jax.qd.emitters import config_emitter
from hte_jax.qd.tasks import planar_arm_evaluate
from hte_jax.qd.variation import SbxPolynomial

GRID = Grid(bins=(16, 16), low=(0.0, 0.0), high=(1.0, 1.0))
CONFIG = MapElitesConfig(batch_size=32, init_size=32, crossover_rate=0.5)


@struct.dataclass
class CountState:
    """emitted: int32 scalar, offspring emitted; accepted: int32 scalar, offspring inserted."""

    emitted: jax.Array
    accepted: jax.Array


@dataclasses.dataclass(frozen=True)
class CountingEmitter(VariationEmitter):
    """The default emitter's offspring, counting what it emits and what gets in."""

    def init(self, repertoire, key):
        return CountState(emitted=jnp.int32(0), accepted=jnp.int32(0))

    def emit(self, repertoire, emitter_state, key):
        genotypes, _ = super().emit(repertoire, emitter_state, key)
        return genotypes, emitter_state.replace(emitted=emitter_state.emitted + genotypes.shape[0])

    def update(self, emitter_state, repertoire, genotypes, evaluation, insertion):
        return emitter_state.replace(accepted=emitter_state.accepted + insertion.accepted.sum(dtype=jnp.int32))


def counting_emitter():
    return CountingEmitter(UniformSelection(), SbxPolynomial.from_config(CONFIG), CONFIG.batch_size)


def test_the_config_emitter_is_the_default_and_leaves_checkpoints_unchanged(tmp_path):
    default = MapElites(GRID, planar_arm_evaluate, 6, CONFIG)
    explicit = MapElites(GRID, planar_arm_evaluate, 6, CONFIG, emitter=config_emitter(CONFIG, GRID))
    a, b = (algo.run_block(algo.init(jax.random.PRNGKey(1)), 4)[0] for algo in (default, explicit))
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    qd_io.save_checkpoint(tmp_path / "c.npz", a, default.checkpoint_metadata())
    arrays, header = qd_io.read_checkpoint(tmp_path / "c.npz")
    repertoire_fields = {f"repertoire/{name}" for name in ("genotypes", "descriptors", "fitnesses", "filled")}
    assert set(arrays) == {"key", "generation"} | repertoire_fields
    assert set(header["metadata"]) == {"container", "config", "genotype_dim"}
    assert "VariationEmitter(selection=UniformSelection()" in explicit.checkpoint_metadata()["emitter"]


def test_emitter_state_is_checkpointed_and_resumed(tmp_path):
    algo = MapElites(GRID, planar_arm_evaluate, 6, CONFIG, emitter=counting_emitter())
    path = tmp_path / "checkpoint.npz"
    run(algo, algo.init(jax.random.PRNGKey(2)), 10, block_size=5, checkpoint_path=path, progress=False)
    resumed = run(algo, resume(algo, path), 20, block_size=5, checkpoint_path=path, progress=False)
    straight = run(algo, algo.init(jax.random.PRNGKey(2)), 20, block_size=5, progress=False)
    for x, y in zip(jax.tree.leaves(resumed), jax.tree.leaves(straight)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    arrays, _ = qd_io.read_checkpoint(path)
    assert int(arrays["emitter_state/emitted"]) == 20 * 32
    new_elites = int(straight.repertoire.size) - int(algo.init(jax.random.PRNGKey(2)).repertoire.size)
    assert new_elites <= int(arrays["emitter_state/accepted"]) < 20 * 32
    with pytest.raises(CheckpointError, match="emitter"):  # the same run without its emitter
        resume(MapElites(GRID, planar_arm_evaluate, 6, CONFIG, emitter=config_emitter(CONFIG, GRID)), path)


def test_batched_runs_carry_one_emitter_state_per_run():
    batched = BatchedMapElites(
        GRID, lambda key, genotypes, condition: planar_arm_evaluate(key, genotypes), 6, jnp.zeros(3), ("a", "b", "c"),
        CONFIG, emitter=counting_emitter(),
    )
    state, _ = batched.run_block(batched.init(jax.random.PRNGKey(3)), 4)
    assert np.asarray(state.emitter_state.emitted).tolist() == [4 * 32] * 3
    template = batched.empty_state(jax.random.PRNGKey(0))
    assert jax.tree.map(jnp.shape, template) == jax.tree.map(jnp.shape, state)


def test_an_emitter_must_make_a_full_batch():
    half = VariationEmitter(UniformSelection(), SbxPolynomial.from_config(CONFIG), CONFIG.batch_size // 2)
    algo = MapElites(GRID, planar_arm_evaluate, 6, CONFIG, emitter=half)
    with pytest.raises(ConfigError, match="expected \\(batch_size, genotype_dim\\) = \\(32, 6\\)"):
        algo.run_block(algo.init(jax.random.PRNGKey(0)), 1)
