"""Task specs (qd.task_spec), repertoire files of any spec (qd.store), and the specs of the flat and HBR problems."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.inspect_checkpoint import describe
from hte_jax.errors import ConfigError
from hte_jax.flat.store import load_flat, shipped_flat_path
from hte_jax.flat.task import FlatTask, flat_spec
from hte_jax.hbr.bottom import bottom_spec
from hte_jax.hbr.middle import middle_spec
from hte_jax.hbr.store import layer_specs, load_hbr, save_hbr
from hte_jax.hbr.top import TopTask, top_spec
from hte_jax.qd import (
    Archive,
    BatchedMapElites,
    CheckpointError,
    Grid,
    MapElites,
    MapElitesConfig,
    TaskSpec,
    load_repertoire,
    run,
    save_checkpoint,
    save_repertoire,
)
from hte_jax.qd.io import read_checkpoint
from hte_jax.qd.tasks import planar_arm

ARM_EXTRAS = {"first_angle": ((), "float32"), "quadrant": ((2,), np.int32)}


def arm_with_extras(key, genotypes):
    """The planar arm with two extras: the first gene (B,) and the arm's quadrant (B, 2) int32."""
    del key
    evaluation = planar_arm(genotypes)
    quadrant = (evaluation.descriptors > 0.5).astype(jnp.int32)
    return evaluation.replace(extras={"first_angle": genotypes[:, 0], "quadrant": quadrant})


def arm_spec(container=Grid((8, 8), (0.0, 0.0), (1.0, 1.0)), name="arm", extras=ARM_EXTRAS, evaluate=arm_with_extras):
    return TaskSpec(name, 5, container, evaluate, extras, qd_offset=-math.pi)


def trained(spec, generations=3, batch=32):
    algo = MapElites.from_spec(spec, MapElitesConfig(batch_size=batch, init_size=batch))
    return algo, run(algo, algo.init(jax.random.PRNGKey(0)), generations, block_size=generations, progress=False)


def assert_same_repertoire(got, want):
    for (path, a), (_, b) in zip(jax.tree_util.tree_flatten_with_path(got)[0], jax.tree_util.tree_flatten_with_path(want)[0]):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=jax.tree_util.keystr(path))
    assert jax.tree.structure(got) == jax.tree.structure(want)


def test_from_spec_builds_the_algorithm_the_constructor_builds():
    spec = arm_spec()
    algo, state = trained(spec)
    assert algo.config.qd_offset == -math.pi and algo.genotype_dim == 5 and algo.container is spec.container
    by_hand = MapElites(spec.container, arm_with_extras, 5, MapElitesConfig(batch_size=32, init_size=32, qd_offset=-math.pi),
                        extras={"first_angle": jnp.float32(0), "quadrant": jnp.zeros(2, jnp.int32)})
    again = run(by_hand, by_hand.init(jax.random.PRNGKey(0)), 3, block_size=3, progress=False)
    assert_same_repertoire(state.repertoire, again.repertoire)
    assert algo.checkpoint_metadata() == by_hand.checkpoint_metadata()
    assert int(state.repertoire.size) > 10
    kept = TaskSpec("arm", 5, spec.container, arm_with_extras, ARM_EXTRAS)  # no qd_offset: the config's stays
    assert MapElites.from_spec(kept, MapElitesConfig(qd_offset=-2.0)).config.qd_offset == -2.0


def test_batched_from_spec_builds_the_algorithm_the_constructor_builds():
    def shifted(key, genotypes, condition):
        evaluation = arm_with_extras(key, genotypes)
        return evaluation.replace(descriptors=jnp.clip(evaluation.descriptors + condition["shift"], 0.0, 1.0))

    conditions = {"shift": jnp.asarray([[0.0, 0.0], [0.2, -0.1]], jnp.float32)}
    config = MapElitesConfig(batch_size=16, init_size=16)
    algo = BatchedMapElites.from_spec(arm_spec(evaluate=shifted), conditions, ("still", "shifted"), config)
    by_hand = BatchedMapElites(algo.container, shifted, 5, conditions, ("still", "shifted"),
                               MapElitesConfig(batch_size=16, init_size=16, qd_offset=-math.pi),
                               extras={"first_angle": jnp.float32(0), "quadrant": jnp.zeros(2, jnp.int32)})
    assert_same_repertoire(algo.init(jax.random.PRNGKey(1)).repertoire, by_hand.init(jax.random.PRNGKey(1)).repertoire)
    assert algo.checkpoint_metadata() == by_hand.checkpoint_metadata() and algo.names == ("still", "shifted")


def test_a_repertoire_file_round_trips_and_is_read_only_by_its_spec(tmp_path):
    spec = arm_spec()
    _, state = trained(spec)
    path = tmp_path / "arm.npz"
    save_repertoire(path, spec, state.repertoire, {"note": "three generations"})
    loaded, meta = load_repertoire(path, spec)
    assert_same_repertoire(loaded, state.repertoire)
    assert meta["note"] == "three generations" and meta["task"]["name"] == "arm"
    assert meta["task"]["extras"] == {"first_angle": [[], "float32"], "quadrant": [[2], "int32"]}
    text = describe(str(path))
    assert f"elites: {int(state.repertoire.size)}, fitness min" in text and '"kind": "hte_jax.repertoire"' in text

    with pytest.raises(CheckpointError, match="task name = 'arm', this spec has 'other'"):
        load_repertoire(path, arm_spec(name="other"))
    with pytest.raises(CheckpointError, match="task container"):
        load_repertoire(path, arm_spec(Grid((8, 9), (0.0, 0.0), (1.0, 1.0))))
    with pytest.raises(CheckpointError, match="task extras"):
        load_repertoire(path, arm_spec(extras={"first_angle": ((), "float32")}))
    with pytest.raises(ConfigError, match="reserved"):
        save_repertoire(tmp_path / "x.npz", spec, state.repertoire, {"task": "mine"})
    with pytest.raises(ConfigError, match=r"genotypes.*\(64, 5\)"):
        save_repertoire(tmp_path / "x.npz", spec, spec.container.empty(4, spec.extras_example()))
    with pytest.raises(ConfigError, match="fields"):
        save_repertoire(tmp_path / "x.npz", spec, spec.container.empty(5))
    save_checkpoint(tmp_path / "ck.npz", state.repertoire)
    with pytest.raises(CheckpointError, match="not a repertoire file"):
        load_repertoire(tmp_path / "ck.npz", spec)

    arrays, header = read_checkpoint(path)
    arrays["slots"] = (arrays["slots"] + 1) % spec.capacity  # every elite one cell off
    save_checkpoint(tmp_path / "moved.npz", arrays, header["metadata"])
    with pytest.raises(CheckpointError, match="repertoire has elites outside their descriptors' cells"):
        load_repertoire(tmp_path / "moved.npz", spec)


def test_an_archive_repertoire_round_trips_and_keeps_its_elites_a_prefix(tmp_path):
    spec = arm_spec(Archive(capacity=128, low=(0.0, 0.0), high=(1.0, 1.0), l=0.05))
    _, state = trained(spec)
    save_repertoire(tmp_path / "archive.npz", spec, state.repertoire)
    loaded, _ = load_repertoire(tmp_path / "archive.npz", spec)
    assert_same_repertoire(loaded, state.repertoire)
    arrays, header = read_checkpoint(tmp_path / "archive.npz")
    arrays["slots"] = arrays["slots"] + 1  # a hole at slot 0
    save_checkpoint(tmp_path / "holey.npz", arrays, header["metadata"])
    with pytest.raises(CheckpointError, match="not a prefix of the archive"):
        load_repertoire(tmp_path / "holey.npz", spec)


def test_descriptors_are_checked_against_the_containers_bounds(tmp_path):
    def raw_xy(key, genotypes):
        evaluation = planar_arm(genotypes)
        return evaluation.replace(descriptors=evaluation.descriptors * 2.0 - 1.0)  # the hand in [-1, 1]^2

    spec = TaskSpec("arm-xy", 4, Grid((6, 6), (-1.0, -1.0), (1.0, 1.0)), raw_xy)
    _, state = trained(spec, generations=1)
    assert (np.asarray(state.repertoire.descriptors)[np.asarray(state.repertoire.filled)] < 0).any()
    save_repertoire(tmp_path / "xy.npz", spec, state.repertoire)
    assert_same_repertoire(load_repertoire(tmp_path / "xy.npz", spec)[0], state.repertoire)
    arrays, header = read_checkpoint(tmp_path / "xy.npz")
    arrays["descriptors"] = arrays["descriptors"] * 1.5
    save_checkpoint(tmp_path / "far.npz", arrays, header["metadata"])
    with pytest.raises(CheckpointError, match=r"descriptors outside \[\[-1.0, -1.0\], \[1.0, 1.0\]\]"):
        load_repertoire(tmp_path / "far.npz", spec)


def test_a_spec_checks_what_it_is_given():
    grid = Grid((4,), (0.0,), (1.0,))
    with pytest.raises(ConfigError, match="non-empty string"):
        TaskSpec("", 3, grid)
    with pytest.raises(ConfigError, match="genotype_dim"):
        TaskSpec("t", 0, grid)
    with pytest.raises(ConfigError, match="has no 'capacity'"):
        TaskSpec("t", 3, object())
    with pytest.raises(ConfigError, match="extra 'x' must be"):
        TaskSpec("t", 3, grid, extras={"x": "float32"})
    with pytest.raises(ConfigError, match="numeric dtype"):
        TaskSpec("t", 3, grid, extras={"x": ((), "U3")})
    with pytest.raises(ConfigError, match="qd_offset"):
        TaskSpec("t", 3, grid, qd_offset=math.inf)
    layout_only = TaskSpec("t", 3, grid, extras={"x": ([2], "int32")})
    assert layout_only.extras == {"x": ((2,), np.dtype(np.int32))} and layout_only.descriptor_dim == 1
    with pytest.raises(ConfigError, match="has no evaluation"):
        MapElites.from_spec(layout_only)
    with pytest.raises(ConfigError, match="has no evaluation"):
        BatchedMapElites.from_spec(layout_only, {"c": jnp.zeros(1)}, ("a",))
    algo = MapElites.from_spec(layout_only.with_evaluate(lambda key, g: None))
    assert algo.genotype_dim == 3 and layout_only.evaluate is None


def old_layer_algorithm(container, genotype_dim, extras, qd_offset):
    """A layer's MapElites as `hbr.training` / `flat.training` built it before the task specs."""
    return MapElites(container, lambda key, genes: None, genotype_dim, MapElitesConfig(qd_offset=qd_offset), extras)


@pytest.mark.parametrize(
    "spec, before",
    [
        (bottom_spec(256, 0.01), old_layer_algorithm(Archive(256, (0.0,) * 3, (1.0,) * 3, 0.01), 6,
                                                     {"leg": jnp.int32(0)}, -1.0)),
        (middle_spec(512, 0.05), old_layer_algorithm(
            Archive(512, (0.0,) * 9, (1.0,) * 9, 0.05), 18,
            {"contact_fraction": jnp.zeros(6, jnp.float32), "medoid": jnp.int32(0)}, -math.pi)),
        (top_spec(TopTask(bins=20)), old_layer_algorithm(
            TopTask(bins=20).grid(), 9,
            {"middle_indices": jnp.zeros(3, jnp.int32), "arrival_yaw": jnp.float32(0)}, -math.pi)),
        (flat_spec(FlatTask("8d", bins=10)), old_layer_algorithm(
            FlatTask("8d", bins=10).grid(), 36,
            {"arrival_yaw": jnp.float32(0), "contact_fraction": jnp.zeros(6, jnp.float32)}, -math.pi)),
    ],
    ids=["bottom", "middle", "top", "flat"],
)
def test_the_existing_specs_keep_their_checkpoints(spec, before):
    """Old run folders resume: a spec's algorithm has the metadata and state layout the old code wrote."""
    algo = MapElites.from_spec(spec.with_evaluate(lambda key, genes: None), MapElitesConfig())
    assert algo.checkpoint_metadata() == before.checkpoint_metadata()
    key = jax.random.PRNGKey(0)
    assert jax.tree.structure(algo.empty_state(key)) == jax.tree.structure(before.empty_state(key))
    assert jax.tree.map(lambda x: (x.shape, x.dtype), algo.empty_state(key)) == jax.tree.map(
        lambda x: (x.shape, x.dtype), before.empty_state(key))


def test_the_shipped_hbr_layers_round_trip_through_their_specs(tmp_path):
    hbr, top_task, meta = load_hbr()
    assert hbr.top_task == top_task and meta["top_task"] == {"bins": top_task.bins, "extent": top_task.extent}
    specs = layer_specs({layer: getattr(hbr, layer).capacity for layer in ("bottom", "middle", "top")}, top_task)
    assert [specs[layer].name for layer in ("bottom", "middle", "top")] == ["hbr-bottom", "hbr-middle", "hbr-top"]
    for layer, spec in specs.items():
        save_repertoire(tmp_path / f"{layer}.npz", spec, getattr(hbr, layer))
        loaded, _ = load_repertoire(tmp_path / f"{layer}.npz", spec)
        assert_same_repertoire(loaded, getattr(hbr, layer))
        assert int(loaded.size) > 100
    save_hbr(tmp_path / "hbr.npz", hbr)  # the top task travels inside the HBR
    again, again_task, _ = load_hbr(tmp_path / "hbr.npz")
    assert again_task == top_task and again.top_task == top_task
    assert_same_repertoire(again.top, hbr.top)
    with pytest.raises(ConfigError, match="top_task"):
        save_hbr(tmp_path / "other.npz", hbr, TopTask(bins=top_task.bins + 1))


def test_a_shipped_flat_repertoire_round_trips_through_its_spec(tmp_path):
    flat, _ = load_flat(shipped_flat_path("2d"))
    spec = flat_spec(flat.task)
    assert spec.name == "flat-2d" and spec.capacity == flat.task.bins**2 and spec.genotype_dim == 36
    save_repertoire(tmp_path / "flat.npz", spec, flat[0])
    loaded, _ = load_repertoire(tmp_path / "flat.npz", spec)
    assert_same_repertoire(loaded, flat[0])
    assert int(loaded.size) > 1000
