"""The HBR shipped in assets/ (acceptance 2 and 3): trained by train_hbr with the gpu preset."""

import dataclasses
import json

import matplotlib.image
import numpy as np
import pytest

from hte_jax.hbr import PRESETS, hbr_statistics, load_hbr, shipped_hbr_path
from hte_jax.hbr.plots import plot_hbr
from hte_jax.hbr.training import HBRConfig
from hte_jax.sim.robot import LEGACY_SOLVER, SolverConfig


@pytest.fixture(scope="module")
def shipped():
    return load_hbr()


def test_shipped_hbr_is_the_gpu_preset_and_covers_the_map(shipped):
    hbr, top_task, meta = shipped
    folder = shipped_hbr_path().parent
    # Read through today's HBRConfig: settings added after training take their (old-behaviour) defaults,
    # the solver the 4 / 8 it was trained with.
    trained = dataclasses.replace(PRESETS["gpu"], solver=SolverConfig(*LEGACY_SOLVER))
    assert HBRConfig.from_dict(meta["training"]["config"]) == trained
    assert HBRConfig.from_dict(json.loads((folder / "config.json").read_text())) == trained
    stats = hbr_statistics(hbr)
    # Acceptance: >= 2500 of the 10 000 top cells, >= 30 distinct contact patterns in the middle.
    assert stats["top"]["capacity"] == 10_000
    assert stats["top"]["elites"] >= 2500
    assert stats["middle"]["contact_patterns"] >= 30
    # The file's statistics are the ones the training run reported (no edits after training).
    summary = json.loads((folder / "summary.json").read_text())
    for layer in ("bottom", "middle", "top"):
        assert stats[layer]["elites"] == summary["statistics"][layer]["elites"]
        assert np.isclose(stats[layer]["mean_fitness"], summary["statistics"][layer]["mean_fitness"])
        rows = (folder / layer / "metrics.csv").read_text().strip().splitlines()
        assert int(rows[-1].split(",")[3]) == stats[layer]["elites"]  # filled, last block
    assert top_task.bins == 100 and top_task.extent == 1.5
    assert shipped_hbr_path().stat().st_size < 4 * 2**20
    for name in ("top_xy_fitness", "middle_xy_yaw_patterns", "bottom_projections"):
        assert (folder / "plots" / f"{name}.png").stat().st_size > 10_000


def test_shipped_top_skills_use_many_middle_motions(shipped):
    hbr, _, _ = shipped
    stats = hbr_statistics(hbr)
    filled = np.asarray(hbr.top.filled)
    used = np.asarray(hbr.top.extras["middle_indices"])[filled]
    assert used.max() < stats["middle"]["elites"]
    assert stats["top"]["distinct_middle_elites_used"] > 1000
    # Every stored top elite's genes are three middle primary descriptors in [0, 1].
    genes = np.asarray(hbr.top.genotypes)[filled]
    assert genes.shape[1] == 9 and genes.min() >= 0 and genes.max() <= 1


def test_figures_of_the_shipped_hbr(shipped, tmp_path):
    """A training run's figures of an HBR: each layer's map, and each layer's curves from its run folder."""
    hbr, top_task, _ = shipped
    plot_hbr(hbr, top_task, shipped_hbr_path().parent, tmp_path)
    for name in ("top_xy_fitness", "middle_xy_yaw_patterns", "bottom_projections", "bottom_metrics", "middle_metrics",
                 "top_metrics"):
        image = matplotlib.image.imread(tmp_path / f"{name}.png")
        assert image.ndim == 3 and image.shape[0] > 100 and image.std() > 0, name
