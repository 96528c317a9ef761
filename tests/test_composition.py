"""Planned composition (hte_jax.hbr.composition): the beam search against a brute-force NumPy
reference, measured steps against a direct rollout, planned execution of HBR skills, and the step
model's storage."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hte_jax.errors import ConfigError
from hte_jax.hbr.composition import (
    StepModel,
    descriptor_steps,
    measure_steps,
    pattern_table,
    plan_batch,
    plan_step,
    planning_table,
)
from hte_jax.hbr.hierarchy import execute_skill
from hte_jax.geometry import planar_pose, relative_pose
from hte_jax.hbr.middle import MiddleTask
from hte_jax.hbr.store import load_hbr, save_hbr
from hte_jax.online.evaluation import EvalConfig
from hte_jax.online.skills import hbr_skills
from hte_jax.qd.io import CheckpointError, read_checkpoint, save_checkpoint
from hte_jax.sim.robot import load_robot
from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state


TASK = MiddleTask()
YAW_WEIGHT = 0.25


def _compose(base, local):
    c, s = np.cos(base[2]), np.sin(base[2])
    yaw = (base[2] + local[2] + np.pi) % (2 * np.pi) - np.pi
    return np.array([base[0] + c * local[0] - s * local[1], base[1] + s * local[0] + c * local[1], yaw])


def _relative(start, end):
    c, s = np.cos(start[2]), np.sin(start[2])
    dx, dy = end[0] - start[0], end[1] - start[1]
    yaw = (end[2] - start[2] + np.pi) % (2 * np.pi) - np.pi
    return np.array([c * dx + s * dy, -s * dx + c * dy, yaw])


def _normalise(step):  # MiddleTask(): x, y over +-0.5 m, yaw over +-1 rad
    return step / np.array([1.0, 1.0, 2.0]) + 0.5


def _brute_force(steps, penalty, here, target, remaining):
    """Best (cost, first elite) over every sequence of `remaining` elites, by enumeration."""
    moves = (steps - 0.5) * np.array([1.0, 1.0, 2.0])
    weights = np.array([1.0, 1.0, YAW_WEIGHT])
    best = (np.inf, -1)
    for sequence in itertools.product(range(len(steps)), repeat=remaining):
        pose = here
        for k in sequence[:-1]:
            pose = _compose(pose, moves[k])
        last = sequence[-1]
        miss = np.linalg.norm((_normalise(_relative(pose, target)) - steps[last]) * weights)
        best = min(best, (miss + penalty[list(sequence)].sum(), sequence[0]))
    return best


@pytest.fixture(scope="module")
def synthetic():
    rng = np.random.default_rng(3)
    patterns = np.array([5, 9, 5, -1, 9, 5, 9, 5, 5, 9, 5, -1])
    steps = rng.uniform(0.3, 0.7, (patterns.size, 3)).astype(np.float32)
    spread = rng.uniform(0.0, 0.1, patterns.size).astype(np.float32)
    spread[[4, 8]] = np.inf  # no valid measured step: left out of every plan (they are the optima otherwise)
    model = StepModel(steps=jnp.asarray(steps), spread=jnp.asarray(spread))
    return patterns, steps, spread, pattern_table(patterns, model)


@pytest.mark.parametrize("remaining", [1, 2, 3])
def test_plan_is_the_brute_force_optimum(synthetic, remaining):
    patterns, steps, spread, table = synthetic
    here = np.array([0.3, -0.2, 0.4], np.float32)
    target = np.array([0.75, 0.1, -0.3], np.float32)
    for pattern in (5, 9):
        members = np.flatnonzero(patterns == pattern)
        excluded = np.where(np.isfinite(spread[members]), 0.0, np.inf)
        cost, first = _brute_force(steps[members].astype(np.float64), excluded, here, target, remaining)
        index, planned = plan_step(table, TASK, jnp.asarray(here), jnp.asarray(target), jnp.int32(pattern), remaining,
                                   beam=(8, 8), yaw_weight=YAW_WEIGHT)
        assert int(index) == members[first]
        np.testing.assert_allclose(float(planned), cost, rtol=1e-4)


def test_plan_batch_traced_steps_missing_patterns_and_any(synthetic):
    patterns, _, _, table = synthetic
    here = jnp.zeros((4, 3))
    target = jnp.asarray([[0.5, 0.0, 0.0], [0.4, 0.3, 0.2], [0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])
    wanted = jnp.asarray([5, 9, 7, -1], jnp.int32)  # 7 has no elite, -1 asks for no plan
    static = plan_batch(table, TASK, here, target, wanted, 2, beam=(8, 8))
    traced = jax.jit(lambda r: plan_batch(table, TASK, here, target, wanted, r, beam=(8, 8)))(jnp.int32(2))
    np.testing.assert_array_equal(static, traced)
    assert patterns[int(static[0])] == 5 and patterns[int(static[1])] == 9
    assert int(static[2]) == -1 and int(static[3]) == -1


@pytest.fixture(scope="module")
def shipped():
    hbr, top_task, _ = load_hbr()
    return hbr, top_task, load_robot()


@pytest.mark.slow
def test_measured_steps_match_a_direct_rollout(shipped, capsys):
    hbr, _, robot = shipped
    rows = np.arange(5)
    params, filled = hbr.middle_params[rows], hbr.middle.filled[rows]
    start = standing_state(robot)
    model = measure_steps(robot, params, filled, hbr.middle_task, start, jax.random.key(0), starts=1)
    # start 0: one second of the neutral pose, then the elite
    direct = rollout(robot, jnp.stack([jnp.zeros_like(params), params], axis=1), jnp.zeros(6, bool), start,
                     RolloutSpec(num_steps=200, pose_steps=(100, 200), record_contacts=False))
    poses = planar_pose(direct.base_pos, direct.base_quat)
    expected = hbr.middle_task.normalise(relative_pose(poses[:, 0], poses[:, 1]))
    # two XLA programs of the same physics: a few 1e-6 apart on some CPUs (3e-6 on an AVX-512 AMD EPYC)
    np.testing.assert_allclose(model.steps, expected, atol=1e-5)
    np.testing.assert_array_equal(model.spread, np.zeros(5))
    # Empty slots are not simulated and change nothing: 5 more slots, empty, with blocks of 5 samples
    # (the size above) run one block, not two, and the filled slots' steps keep their bits.
    empty = jnp.full((5, params.shape[1]), jnp.nan)
    with_empty = measure_steps(robot, jnp.concatenate([params, empty]),
                               jnp.concatenate([filled, jnp.zeros(5, bool)]), hbr.middle_task, start,
                               jax.random.key(0), starts=1, chunk=5, progress=True)
    np.testing.assert_array_equal(with_empty.steps[:5], model.steps)
    np.testing.assert_array_equal(with_empty.steps[5:], 0.0)
    np.testing.assert_array_equal(with_empty.spread[5:], np.inf)
    assert "1/1" in capsys.readouterr().err  # the progress bar counted one block
    # 3 starts in blocks of 5 samples: 3 blocks of the first call's program (no other compile)
    several = measure_steps(robot, params, filled, hbr.middle_task, start, jax.random.key(0), starts=3, chunk=5)
    assert np.all(np.isfinite(several.spread)) and np.all(np.asarray(several.spread) > 0)
    assert np.all((np.asarray(several.steps) > 0) & (np.asarray(several.steps) < 1))


@pytest.mark.slow
def test_planned_execution_keeps_the_pattern_and_leaves_any_pattern_steps_alone(shipped):
    hbr, top_task, robot = shipped
    slots = np.flatnonzero(np.asarray(hbr.top.filled))[:3]
    genes = hbr.top.genotypes[slots]
    ends = jnp.concatenate([top_task.denormalise(hbr.top.descriptors[slots]), hbr.top.extras["arrival_yaw"][slots, None]],
                           axis=1)
    table = planning_table(hbr)
    starts = jax.tree.map(lambda x: jnp.broadcast_to(x, (3, *x.shape)), standing_state(robot))
    run = jax.jit(lambda g, p, e, t: execute_skill(robot, hbr, g, starts, patterns=p, table=t, ends=e))
    held = jnp.asarray([[63] * 3, [45] * 3, [30] * 3], jnp.int32)
    planned = run(genes, held, ends, table)
    executed = np.asarray(hbr.middle_patterns)[np.asarray(planned.steps.middle_index)]  # (3 steps, 3 skills)
    np.testing.assert_array_equal(executed, np.asarray(held).T)
    anyway = run(genes, jnp.full((3, 3), -1, jnp.int32), ends, table)
    paper = execute_skill(robot, hbr, genes, starts)
    np.testing.assert_array_equal(anyway.steps.middle_index, paper.steps.middle_index)  # the same elites
    np.testing.assert_allclose(anyway.displacement, paper.displacement, atol=1e-5)  # up to the compiler's fusion


@pytest.mark.slow
def test_step_model_is_stored_and_checked(shipped, tmp_path):
    hbr, top_task, _ = shipped
    count = int(np.asarray(hbr.middle.filled).sum())
    model = descriptor_steps(hbr.middle.descriptors)
    model = model.replace(spread=jnp.where(hbr.middle.filled, 0.03, jnp.inf))
    save_hbr(tmp_path / "with.npz", hbr.replace(step_model=model), top_task)
    loaded, _, _ = load_hbr(tmp_path / "with.npz")
    np.testing.assert_array_equal(loaded.step_model.steps[:count], model.steps[:count])
    np.testing.assert_array_equal(loaded.step_model.spread, model.spread)
    save_hbr(tmp_path / "without.npz", hbr.replace(step_model=None), top_task)
    assert load_hbr(tmp_path / "without.npz")[0].step_model is None
    arrays, stored = read_checkpoint(tmp_path / "with.npz")
    arrays["middle_step_spread"] = arrays["middle_step_spread"][:-1]
    save_checkpoint(tmp_path / "bad.npz", arrays, stored["metadata"], compress=True)
    with pytest.raises(CheckpointError, match="middle_step_spread"):
        load_hbr(tmp_path / "bad.npz")


def test_composition_setting_is_checked(shipped):
    hbr, top_task, _ = shipped
    with pytest.raises(ConfigError, match="composition"):
        EvalConfig(composition="straight")
    with pytest.raises(ValueError, match="composition"):
        hbr_skills(hbr, top_task, composition="straight")
    assert hbr_skills(hbr, top_task, composition="waypoints").table is None
    assert hbr_skills(hbr, top_task).table is not None
