"""Measured pattern ends (hte_jax.hbr.pattern_ends): the planner's priors against a NumPy loop, the
measurement against direct skill execution, the file's checks, and the variants that plan with
them (no usable end: the stored outcomes; otherwise each observation learnt against the measured end)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.hbr.composition import skill_ends
from hte_jax.hbr.execution import STEPS_PER_SKILL, execute_skill
from hte_jax.hbr.pattern_ends import (
    PatternEnds,
    load_pattern_ends,
    measure_pattern_ends,
    planning_priors,
    save_pattern_ends,
    skills_fingerprint,
)
from hte_jax.hbr.sparing import sparing_table
from hte_jax.hbr.store import load_hbr, load_spare, spare_beside
from hte_jax.online import variants
from hte_jax.online.evaluation import EvalConfig, run_batch
from hte_jax.online.execute import hbr_skills
from hte_jax.online.mcts import PlannerConfig
from hte_jax.qd.io import CheckpointError
from hte_jax.sim.robot import RobotConfig, load_robot
from hte_jax.sim.rollout import standing_state


@pytest.fixture(scope="module")
def shipped():
    """The shipped HBR with its spare archive (as the sparing variants load it)."""
    hbr, task, _ = load_hbr()
    spare = spare_beside(None)
    return (load_spare(spare, hbr) if spare else hbr), task


def test_planning_priors_match_a_loop():
    rng = np.random.default_rng(0)
    slots = np.array([4, 9, 2, 7])
    ends = PatternEnds(patterns=np.array([47, 61, 45]), slots=slots, ends=rng.normal(size=(3, 4, 3)).astype(np.float32),
                       valid=rng.random((3, 4)) > 0.3, table="sparing", fingerprint="x")
    action_slots = np.array([9, 7, 5, 4, -1, 12, 0])  # slots 5, 12, 0 were not measured; -1 is padding
    stored = rng.normal(size=(7, 4)).astype(np.float32)
    priors = planning_priors(ends, action_slots, stored)
    assert priors.shape == (64, 7, 4)
    nothing = PatternEnds(patterns=np.array([47]), slots=np.zeros(0, int), ends=np.zeros((1, 0, 3), np.float32),
                          valid=np.zeros((1, 0), bool), table="sparing", fingerprint="x")
    np.testing.assert_array_equal(planning_priors(nothing, action_slots, stored), np.broadcast_to(stored, (64, 7, 4)))
    for pattern in range(64):
        for a, slot in enumerate(action_slots):
            expected = stored[a]
            if pattern in ends.patterns.tolist() and slot in slots.tolist():
                k, n = ends.patterns.tolist().index(pattern), slots.tolist().index(slot)
                if ends.valid[k, n]:
                    dx, dy, dyaw = ends.ends[k, n]
                    expected = np.array([dx, dy, np.cos(dyaw), np.sin(dyaw)], np.float32)
            np.testing.assert_allclose(priors[pattern, a], expected, rtol=1e-6, atol=1e-7)


def test_measurement_equals_direct_execution_and_the_file_checks_its_hbr(shipped, tmp_path):
    hbr, task = shipped
    table = sparing_table(hbr)
    robot = load_robot(RobotConfig())
    start = standing_state(robot)
    slots = np.flatnonzero(np.asarray(hbr.top.filled))[[0, 500, 1000]]
    patterns = np.array([47, 61])
    # 6 executions in chunks of 4: the second chunk wraps round
    ends = measure_pattern_ends(robot, hbr, task, start, table, "sparing", patterns, skills=slots, chunk=4, progress=False)
    assert ends.ends.shape == (2, 3, 3) and ends.valid.all()
    pair_slots, pair_patterns = np.tile(slots, 2), np.repeat(patterns, 3)
    stored = skill_ends(hbr.top.descriptors[pair_slots], hbr.top.extras["arrival_yaw"][pair_slots], task.extent)
    starts = jax.tree.map(lambda x: jnp.broadcast_to(x, (6, *x.shape)), start)
    direct = execute_skill(robot, hbr, hbr.top.genotypes[pair_slots], starts,
                           patterns=jnp.repeat(jnp.asarray(pair_patterns, jnp.int32)[:, None], STEPS_PER_SKILL, axis=1),
                           table=table, ends=stored)
    np.testing.assert_allclose(ends.ends.reshape(6, 3), np.asarray(direct.displacement), atol=1e-5)
    # round trip, and the checks of a file that belongs to other skills
    path = tmp_path / "ends.npz"
    save_pattern_ends(path, ends)
    loaded = load_pattern_ends(path, hbr)
    np.testing.assert_array_equal(loaded.ends, ends.ends)
    assert loaded.table == "sparing" and loaded.fingerprint == skills_fingerprint(hbr)
    other = hbr.replace(top=hbr.top.replace(genotypes=hbr.top.genotypes.at[slots[0], 0].add(0.1)))
    with pytest.raises(CheckpointError, match="other skills"):
        load_pattern_ends(path, other)
    with pytest.raises(CheckpointError, match="not a pattern-ends file"):
        save_pattern_ends_kind = tmp_path / "bad.npz"
        from hte_jax.qd.io import save_checkpoint
        save_checkpoint(save_pattern_ends_kind, {"x": np.zeros(1)}, {"kind": "something"})
        load_pattern_ends(save_pattern_ends_kind)


def test_measured_variants_are_entries_that_need_sparing_ends(shipped):
    hbr, task = shipped
    entry = variants.variant("hte-measured")
    assert entry.measured_ends and entry.sparing and entry.rule == "sensed"
    assert variants.variant("perfect-measured").rule == "oracle"
    with pytest.raises(ConfigError, match="no contact patterns"):
        variants.add_variant(variants.Variant("flat-measured", repertoire="2d", measured_ends=True, summary="x"))
    assert hbr_skills(hbr, task).priors is None


def test_measured_variant_plans_and_learns_against_the_measured_ends(shipped, tmp_path):
    hbr, task = shipped
    slots = np.flatnonzero(np.asarray(hbr.top.filled))
    stored = np.asarray(skill_ends(hbr.top.descriptors[slots], hbr.top.extras["arrival_yaw"][slots], task.extent))
    patterns = np.array([47])  # leg 1 lifted
    fingerprint = skills_fingerprint(hbr)
    config = EvalConfig(damages="leg1", replicates=1, max_actions=3, planner=PlannerConfig(iterations=50, roots=1),
                        damage_model="raised")

    def run(valid: bool, shift: float, names=("hte-spare", "hte-measured")):
        ends = PatternEnds(patterns=patterns, slots=slots.astype(np.int32),
                           ends=(stored + np.array([shift, 0.0, 0.0], np.float32))[None].astype(np.float32),
                           valid=np.full((1, slots.size), valid), table="sparing", fingerprint=fingerprint)
        path = tmp_path / f"ends_{valid}.npz"
        save_pattern_ends(path, ends)
        result = run_batch(dataclasses.replace(config, pattern_ends=str(path)), None, list(names), progress=False)
        return result.episodes

    # no usable end: every episode plans with the stored outcomes, whatever its last pattern
    ends = PatternEnds(patterns=patterns, slots=slots.astype(np.int32), ends=stored[None].astype(np.float32),
                       valid=np.zeros((1, slots.size), bool), table="sparing", fingerprint=fingerprint)
    skills = hbr_skills(hbr, task, sparing=True, ends=ends)
    learnt = variants.PatternState(mode=None, oracle=None, optimism=None, secondary=None, contacts=None, motion=None,
                                   sparing=None, measured=jnp.array([True, True, False]),
                                   last=jnp.array([47, -1, 47], jnp.int32))
    np.testing.assert_array_equal(skills.planning_prior(learnt), np.broadcast_to(skills.actions.prior, (3, *skills.actions.prior.shape)))
    shifted = run(True, 0.3)  # every end 0.3 m further in x under leg 1's pattern
    measured_prior = np.asarray(hbr_skills(hbr, task, sparing=True, ends=PatternEnds(
        patterns=patterns, slots=slots.astype(np.int32), ends=(stored + np.array([0.3, 0.0, 0.0], np.float32))[None],
        valid=np.ones((1, slots.size), bool), table="sparing", fingerprint=fingerprint)).planning_prior(learnt))
    np.testing.assert_allclose(measured_prior[0, :, 0], skills.actions.prior[:, 0] + 0.3, atol=1e-5)  # measured, pattern 47
    np.testing.assert_array_equal(measured_prior[1:], np.asarray(skills.planning_prior(learnt))[1:])  # no pattern yet / not measured
    actions = np.asarray(shifted.history.action[1])
    last = np.asarray(shifted.history.patterns[1])[:, -1]
    taken = int(shifted.taken[1])
    assert taken >= 2 and (last[: taken - 1] == 47).any(), "the sensed rule should lift leg 1 within the first actions"
    # each observation is learnt against the prior it was planned with: the stored end until a step
    # ran with leg 1's pattern, then that pattern's measured end
    observed_prior = np.asarray(shifted.rte.prior[1, 0])  # (L, 4)
    for a in range(taken):
        expected_x = stored[actions[a], 0] + (0.3 if a > 0 and last[a - 1] == 47 else 0.0)
        assert abs(observed_prior[a, 0] - expected_x) < 1e-4, (a, observed_prior[a, 0], expected_x)
