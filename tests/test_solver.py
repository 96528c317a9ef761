"""The physics' solver settings: the default holds its fidelity budget against a converged
reference, every CLI can set them, and configurations stored before they were settings keep the
solver they ran with (4 / 8)."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

from experiments.train_flat import main as flat_main
from experiments.train_hbr import main as hbr_main
from hte_jax.errors import ConfigError
from hte_jax.flat.store import load_flat, shipped_flat_path
from hte_jax.flat.training import FlatConfig
from hte_jax.flat.training import normalised_config as flat_normalised
from hte_jax.flat.training import preset as flat_preset
from hte_jax.geometry import planar_pose
from hte_jax.hbr.training import PRESETS, HBRConfig, normalised_config
from hte_jax.online.evaluation import EvalConfig
from hte_jax.qd.io import prepare_run_dir
from hte_jax.sim.damage import paper_damage_masks
from hte_jax.sim.robot import FOOT_RADIUS, LEGACY_SOLVER, SOLVER_FIELDS, RobotConfig, SolverConfig, load_robot, mj_model
from hte_jax.sim.rollout import rollout, standing_state
from tests.test_rollout import SPEC  # test_rollout's 3 s spec at its batch shape (16)

# Converged: doubling both counts changes no final position (benchmarks/physics_frontier.py).
REFERENCE = RobotConfig(solver_iterations=20, ls_iterations=20)
OLD = dict(zip(SOLVER_FIELDS, LEGACY_SOLVER))


def _final(config: RobotConfig, params: np.ndarray, damages: np.ndarray):
    """Final planar pose, validity and deepest foot penetration of 3 s rollouts from the standing state."""
    robot = load_robot(config)
    damages = jnp.asarray(damages)
    result = rollout(robot, jnp.asarray(params), damages, standing_state(robot, damages), SPEC)
    pose = np.asarray(planar_pose(result.base_pos[:, -1], result.base_quat[:, -1]))
    depth = FOOT_RADIUS - np.asarray(result.foot_pos)[..., 2].min(axis=(1, 2))
    return pose, np.asarray(result.valid), depth


@pytest.mark.slow
def test_default_solver_holds_its_fidelity_budget():
    """32 random controllers for 3 s, intact and with the paper's damages in turn, against the
    converged solver: the budget of docs/design.md (final position median <= 1 cm, p90 <= 3 cm,
    no rollout invalid that the reference keeps valid, max foot penetration within 1 mm)."""
    params = np.random.default_rng(7).uniform(size=(16, 36)).astype(np.float32)
    cases = (np.zeros((16, 6), bool), paper_damage_masks()[np.arange(16) % 7])
    runs = []
    for config in (RobotConfig(), REFERENCE):
        parts = [_final(config, params, damages) for damages in cases]
        runs.append([np.concatenate(column) for column in zip(*parts)])
    (pose, valid, depth), (ref_pose, ref_valid, ref_depth) = runs
    assert not (ref_valid & ~valid).any()
    both = valid & ref_valid
    assert both.sum() >= 28
    error = np.linalg.norm(pose[both, :2] - ref_pose[both, :2], axis=1)
    assert np.median(error) <= 0.01 and np.percentile(error, 90) <= 0.03, error
    assert depth[both].max() <= ref_depth[both].max() + 0.001


@pytest.mark.slow
def test_shipped_elites_run_under_the_default_as_under_the_solver_they_were_trained_with():
    """Acceptance 4 of the solver issue: the default's line-search cap (4) never binds where 4 / 8
    stopped earlier, so 16 shipped Flat-2D elites end exactly where they end under 4 / 8."""
    flat, _ = load_flat(shipped_flat_path("2d"))
    rows = np.flatnonzero(np.asarray(flat[0].filled))[:: 97][:16]
    params = np.asarray(flat[0].genotypes)[rows]
    intact = np.zeros((len(rows), 6), bool)
    (pose, valid, _), (old_pose, old_valid, _) = (_final(config, params, intact) for config in (RobotConfig(), RobotConfig(**OLD)))
    assert len(rows) == 16 and valid.all() and (valid == old_valid).all()
    np.testing.assert_allclose(pose, old_pose, atol=1e-5)


def test_solver_settings_reach_the_model():
    model = mj_model(RobotConfig(solver_iterations=3, ls_iterations=5, solver_tolerance=1e-6))
    assert (model.opt.iterations, model.opt.ls_iterations, model.opt.tolerance) == (3, 5, pytest.approx(1e-6))
    assert mj_model(RobotConfig()).opt.tolerance == pytest.approx(1e-8)  # MuJoCo's default, unchanged
    with pytest.raises(ConfigError, match="solver_tolerance"):
        RobotConfig(solver_tolerance=-1.0)
    robot = EvalConfig(solver=SolverConfig(solver_iterations=4, ls_iterations=8)).robot
    assert (robot.solver_iterations, robot.ls_iterations) == (4, 8)
    assert EvalConfig().robot == RobotConfig()
    for config in (PRESETS["tiny"], flat_preset("tiny", "2d")):
        assert config.robot == RobotConfig() and {"solver_iterations", "ls_iterations"} <= set(config.to_dict())


def test_configurations_stored_without_solver_settings_read_as_4_8():
    old_hbr = {k: v for k, v in PRESETS["tiny"].to_dict().items() if k not in SOLVER_FIELDS}
    assert HBRConfig.from_dict(old_hbr).robot == RobotConfig(**OLD)
    assert normalised_config(old_hbr) == {**PRESETS["tiny"].to_dict(), **OLD}
    old_flat = {k: v for k, v in flat_preset("tiny", "2d").to_dict().items() if k not in SOLVER_FIELDS}
    assert FlatConfig.from_dict(old_flat).robot == RobotConfig(**OLD)
    assert flat_normalised(old_flat) == {**flat_preset("tiny", "2d").to_dict(), **OLD}


@pytest.mark.parametrize("kind", ["hbr", "flat"])
def test_old_run_folders_resume_with_the_old_solver(kind, tmp_path, capsys):
    """--resume on a folder whose config.json predates the solver settings continues with 4 / 8;
    an explicit other solver is refused when the run starts."""
    base = PRESETS["tiny"] if kind == "hbr" else flat_preset("tiny", "2d")
    main = hbr_main if kind == "hbr" else flat_main
    args = ["--preset", "tiny", "--out", str(tmp_path)] + ([] if kind == "hbr" else ["--variant", "2d"])
    old = {k: v for k, v in base.to_dict().items() if k not in SOLVER_FIELDS}
    (tmp_path / "config.json").write_text(json.dumps(old))

    assert main([*args, "--resume", "--show-config"]) == 0
    resumed = json.loads(capsys.readouterr().out)
    assert resumed == {**base.to_dict(), **OLD}
    normalise = normalised_config if kind == "hbr" else flat_normalised
    assert prepare_run_dir(tmp_path, resumed, True, normalise=normalise) == tmp_path

    assert main([*args, "--resume", "--show-config", "--solver-iterations", "2"]) == 0
    explicit = json.loads(capsys.readouterr().out)
    assert (explicit["solver_iterations"], explicit["ls_iterations"]) == (2, 8)
    with pytest.raises(ConfigError, match="differs in: solver_iterations"):
        prepare_run_dir(tmp_path, explicit, True, normalise=normalise)

    assert main([*args, "--show-config"]) == 0  # not resuming: today's default
    assert json.loads(capsys.readouterr().out) == base.to_dict()
