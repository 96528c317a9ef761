"""Secondary-descriptor modulation (paper Fig. 4 / 5): counts on hand-made cases and on real
re-executions of shipped skills, checked against direct hierarchical execution."""

import json

import jax
import jax.numpy as jnp
import matplotlib.image
import numpy as np
import pytest

from experiments.modulation import main as modulation_main
from hte_jax.hbr.composition import planning_table, skill_ends
from hte_jax.hbr.hierarchy import STEPS_PER_SKILL, execute_skill
from hte_jax.hbr.middle import pattern_code
from hte_jax.hbr.modulation import Modulation, spread_skills
from hte_jax.sim import load_robot, standing_state


def _hand_case() -> Modulation:
    # 2 skills in cells 5 and 7, 3 wanted patterns (63, 62, 0)
    return Modulation(
        slots=np.array([5, 7]),
        patterns=np.array([63, 62, 0]),
        target_xy=np.array([[0.0, 0.0], [1.0, 0.0]]),
        final_xy=np.array([[[0.0, 0.03], [0.0, 0.5], [0.04, 0.0]], [[1.0, 0.2], [1.0, 0.0], [1.0, 0.06]]]),
        measured=np.array([[63, 62, 3], [63, 63, 0]]),
        valid=np.array([[True, True, True], [True, True, False]]),
        available=np.ones((2, 3), bool),
        final_cell=np.array([[5, 9, 5], [8, 7, -1]]),
    )


def test_counts_hand_case():
    mod = _hand_case()
    np.testing.assert_array_equal(mod.shows_pattern, [[True, True, False], [True, False, False]])
    np.testing.assert_array_equal(mod.reaches(), [[True, False, True], [False, True, False]])
    counts = mod.counts()
    np.testing.assert_array_equal(counts["shows"], [2, 1])
    np.testing.assert_array_equal(counts["reaches"], [2, 1])
    np.testing.assert_array_equal(counts["both"], [1, 0])
    np.testing.assert_allclose(counts["median_error"], [np.median([0.03, 0.5]), 0.2])
    near = mod.counts(radius=0.05)  # within 5 cm instead of the same cell
    np.testing.assert_array_equal(near["reaches"], [2, 1])  # the invalid execution never counts
    np.testing.assert_array_equal(near["both"], [1, 0])
    summary = mod.summary()
    assert summary["skills_showing_each_pattern"] == [2, 1, 0] and summary["feasible_patterns"] == 2
    assert summary["mean_patterns_both_per_skill"] == 0.5


def test_spread_skills_take_one_skill_per_patch():
    """On a full 16 x 16 grid, 16 skills are one per 4 x 4 block and 64 one per 2 x 2 block."""
    cells = np.stack(np.meshgrid(np.arange(16), np.arange(16), indexing="ij"), axis=-1).reshape(-1, 2)
    descriptors, filled = (cells + 0.5) / 16, np.ones(256, bool)
    for seed in range(5):
        for count, side in ((16, 4), (64, 2)):
            chosen = spread_skills(filled, descriptors, count, seed)
            blocks = {tuple(block) for block in cells[chosen] // side}
            assert chosen.size == count and len(blocks) == count  # every block once
    assert len({tuple(spread_skills(filled, descriptors, 16, seed)) for seed in range(5)}) > 1  # the seed draws
    filled[::3] = False
    np.testing.assert_array_equal(spread_skills(filled, descriptors, 500, 0), np.flatnonzero(filled))
    assert filled[spread_skills(filled, descriptors, 30, 0)].all()


def test_spread_skills_cover_the_shipped_map(shipped_hbr):
    """Unlike the first skills by cell (one strip of the map), a sample spans the whole map and
    sits as far from the centre as the skills do on average."""
    hbr, task = shipped_hbr
    filled, descriptors = np.asarray(hbr.top.filled), np.asarray(hbr.top.descriptors)
    everything = descriptors[filled]
    span = everything.max(axis=0) - everything.min(axis=0)
    first = descriptors[np.flatnonzero(filled)[:48]]
    assert ((first.max(axis=0) - first.min(axis=0)) / span).min() < 0.2
    radius = np.linalg.norm(np.asarray(task.denormalise(everything)), axis=-1).mean()
    for seed in range(5):
        sample = descriptors[spread_skills(filled, descriptors, 48, seed)]
        assert ((sample.max(axis=0) - sample.min(axis=0)) / span).min() > 0.8
        assert abs(np.linalg.norm(np.asarray(task.denormalise(sample)), axis=-1).mean() / radius - 1) < 0.1


@pytest.mark.slow
def test_reexecutions_match_direct_hierarchical_execution(tmp_path, shipped_hbr):
    out = tmp_path / "mod"
    assert modulation_main(["--skills", "2", "--seed", "3", "--chunk", "64", "--out", str(out), "--no-progress"]) == 0
    mod = Modulation.load(out / "modulation.npz")
    assert mod.final_xy.shape == (2, 64, 2) and mod.patterns.tolist() == list(range(64))
    data = json.loads((out / "modulation.json").read_text())
    assert data["per_skill"]["shows"] == mod.counts()["shows"].tolist()
    assert data["summary"]["skills"] == 2
    hbr, task = shipped_hbr
    filled = int(np.asarray(hbr.top.filled).sum())
    assert data["sample"] == {"skills": 2, "of": filled, "seed": 3}
    assert mod.slots.tolist() == spread_skills(hbr.top.filled, hbr.top.descriptors, 2, seed=3).tolist()
    for name in ("modulation_map", "modulation_grid"):
        image = matplotlib.image.imread(out / f"{name}.png")
        assert image.ndim == 3 and image.std() > 0
    # two (skill, pattern) pairs re-executed directly with the pattern held for the 3 steps, each
    # step planned to the skill's end (the CLI's default composition)
    robot = load_robot()
    pairs = [(0, 63), (1, 27)]
    slots = np.array([mod.slots[s] for s, _ in pairs])
    genes = hbr.top.genotypes[slots]
    ends = skill_ends(hbr.top.descriptors[slots], hbr.top.extras["arrival_yaw"][slots], task.extent)
    held = jnp.asarray([[p] * STEPS_PER_SKILL for _, p in pairs], jnp.int32)
    start = jax.tree.map(lambda x: jnp.broadcast_to(x, (2, *x.shape)), standing_state(robot))
    skill = execute_skill(robot, hbr, genes, start, patterns=held, table=planning_table(hbr), ends=ends)
    shown = np.asarray(pattern_code((skill.steps.contact_fraction.mean(axis=0) > 0.3).astype(jnp.float32)))
    for row, (s, p) in enumerate(pairs):
        np.testing.assert_allclose(mod.final_xy[s, p], np.asarray(skill.displacement[row, :2]), atol=2e-3)
        assert mod.measured[s, p] == shown[row]
    # the skills' stored final positions are their top-layer descriptors
    np.testing.assert_allclose(mod.target_xy, np.asarray(task.denormalise(hbr.top.descriptors[mod.slots])), atol=1e-6)
    # re-plotting from the saved data gives the same counts, with a radius
    again = tmp_path / "again"
    assert modulation_main(["--data", str(out / "modulation.npz"), "--radius", "0.1", "--out", str(again)]) == 0
    assert json.loads((again / "modulation.json").read_text())["per_skill"]["shows"] == data["per_skill"]["shows"]


def test_the_cli_replots_saved_data_without_simulating(tmp_path, capsys):
    """--data: the figures and counts of a modulation.npz written earlier (here the hand case), nothing re-run."""
    mod = _hand_case()
    mod.save(tmp_path / "hand.npz")
    out = tmp_path / "replot"
    assert modulation_main(["--data", str(tmp_path / "hand.npz"), "--radius", "0.05", "--out", str(out)]) == 0
    data = json.loads((out / "modulation.json").read_text())
    assert data["per_skill"]["both"] == mod.counts(0.05)["both"].tolist() and data["composition"] is None
    assert data["per_skill"]["slot"] == [5, 7] and not (out / "modulation.npz").exists()
    for name in ("modulation_map", "modulation_grid"):
        image = matplotlib.image.imread(out / f"{name}.png")
        assert image.ndim == 3 and image.std() > 0
    assert f"wrote figures and data under {out}" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["--skills", "0"], "--skills must be >= 1"),
    (["--skills", "some"], "--skills must be a positive integer or all"),
    (["--radius", "-1"], "--radius"),
    (["--hbr", "/nowhere/hbr.npz"], "no such checkpoint"),
])
def test_modulation_cli_errors(args, message, tmp_path, capsys):
    assert modulation_main([*args, "--out", str(tmp_path)]) == 2
    assert message in capsys.readouterr().err
