"""Flat baselines (issue 5): evaluation hand cases, batched MAP-Elites, training CLI, resume,
repertoire files, Table 2 statistics (APROL's repertoires: test_flat_aprol.py)."""

import json

import jax
import jax.numpy as jnp
import matplotlib.image
import numpy as np
import pytest

from experiments.repertoire_stats import main as stats_main
from experiments.train_flat import main as flat_main
from hte_jax.errors import ConfigError
from hte_jax.flat.comparison import aggregate, file_statistics
from hte_jax.flat.store import load_flat, shipped_flat_path
from hte_jax.flat.task import FlatTask, evaluate_flat
from hte_jax.flat.training import PRESETS, VARIANTS, preset, train_flat, with_overrides
from hte_jax.hbr.store import shipped_hbr_path
from hte_jax.qd.batched import BatchedMapElites
from hte_jax.qd.grid import Grid
from hte_jax.qd.io import CheckpointError, read_checkpoint, save_checkpoint
from hte_jax.qd.loop import MapElitesConfig
from hte_jax.qd.metrics import projected_statistics
from hte_jax.qd.tasks import planar_arm
from hte_jax.sim import standing_state
from hte_jax.sim.damage import APROL_DAMAGES, damage_masks, parse_damage
from tests import golden

# Bit for bit: the golden output of the tiny Flat-8D run and a resumed run against it.
pytestmark = pytest.mark.exact_numerics


flat8d_run = golden.run_fixture("flat8d_tiny")


@pytest.mark.slow
def test_tiny_8d_run_matches_the_golden_output(flat8d_run):
    golden.check("flat8d_tiny", flat8d_run)


@pytest.mark.slow
def test_standing_still_is_the_centre_cell_with_every_healthy_foot_down(robot):
    task = FlatTask(descriptor="8d", steps=100)
    zeros = jnp.zeros((1, 36))
    for damage in ("none", "leg0", "legs1+4"):
        mask = parse_damage(damage)
        evaluation = evaluate_flat(robot, task, standing_state(robot, mask), jnp.asarray(mask), None, zeros)
        descriptor = np.asarray(evaluation.descriptors[0])
        assert bool(evaluation.valid[0])
        np.testing.assert_allclose(descriptor[:2], 0.5, atol=0.002)  # within 6 mm of the start
        np.testing.assert_array_equal(descriptor[2:], (~mask).astype(np.float32))
        np.testing.assert_array_equal(np.asarray(evaluation.extras["contact_fraction"][0]), (~mask).astype(np.float32))
        assert abs(float(evaluation.extras["arrival_yaw"][0])) < 0.01


def test_aprol_damages_are_the_six_single_and_fifteen_two_leg_damages():
    masks = damage_masks(APROL_DAMAGES)
    assert masks.shape == (21, 6)
    assert sorted(masks.sum(axis=1).tolist()) == [1] * 6 + [2] * 15
    assert len({tuple(m) for m in masks}) == 21
    np.testing.assert_array_equal(parse_damage("legs1+4"), parse_damage(6))  # the paper's middle-legs damage
    with pytest.raises(ConfigError, match="unknown damage 'legs4\\+1'"):
        parse_damage("legs4+1")


def _arm_algorithm(offsets):
    def evaluate(key, genotypes, offset):
        evaluation = planar_arm(genotypes)
        return evaluation.replace(fitnesses=evaluation.fitnesses + offset * genotypes[:, 0])

    return BatchedMapElites(
        container=Grid(bins=(8, 8), low=(0.0, 0.0), high=(1.0, 1.0)),
        evaluate=evaluate,
        genotype_dim=4,
        conditions=jnp.asarray(offsets, jnp.float32),
        names=tuple(f"offset{o}" for o in offsets),
        config=MapElitesConfig(batch_size=16, init_size=32, mutation_rate=0.3),
    )


@pytest.mark.slow
def test_batched_runs_equal_the_same_runs_made_one_by_one():
    algo = _arm_algorithm([0.0, 1.0, -2.0])
    key = jax.random.PRNGKey(3)
    state, _ = algo.run_block(algo.init(key), 5)
    assert int(state.generation) == 5 and algo.evaluations(state) == 3 * (32 + 5 * 16)
    for run, run_key in enumerate(algo.run_keys(key)):
        single = algo.single(run)
        alone, _ = single.run_block(single.init(run_key), 5)
        for got, want in zip(jax.tree.leaves(jax.tree.map(lambda x: x[run], state.repertoire)),
                             jax.tree.leaves(alone.repertoire)):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    filled = np.asarray(state.repertoire.filled)
    genes = np.asarray(state.repertoire.genotypes)
    # the conditions really differ: the runs' elites are not the same
    assert not np.array_equal(genes[0][filled[0]], genes[2][filled[2]])
    metrics = jax.device_get(algo.metrics(state))
    assert int(metrics.filled) == int(filled.sum())
    with pytest.raises(ConfigError, match="one per name"):
        BatchedMapElites(algo.container, algo.evaluate, 4, jnp.zeros(2), ("a", "b", "c"))


@pytest.mark.slow
def test_8d_run_writes_consistent_repertoires_and_plots(flat8d_run):
    flat, meta = load_flat(flat8d_run / "repertoires.npz")
    config = preset("tiny", "8d")
    assert meta["training"]["config"] == config.to_dict() and flat.task == config.task
    rep = flat[0]
    filled = np.asarray(rep.filled)
    descriptors = np.asarray(rep.descriptors)[filled]
    fraction = np.asarray(rep.extras["contact_fraction"])[filled]
    np.testing.assert_array_equal(descriptors[:, 2:], (fraction > config.contact_threshold).astype(np.float32))
    cells = np.asarray(flat.task.grid().cell_index(jnp.asarray(descriptors)))
    np.testing.assert_array_equal(cells, np.flatnonzero(filled))
    rows = (flat8d_run / "metrics.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + config.generations + 1  # header, initial batch, one per generation (block 1)
    for name in ("xy_fitness", "contact_patterns", "metrics"):
        image = matplotlib.image.imread(flat8d_run / "plots" / f"{name}.png")
        assert image.ndim == 3 and image.std() > 0


@pytest.mark.slow
def test_killed_flat_run_resumes_bit_identical(flat8d_run, tmp_path, capsys):
    class Killed(Exception):
        pass

    def kill(block, state, row):
        if block == 0:
            raise Killed

    config = preset("tiny", "8d")
    with pytest.raises(Killed):
        train_flat(config, tmp_path / "killed", progress=True, on_block=kill, plots=False)
    assert "flat 8d: initial batch" in capsys.readouterr().err  # the initial batch shows its progress bar
    assert (tmp_path / "killed" / "checkpoint.npz").exists() and not (tmp_path / "killed" / "repertoires.npz").exists()
    train_flat(config, tmp_path / "killed", resume_run=True, progress=True, plots=False)
    assert "initial batch" not in capsys.readouterr().err  # resumed from the checkpoint: no initial batch
    resumed, _ = read_checkpoint(tmp_path / "killed" / "repertoires.npz")
    whole, _ = read_checkpoint(flat8d_run / "repertoires.npz")
    assert resumed.keys() == whole.keys()
    for name in whole:
        np.testing.assert_array_equal(resumed[name], whole[name], err_msg=name)
    strip = lambda text: [line.rsplit(",", 1)[0] for line in text.splitlines()]  # noqa: E731 - drop wall time
    assert strip((tmp_path / "killed" / "metrics.csv").read_text()) == strip((flat8d_run / "metrics.csv").read_text())


@pytest.mark.slow
def test_flat_cli_errors_name_the_problem(flat8d_run, capsys):
    assert flat_main(["--variant", "3d"]) == 2
    assert "unknown variant '3d'" in capsys.readouterr().err
    assert flat_main(["--preset", "huge"]) == 2
    assert "unknown preset" in capsys.readouterr().err
    assert flat_main(["--batch-size", "0"]) == 2
    assert "batch_size" in capsys.readouterr().err
    assert flat_main(["--mutation-rate", "lots"]) == 2
    assert "mutation_rate" in capsys.readouterr().err
    assert flat_main(["--variant", "8d", "--preset", "tiny", "--out", str(flat8d_run)]) == 2
    assert "--resume" in capsys.readouterr().err
    assert flat_main(["--variant", "8d", "--preset", "tiny", "--out", str(flat8d_run), "--resume", "--seed", "4"]) == 2
    assert "seed" in capsys.readouterr().err
    assert flat_main(["--variant", "aprol", "--show-config"]) == 0
    assert json.loads(capsys.readouterr().out) == preset("cpu", "aprol").to_dict()


def test_presets_match_the_hbr_top_layer_budget():
    from hte_jax.hbr.training import preset as hbr_preset

    for name in ("gpu", "paper"):
        top = hbr_preset(name).top
        for variant in ("2d", "8d"):
            assert PRESETS[name][variant].evaluations == top.evaluations
    assert set(VARIANTS) == set(PRESETS["cpu"])
    assert with_overrides(preset("cpu", "2d"), {"generations": "3"}).generations == 3
    with pytest.raises(ConfigError, match="unknown setting 'speed'"):
        with_overrides(preset("cpu", "2d"), {"speed": 1})


@pytest.mark.slow
def test_flat_files_are_checked_on_load(flat8d_run, tmp_path):
    arrays, header = read_checkpoint(flat8d_run / "repertoires.npz")
    meta = header["metadata"]

    def write(name, arrays=arrays, meta=meta):
        path = tmp_path / f"{name}.npz"
        save_checkpoint(path, arrays, meta)
        return path

    with pytest.raises(CheckpointError, match="r00_genotypes has shape"):
        load_flat(write("shape", {**arrays, "r00_genotypes": arrays["r00_genotypes"][:, :35]}))
    moved = arrays["r00_slots"].copy()
    moved[0] = (moved[0] + 1) % 6400 if (moved[0] + 1) % 6400 not in moved else moved[0] - 1
    with pytest.raises(CheckpointError, match="outside their descriptors' cells"):
        load_flat(write("moved", {**arrays, "r00_slots": moved}))
    with pytest.raises(CheckpointError, match="bad flat repertoire header"):
        load_flat(write("damage", meta={**meta, "damages": ["leg9"]}))
    with pytest.raises(CheckpointError, match="missing 'r00_fitnesses'"):
        load_flat(write("missing", {k: v for k, v in arrays.items() if k != "r00_fitnesses"}))
    with pytest.raises(CheckpointError, match="not a flat repertoire file"):
        load_flat(shipped_hbr_path())
    with pytest.raises(ConfigError, match="unknown flat variant"):
        shipped_flat_path("4d")


def test_projected_statistics_hand_case():
    # three elites in x-y cell (0, 0) of a 2 x 2 grid, one in cell (1, 1)
    descriptors = np.array([[0.1, 0.1, 0], [0.2, 0.3, 1], [0.4, 0.4, 1], [0.9, 0.6, 0], [0.7, 0.7, 0]])
    fitnesses = np.array([-0.5, -0.1, -0.3, -0.2, -9.0])
    filled = np.array([True, True, True, True, False])
    stats = projected_statistics(descriptors, fitnesses, filled, bins=2)
    assert stats == {"size": 4, "effective_size": 2, "mean_fitness": pytest.approx(-0.15),
                     "mean_fitness_all": pytest.approx(-0.275)}
    rows = [{"method": "A", "evaluations": 10, "size": s, "effective_size": s, "mean_fitness": f,
             "mean_fitness_all": f} for s, f in ((1, -0.1), (3, -0.3))]
    table = aggregate(rows)
    assert table["A"]["n"] == 2
    assert table["A"]["size"] == pytest.approx((2.0, np.sqrt(2.0)))
    assert table["A"]["mean_fitness"] == pytest.approx((-0.2, np.sqrt(0.02)))


@pytest.mark.slow
def test_repertoire_stats_cli_over_files(flat8d_run, tmp_path, capsys):
    out = tmp_path / "table"
    assert stats_main(["--hbr", str(shipped_hbr_path()), "--flat8d", str(flat8d_run), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "HBR (ours)" in printed and "HBR (paper)" in printed and "Flat-8D (paper)" in printed
    data = json.loads((out / "table2.json").read_text())
    assert [row["method"] for row in data["rows"]] == ["HBR", "Flat-8D"]
    assert data["rows"][1] == {**file_statistics(flat8d_run), "path": data["rows"][1]["path"]}
    assert data["aggregate"]["Flat-8D"]["size"][0] == data["rows"][1]["size"]
    assert (out / "table2.md").read_text().startswith("| method |")
    assert stats_main(["--flat2d", str(tmp_path / "nowhere.npz"), "--out", str(out)]) == 2
    assert "no such checkpoint file" in capsys.readouterr().err
