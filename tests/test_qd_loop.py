"""The MAP-Elites loop, metrics, variation, checkpoints and plots (acceptance 2-4)."""

import csv
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib.image
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.qd import (
    Archive,
    CheckpointError,
    Evaluation,
    Grid,
    MapElites,
    MapElitesConfig,
    load_checkpoint,
    repertoire_metrics,
    resume,
    run,
    save_checkpoint,
)
from hte_jax.qd import io as qd_io
from hte_jax.qd.plots import grid_projection, plot_metrics
from hte_jax.qd.tasks import planar_arm, planar_arm_evaluate
from hte_jax.qd.selection import UniformSelection
from hte_jax.qd.variation import polynomial_mutation, sbx_crossover

ROOT = Path(__file__).resolve().parents[1]


def _column(rows, name):
    return np.array([float(r[name]) for r in rows])


@pytest.fixture(scope="module")
def arm_run(tmp_path_factory):
    """8-DoF arm, 32 x 32 grid, batch 128: 100 generations = 12,928 evaluations."""
    out = tmp_path_factory.mktemp("arm")
    config = MapElitesConfig(batch_size=128, init_size=128, mutation_rate=0.2, qd_offset=-np.pi)
    algo = MapElites(Grid(bins=(32, 32), low=(0.0, 0.0), high=(1.0, 1.0)), planar_arm_evaluate, 8, config)
    state = run(algo, algo.init(jax.random.PRNGKey(0)), 100, block_size=10, log_path=out / "metrics.csv", progress=False)
    with open(out / "metrics.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    return algo, state, rows, out


def test_map_elites_on_the_arm_improves_monotonically(arm_run):
    """Acceptance 2: coverage and QD score never drop; stated levels after 12,928 evaluations."""
    algo, state, rows, _ = arm_run
    assert [int(r["block"]) for r in rows] == list(range(-1, 10))
    assert int(rows[-1]["evaluations"]) == 128 + 100 * 128 == algo.evaluations(state)
    coverage, qd_score = _column(rows, "coverage"), _column(rows, "qd_score")
    assert np.all(np.diff(coverage) >= 0) and np.all(np.diff(qd_score) >= 0)
    assert coverage[-1] >= 0.65 and coverage[0] < 0.15
    assert qd_score[-1] >= 1800.0
    assert _column(rows, "max_fitness")[-1] > -0.3


def test_elites_are_what_the_task_says(arm_run):
    """Every stored elite re-evaluates to its stored fitness and descriptor, in its own cell."""
    algo, state, _, _ = arm_run
    rep = state.repertoire
    filled = np.asarray(rep.filled)
    again = planar_arm(rep.genotypes)
    np.testing.assert_allclose(np.asarray(again.fitnesses)[filled], np.asarray(rep.fitnesses)[filled], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(again.descriptors)[filled], np.asarray(rep.descriptors)[filled], atol=1e-6)
    cells = np.asarray(algo.container.cell_index(rep.descriptors))
    np.testing.assert_array_equal(cells[filled], np.flatnonzero(filled))


def test_map_elites_with_an_unstructured_archive():
    archive = Archive(capacity=2048, low=(0.0, 0.0), high=(1.0, 1.0), l=0.04, chunk_size=128)
    algo = MapElites(archive, planar_arm_evaluate, 6, MapElitesConfig(batch_size=64, init_size=128))
    state = algo.init(jax.random.PRNGKey(1))
    start = int(state.repertoire.size)
    state, _ = algo.run_block(state, 20)
    rep = state.repertoire
    size = int(rep.size)
    assert size > start + 50
    desc = np.asarray(rep.descriptors[:size])
    dist = np.linalg.norm(desc[:, None] - desc[None], axis=-1) + np.eye(size) * 9
    assert dist.min() > (1 - archive.eps) * archive.l  # the archive keeps its elites apart


def test_metrics_by_hand():
    rep = Grid(bins=(4,), low=(0.0,), high=(1.0,)).empty(1)
    rep = rep.replace(fitnesses=jnp.asarray([-1.0, -jnp.inf, -0.5, -jnp.inf]), filled=jnp.asarray([True, False, True, False]))
    m = repertoire_metrics(rep, offset=-np.pi)
    assert int(m.filled) == 2 and float(m.coverage) == 0.5
    assert float(m.qd_score) == pytest.approx(2 * np.pi - 1.5, rel=1e-6)
    assert float(m.mean_fitness) == pytest.approx(-0.75) and float(m.max_fitness) == pytest.approx(-0.5)
    empty = repertoire_metrics(rep.replace(filled=jnp.zeros(4, bool)), offset=0.0)
    assert int(empty.filled) == 0 and float(empty.qd_score) == 0.0 and np.isnan(float(empty.max_fitness))


def test_polynomial_mutation_formula():
    key = jax.random.PRNGKey(3)
    genes = jax.random.uniform(jax.random.PRNGKey(4), (500, 6))
    assert np.array_equal(np.asarray(polynomial_mutation(key, genes, 0.0, 10.0)), np.asarray(genes))
    mutated = np.asarray(polynomial_mutation(key, genes, 1.0, 10.0))
    _, key_r = jax.random.split(key)
    r = np.asarray(jax.random.uniform(key_r, genes.shape), np.float64)
    power = 1 / 11
    delta = np.where(r < 0.5, (2 * r) ** power - 1, 1 - (2 * (1 - r)) ** power)
    np.testing.assert_allclose(mutated, np.clip(np.asarray(genes) + delta, 0, 1), atol=1e-6)
    rate = np.mean(np.asarray(polynomial_mutation(key, genes, 0.17, 10.0)) != np.asarray(genes))
    assert 0.14 < rate < 0.20


def test_uniform_selection_only_picks_elites_uniformly():
    rep = Grid(bins=(10,), low=(0.0,), high=(1.0,)).empty(1)
    rep = rep.replace(filled=jnp.zeros(10, bool).at[jnp.asarray([1, 4, 5, 9])].set(True))
    picks = np.asarray(UniformSelection().select(jax.random.PRNGKey(0), rep, 40_000))
    counts = np.bincount(picks, minlength=10)
    assert set(np.flatnonzero(counts)) == {1, 4, 5, 9}
    assert np.all(np.abs(counts[[1, 4, 5, 9]] - 10_000) < 500)


def test_sbx_crossover_stays_between_bounds_and_keeps_equal_parents():
    a = jax.random.uniform(jax.random.PRNGKey(0), (200, 5))
    child = np.asarray(sbx_crossover(jax.random.PRNGKey(1), a, a, 10.0))
    np.testing.assert_allclose(child, np.asarray(a), atol=1e-7)
    b = jax.random.uniform(jax.random.PRNGKey(2), (200, 5))
    child = np.asarray(sbx_crossover(jax.random.PRNGKey(1), a, b, 10.0))
    assert child.min() >= 0 and child.max() <= 1 and not np.allclose(child, np.asarray(a))


def test_config_errors():
    with pytest.raises(ConfigError, match="multiple of batch_size"):
        MapElitesConfig(batch_size=64, init_size=100)
    with pytest.raises(ConfigError, match="mutation_rate"):
        MapElitesConfig(mutation_rate=1.5)
    with pytest.raises(ConfigError, match="batch_size"):
        MapElitesConfig(batch_size=0)


# --- checkpoints -------------------------------------------------------------------------


def _run_script(directory, *flags):
    cmd = [sys.executable, "-m", "tests.qd_run_script", str(directory), *flags]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_kill_and_resume_is_bit_identical(tmp_path):
    """Acceptance 3: SIGKILL after block 2, resume, and get exactly the uninterrupted run."""
    straight, killed = tmp_path / "straight", tmp_path / "killed"
    assert _run_script(straight).returncode == 0
    interrupted = _run_script(killed, "--kill-after-block", "2")
    assert interrupted.returncode == -9, interrupted.stderr
    arrays, header = qd_io.read_checkpoint(killed / "checkpoint.npz")
    assert int(arrays["generation"]) == 30
    assert _run_script(killed, "--resume").returncode == 0
    final_a, _ = qd_io.read_checkpoint(straight / "checkpoint.npz")
    final_b, _ = qd_io.read_checkpoint(killed / "checkpoint.npz")
    assert sorted(final_a) == sorted(final_b)
    for name in final_a:
        np.testing.assert_array_equal(final_a[name], final_b[name], err_msg=name)
    rows_a = list(csv.DictReader(open(straight / "metrics.csv")))
    rows_b = list(csv.DictReader(open(killed / "metrics.csv")))
    assert [int(r["block"]) for r in rows_b] == list(range(-1, 6))
    for a, b in zip(rows_a, rows_b):
        assert {k: v for k, v in a.items() if k != "wall_time_s"} == {k: v for k, v in b.items() if k != "wall_time_s"}


@pytest.fixture
def small_algo():
    config = MapElitesConfig(batch_size=32, init_size=32)
    return MapElites(Grid(bins=(8, 8), low=(0.0, 0.0), high=(1.0, 1.0)), planar_arm_evaluate, 4, config)


def test_checkpoint_roundtrip_with_extras(tmp_path):
    grid = Grid(bins=(4,), low=(0.0,), high=(1.0,))
    rep = grid.empty(2, extras={"angle": jnp.float32(0), "children": jnp.zeros(3, jnp.int32)})
    rep, _ = grid.add(
        rep,
        jnp.ones((2, 2)),
        Evaluation(jnp.asarray([1.0, 2.0]), jnp.asarray([[0.1], [0.9]]), jnp.ones(2, bool),
                   {"angle": jnp.asarray([0.5, 0.7]), "children": jnp.asarray([[1, 2, 3], [4, 5, 6]], jnp.int32)}),
    )
    save_checkpoint(tmp_path / "rep.npz", rep, {"note": "x"})
    loaded = load_checkpoint(tmp_path / "rep.npz", grid.empty(2, extras={"angle": jnp.float32(0), "children": jnp.zeros(3, jnp.int32)}))
    for a, b in zip(jax.tree.leaves(rep), jax.tree.leaves(loaded)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.asarray(loaded.extras["children"])[3].tolist() == [4, 5, 6]


def test_truncated_checkpoint_is_a_clear_error(tmp_path, small_algo):
    path = tmp_path / "ck.npz"
    save_checkpoint(path, small_algo.init(jax.random.PRNGKey(0)), small_algo.checkpoint_metadata())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        resume(small_algo, path)


def test_corrupt_checkpoint_is_a_clear_error(tmp_path, small_algo):
    path = tmp_path / "ck.npz"
    save_checkpoint(path, small_algo.init(jax.random.PRNGKey(0)), small_algo.checkpoint_metadata())
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(64)  # flip bytes inside an array: CRC mismatch
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        resume(small_algo, path)
    (tmp_path / "junk.npz").write_bytes(b"not a zip at all")
    with pytest.raises(CheckpointError, match="junk.npz: not an hte-jax checkpoint"):
        resume(small_algo, tmp_path / "junk.npz")
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        resume(small_algo, tmp_path / "missing.npz")


def test_mismatched_checkpoint_is_a_clear_error(tmp_path, small_algo):
    path = tmp_path / "ck.npz"
    save_checkpoint(path, small_algo.init(jax.random.PRNGKey(0)), small_algo.checkpoint_metadata())
    other = MapElites(small_algo.container, planar_arm_evaluate, 5, small_algo.config)
    with pytest.raises(CheckpointError, match="genotype_dim = 4"):
        resume(other, path)
    with pytest.raises(CheckpointError, match=r"repertoire/genotypes' has shape \(64, 4\), expected \(64, 5\)"):
        load_checkpoint(path, other.empty_state(jax.random.PRNGKey(0)))
    bigger = MapElites(small_algo.container, planar_arm_evaluate, 4, MapElitesConfig(batch_size=64, init_size=64))
    with pytest.raises(CheckpointError, match="config"):
        resume(bigger, path)


def test_checkpoint_version_is_checked(tmp_path, small_algo, monkeypatch):
    monkeypatch.setattr(qd_io, "FORMAT_VERSION", 99)
    save_checkpoint(tmp_path / "future.npz", small_algo.empty_state(jax.random.PRNGKey(0)))
    monkeypatch.undo()
    with pytest.raises(CheckpointError, match="version 99 is not supported"):
        resume(small_algo, tmp_path / "future.npz")


def test_failed_write_leaves_the_previous_checkpoint(tmp_path, small_algo, monkeypatch):
    path = tmp_path / "ck.npz"
    state = small_algo.init(jax.random.PRNGKey(0))
    save_checkpoint(path, state, small_algo.checkpoint_metadata())
    before = path.read_bytes()

    def broken_savez(handle, **arrays):
        handle.write(b"PK\x03\x04 half a file")
        raise OSError("disk full")

    monkeypatch.setattr(qd_io.np, "savez", broken_savez)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, state, small_algo.checkpoint_metadata())
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["ck.npz"]  # no temporary file left


# --- plots -------------------------------------------------------------------------------


def test_grid_projection_keeps_the_best_over_hidden_dimensions():
    grid = Grid(bins=(2, 3, 2), low=(0.0,) * 3, high=(1.0,) * 3)
    fitness = np.arange(12, dtype=np.float32)
    filled = np.ones(12, bool)
    filled[[4, 5]] = False  # cell (0, 2, *) empty
    rep = grid.empty(1).replace(fitnesses=jnp.asarray(np.where(filled, fitness, -np.inf)), filled=jnp.asarray(filled))
    proj = grid_projection(grid, rep, (0, 1))
    expected = np.where(filled, fitness, -np.inf).reshape(2, 3, 2).max(axis=2)
    np.testing.assert_array_equal(np.nan_to_num(proj, nan=-1), np.where(np.isfinite(expected), expected, -1))
    assert np.isnan(proj[0, 2])
    np.testing.assert_array_equal(grid_projection(grid, rep, (1, 0)), proj.T)


def test_metrics_plot_is_written(arm_run, tmp_path):
    out = arm_run[3]
    plot_metrics(out / "metrics.csv", path=tmp_path / "metrics.png")
    image = matplotlib.image.imread(tmp_path / "metrics.png")
    assert image.shape[0] > 200 and image.shape[1] > 200 and image.std() > 0.01


# --- command line ------------------------------------------------------------------------


def test_inspect_checkpoint_cli(tmp_path, small_algo):
    path = tmp_path / "ck.npz"
    save_checkpoint(path, small_algo.init(jax.random.PRNGKey(0)), small_algo.checkpoint_metadata())
    cmd = [sys.executable, "-m", "experiments.inspect_checkpoint"]
    ok = subprocess.run([*cmd, str(path)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert "elites: " in ok.stdout and "repertoire/genotypes" in ok.stdout and "generation: 0" in ok.stdout
    path.write_bytes(path.read_bytes()[:100])
    bad = subprocess.run([*cmd, str(path)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2
    assert "truncated or corrupt" in bad.stderr and "Traceback" not in bad.stderr
