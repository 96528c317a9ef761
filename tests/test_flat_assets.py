"""The flat repertoires shipped in assets/flat_gpu (issue 5): trained by train_flat with the gpu preset."""

import dataclasses
import json

import matplotlib.image
import numpy as np
import pytest

from hte_jax.flat.plots import contact_pattern_counts, plot_flat
from hte_jax.flat.store import load_flat, shipped_flat_path
from hte_jax.flat.training import FlatConfig, flat_statistics, preset
from hte_jax.hbr.middle import pattern_code
from hte_jax.sim.damage import APROL_DAMAGES
from hte_jax.sim.robot import LEGACY_SOLVER, SOLVER_FIELDS, SolverConfig


@pytest.mark.parametrize("variant", ["2d", "8d", pytest.param("aprol", marks=pytest.mark.slow)])
def test_shipped_flat_sets_are_the_gpu_preset_as_trained(variant):
    path = shipped_flat_path(variant)
    flat, meta = load_flat(path)
    # trained before the solver was a setting, i.e. with 4 / 8 (the file is as written then)
    config = dataclasses.replace(preset("gpu", variant), solver=SolverConfig(*LEGACY_SOLVER))
    stored = {k: v for k, v in config.to_dict().items() if k not in SOLVER_FIELDS}
    assert meta["training"]["config"] == stored and flat.task == config.task
    assert FlatConfig.from_dict(meta["training"]["config"]) == config
    folder = path.parent / variant
    assert json.loads((folder / "config.json").read_text()) == stored
    summary = json.loads((folder / "summary.json").read_text())
    # the file holds exactly what the training run reported (no edits after training)
    stats = flat_statistics(flat)
    assert stats.keys() == summary["statistics"].keys()
    for name, row in stats.items():
        assert row["size"] == summary["statistics"][name]["size"] > 0
        assert np.isclose(row["mean_fitness"], summary["statistics"][name]["mean_fitness"])
    rows = (folder / "metrics.csv").read_text().strip().splitlines()
    assert int(rows[-1].split(",")[3]) == sum(row["size"] for row in stats.values())  # filled, last block
    assert path.stat().st_size < 10 * 2**20
    for png in (folder / "plots").glob("*.png"):
        assert png.stat().st_size > 10_000


def test_shipped_8d_set_spans_many_contact_patterns():
    flat, _ = load_flat(shipped_flat_path("8d"))
    rep = flat[0]
    filled = np.asarray(rep.filled)
    codes = np.asarray(pattern_code(np.asarray(rep.descriptors)[filled, 2:]))
    assert len(np.unique(codes)) >= 30
    stats = flat_statistics(flat)["none"]
    assert stats["effective_size"] < stats["size"]  # 8-D elites collapse onto fewer x-y cells


def test_figures_of_the_shipped_8d_set(tmp_path):
    """A training run's figures of a set: its x-y map, its contact patterns (one count per elite) and its curves."""
    path = shipped_flat_path("8d")
    flat, _ = load_flat(path)
    counts = contact_pattern_counts(flat, 0)
    assert counts.shape == (64,) and counts.sum() == int(np.asarray(flat[0].filled).sum())
    plot_flat(flat, path.parent / "8d" / "metrics.csv", tmp_path)
    for name in ("xy_fitness", "contact_patterns", "metrics"):
        image = matplotlib.image.imread(tmp_path / f"{name}.png")
        assert image.ndim == 3 and image.shape[0] > 100 and image.std() > 0, name


@pytest.mark.slow
def test_shipped_aprol_set_has_one_repertoire_per_damage_with_those_legs_lifted():
    flat, _ = load_flat(shipped_flat_path("aprol"))
    assert flat.damages == tuple(APROL_DAMAGES)
    for r, mask in enumerate(flat.damage_masks):
        rep = flat[r]
        filled = np.asarray(rep.filled)
        fraction = np.asarray(rep.extras["contact_fraction"])[filled]
        assert filled.sum() > 100
        assert (fraction[:, mask] == 0).all(), flat.damages[r]
        assert fraction[:, ~mask].mean() > 0.3, flat.damages[r]
