"""docs/extending.md: its worked examples run as written and do what they say."""

import json
import re
import sys
import types
from pathlib import Path

import jax
import numpy as np
import pytest

from hte_jax.qd.io import read_checkpoint

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"


def section_code(title: str) -> str:
    """The python code blocks of the `## <title>` section of docs/extending.md, joined."""
    text = DOC.read_text()
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    section = text[start : end if end >= 0 else len(text)]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.DOTALL)
    assert blocks, f"no python block under '## {title}'"
    return "\n".join(blocks)


@pytest.fixture(scope="module")
def variation_example():
    """The namespace left by Example 1's code, run as a module of its own."""
    module = types.ModuleType("extending_example_1")
    sys.modules[module.__name__] = module
    try:
        exec(compile(section_code("Example 1: a new variation operator"), str(DOC), "exec"), module.__dict__)
        yield module.__dict__
    finally:
        del sys.modules[module.__name__]


def test_the_iso_line_example_trains_the_arm(variation_example, capsys):
    ns = variation_example
    algo, start, state = ns["algo"], ns["start"], ns["state"]
    assert algo.emitter is ns["emitter"] and int(state.generation) == 30
    before, after = algo.metrics(start), algo.metrics(state)
    assert int(after.filled) > int(before.filled) + 30  # 64 random arms fill far fewer of the 256 cells
    assert float(after.qd_score) > float(before.qd_score)
    assert float(after.max_fitness) > float(before.max_fitness)
    rep = state.repertoire
    genotypes = np.asarray(rep.genotypes)[np.asarray(rep.filled)]
    assert genotypes.min() >= 0.0 and genotypes.max() <= 1.0
    assert "IsoLineVariation(sigma_iso=0.01, sigma_line=0.2)" in algo.checkpoint_metadata()["emitter"]


def test_iso_line_children_differ_from_their_parents(variation_example):
    rep = variation_example["state"].repertoire
    emitter = variation_example["emitter"]
    slots = []

    def draw_parents(key):
        slots.append(emitter.select(rep, key))
        return rep.genotypes[slots[-1]]

    children = np.asarray(emitter.variation.vary(jax.random.PRNGKey(7), draw_parents))
    parents = np.asarray(rep.genotypes[slots[0]])
    assert len(slots) == 2 and children.shape == parents.shape == (64, 6)
    assert np.all(np.any(children != parents, axis=1))
    assert children.min() >= 0.0 and children.max() <= 1.0


def test_iso_line_matches_the_formula_in_numpy(variation_example):
    """Same random draws, the formula in float64: x + s_iso N(0, I) + s_line N(0, 1) (y - x), clipped."""
    variation = variation_example["IsoLineVariation"](sigma_iso=0.05, sigma_line=0.5)
    pool = jax.random.uniform(jax.random.PRNGKey(1), (40, 7))

    def draw_parents(key):
        return pool[jax.random.randint(key, (32,), 0, 40)]

    key = jax.random.PRNGKey(2)
    got = np.asarray(variation.vary(key, draw_parents))
    key_x, key_y, key_iso, key_line = jax.random.split(key, 4)
    x, y = (np.asarray(draw_parents(k), np.float64) for k in (key_x, key_y))
    iso = np.asarray(jax.random.normal(key_iso, (32, 7)), np.float64)
    line = np.asarray(jax.random.normal(key_line, (32, 1)), np.float64)
    want = np.clip(x + 0.05 * iso + 0.5 * line * (y - x), 0.0, 1.0)
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert np.any((want == 0.0) | (want == 1.0)) and np.any((want > 0.0) & (want < 1.0))  # both branches of the clip


@pytest.mark.slow
def test_the_new_variant_example_runs_its_own_rule_through_maze_eval(tmp_path, monkeypatch):
    from hte_jax.online import variants
    from hte_jax.online.rules import CANDIDATE_PATTERNS

    monkeypatch.chdir(tmp_path)
    module = types.ModuleType("extending_example_2")
    try:
        exec(compile(section_code("Example 2: a new adaptation variant"), str(DOC), "exec"), module.__dict__)
        assert module.status == 0
        assert type(variants.variant("hte-mean").rule).__name__ == "GpMean"
        run = tmp_path / "runs" / "hte-mean"
        summary = json.loads((run / "summary.json").read_text())
        assert set(summary["variants"]) == {"hte-mean", "hte"}
        labels = [record["variant"] for record in json.loads((run / "episodes.json").read_text())["episodes"]]
        arrays, _ = read_checkpoint(run / "episodes_0.npz")
        patterns, taken = np.asarray(arrays["patterns"]), np.asarray(arrays["taken"])
        row = labels.index("hte-mean")
        chosen = patterns[row, : taken[row]]
        assert taken[row] >= 1 and set(chosen.ravel().tolist()) <= set(CANDIDATE_PATTERNS.tolist())
    finally:  # the registry is global: leave it as the other tests expect it
        variants.VARIANTS.pop("hte-mean", None)


@pytest.mark.slow
def test_the_new_task_example_trains_saves_and_loads_its_repertoire(tmp_path, monkeypatch, capsys):
    from hte_jax.qd import Grid, TaskSpec, load_repertoire
    from hte_jax.qd.io import CheckpointError

    monkeypatch.chdir(tmp_path)
    module = types.ModuleType("extending_example_3")
    exec(compile(section_code("Example 3: a new QD task"), str(DOC), "exec"), module.__dict__)
    ns = module.__dict__
    state, loaded, spec = ns["state"], ns["loaded"], ns["spec"]
    assert int(state.generation) == 4 and ns["header"]["generations"] == 4
    assert ns["header"]["task"]["name"] == "duty-gaits" and ns["algo"].config.qd_offset == -1.0
    for name, saved, back in zip(("genotypes", "descriptors", "fitnesses", "filled", "extras"),
                                 (state.repertoire.genotypes, state.repertoire.descriptors, state.repertoire.fitnesses,
                                  state.repertoire.filled, state.repertoire.extras["leg_duty"]),
                                 (loaded.genotypes, loaded.descriptors, loaded.fitnesses, loaded.filled,
                                  loaded.extras["leg_duty"])):
        np.testing.assert_array_equal(np.asarray(back), np.asarray(saved), err_msg=name)
    filled = np.asarray(loaded.filled)
    assert 0 < filled.sum() <= spec.capacity == 64
    descriptors, duty = np.asarray(loaded.descriptors)[filled], np.asarray(loaded.extras["leg_duty"])[filled]
    assert descriptors.min() >= 0.0 and descriptors.max() <= 1.0 and duty.min() >= 0.0 and duty.max() <= 1.0
    np.testing.assert_allclose(descriptors, duty[:, [[0, 5], [1, 4], [2, 3]]].mean(axis=-1), atol=1e-6)
    assert len(np.unique(descriptors.round(6), axis=0)) == filled.sum()  # one elite per cell, as stored
    fitness = np.asarray(loaded.fitnesses)[filled]
    assert np.isfinite(fitness).all() and np.abs(fitness).max() < 1.0  # metres in one second
    printed = capsys.readouterr().out
    assert f"{filled.sum()} of 64 cells filled" in printed and "(hind)" in printed
    other = TaskSpec(spec.name, spec.genotype_dim, Grid((5, 5, 5), (0.0,) * 3, (1.0,) * 3), extras=spec.extras)
    with pytest.raises(CheckpointError, match="container"):
        load_repertoire(tmp_path / "runs" / "duty-gaits" / "repertoire.npz", other)


@pytest.mark.slow
def test_the_executor_example_drives_native_mujoco_to_the_goal(capsys):
    from hte_jax.online.action import SECONDS_PER_ACTION
    from hte_jax.online.maze import PAPER_MAZE

    module = types.ModuleType("extending_example_4")
    exec(compile(section_code("Example 4: a new executor"), str(DOC), "exec"), module.__dict__)
    episode, robot = module.episode, module.robot
    taken = int(episode.taken[0])
    assert "reached the goal: True, after" in capsys.readouterr().out
    assert episode.sim is None and bool(episode.reached[0]) and not bool(episode.broken[0])
    assert 1 <= taken <= module.config.max_actions
    # The episode's record is the native robot's: it ends where the robot stands, at the goal.
    track = np.asarray(episode.trajectory[0])
    np.testing.assert_array_equal(track[SECONDS_PER_ACTION * taken], robot.pose())
    assert np.linalg.norm(robot.pose()[:2] - np.asarray(PAPER_MAZE.goal)) < PAPER_MAZE.goal_radius
    np.testing.assert_allclose(track[0, :2], PAPER_MAZE.start[:2], atol=1e-6)  # it started at the maze's start
    np.testing.assert_allclose(np.cos(track[0, 2] - PAPER_MAZE.start[2]), 1.0, atol=1e-6)
    # Every step took RTE's any pattern until a leg was sensed off the floor, then leg 1's pattern.
    patterns = np.asarray(episode.history.patterns[0, :taken])
    assert set(patterns.ravel().tolist()) <= {-1, 0b101111} and (patterns[-1] == 0b101111).all()


@pytest.mark.slow
def test_the_damage_example_registers_a_heavy_leg_that_the_rollout_runs(capsys):
    from hte_jax.sim import damage

    namespace: dict = {}
    try:
        exec(compile(section_code("Example 5: a new damage"), str(DOC), "exec"), namespace)
        printed = capsys.readouterr().out.splitlines()
        assert printed == ["added 0.3644 kg", "True"]  # the doc's comments
        heavy = namespace["heavy"]
        assert int(heavy.model) == list(damage.DAMAGE_PARTS).index("heavy")
        # Its edit changes only leg 0's tibia; the other models' edits leave the robot alone.
        robot = namespace["robot"]
        edited = np.asarray(damage.edited_model(robot.model, heavy, robot.info).body_mass)
        changed = np.flatnonzero(edited != np.asarray(robot.model.body_mass))
        assert changed.tolist() == [robot.info.leg_bodies[0][2]]
        with pytest.raises(damage.ConfigError, match="exists"):
            damage.register_damage(namespace["Heavy"]("heavy"))
    finally:
        damage.DAMAGE_PARTS.pop("heavy", None)
