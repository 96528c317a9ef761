"""Adaptation episodes end to end through `experiments.maze_eval`: the intact and leg-1-damaged robot
reach the goal with HTE, every record is consistent with the simulated trajectory, outputs are
complete, and bad input is refused with a clear message."""

import json

import matplotlib.image
import numpy as np
import pytest

from experiments.maze_eval import main as maze_main
from hte_jax.flat.store import shipped_flat_path
from hte_jax.geometry import compose_pose, relative_pose
from hte_jax.online.episode import SECONDS_PER_ACTION
from hte_jax.online.rules import CANDIDATE_PATTERNS
from hte_jax.online.maze import PAPER_MAZE
from hte_jax.qd.io import read_checkpoint
from tests import golden

# Bit for bit: the golden output of the short maze_eval run.
pytestmark = pytest.mark.exact_numerics

MAX_ACTIONS = 30
assert golden.MAZE_ARGS[golden.MAZE_ARGS.index("--max-actions") + 1] == str(MAX_ACTIONS)


run = golden.run_fixture("maze_short")


@pytest.mark.slow
def test_short_run_matches_the_golden_output(run):
    golden.check("maze_short", run)


def _records(run):
    return json.loads((run / "episodes.json").read_text())["episodes"]


@pytest.mark.slow
def test_hte_reaches_the_goal_intact_and_with_leg1_damaged(run):
    records = {(r["variant"], r["damage"]): r for r in _records(run)}
    assert set(records) == {("hte", "none"), ("hte", "leg1"), ("rte", "none"), ("rte", "leg1")}
    for damage in ("none", "leg1"):
        hte = records["hte", damage]
        assert hte["reached"] and not hte["broken"] and hte["actions"] <= MAX_ACTIONS
        assert len(hte["prediction_error"]) == hte["actions_taken"]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["variants"]["hte"]["reached"] == 2 and summary["max_actions"] == MAX_ACTIONS


@pytest.mark.slow
def test_records_agree_with_the_simulated_trajectory(run):
    arrays, header = read_checkpoint(run / "episodes_0.npz")
    labels = header["metadata"]
    assert labels["variants"] == ["hte", "hte", "rte", "rte"] and labels["damages"] == ["none", "leg1"] * 2
    assert len(labels["plan_seconds"]) == max(arrays["taken"])
    for i, variant in enumerate(labels["variants"]):
        n = int(arrays["taken"][i])
        track = arrays["trajectory"][i]
        assert 1 <= n <= MAX_ACTIONS
        assert (arrays["action"][i, :n] >= 0).all() and (arrays["action"][i, n:] == -1).all()
        for k in range(n):
            before, after = track[SECONDS_PER_ACTION * k], track[SECONDS_PER_ACTION * (k + 1)]
            np.testing.assert_allclose(arrays["observed"][i, k], relative_pose(before, after), atol=1e-4)
            # The planner started at the measured pose (or a 0.5 m offset out of a wall's margin).
            assert np.linalg.norm(arrays["start"][i, k, :2] - before[:2]) <= 0.5 * np.sqrt(2) + 1e-5
            # Its path begins there and its first step is the chosen action's predicted outcome.
            path = arrays["path"][i, k]
            np.testing.assert_allclose(path[0], arrays["start"][i, k], atol=1e-5)
            np.testing.assert_allclose(path[1, :2], compose_pose(path[0], arrays["predicted"][i, k])[:2], atol=1e-4)
        assert (track[SECONDS_PER_ACTION * n:] == track[SECONDS_PER_ACTION * n]).all()  # still after the end
        at_goal = np.linalg.norm(track[-1, :2] - np.asarray(PAPER_MAZE.goal)) < PAPER_MAZE.goal_radius
        assert bool(arrays["reached"][i]) == at_goal
        patterns = arrays["patterns"][i, :n]
        if variant == "rte":
            assert (patterns == -1).all()  # the trained decoding: nearest elite, any pattern
        else:
            assert np.isin(patterns, CANDIDATE_PATTERNS).all()
    # The intact robot's first RTE action does about what the repertoire predicts (3 cm cells,
    # plus the neutral second's settling).
    intact_rte = next(r for r in _records(run) if (r["variant"], r["damage"]) == ("rte", "none"))
    assert intact_rte["prediction_error"][0] < 0.15


@pytest.mark.slow
def test_outputs_and_plots(run):
    config = json.loads((run / "config.json").read_text())
    assert config["variants"] == "hte,rte" and config["max_actions"] == MAX_ACTIONS and config["preset"] == "cpu"
    for name in ("maze_hte", "maze_rte", "prediction_error", "fig6_actions"):
        image = matplotlib.image.imread(run / "plots" / f"{name}.png")
        assert image.ndim == 3 and image.std() > 0


@pytest.mark.parametrize("args, message", [
    (["--variant", "ite"], "unknown variant"),
    (["--damage", "leg9"], "unknown damage"),
    (["--damage", "7"], "unknown damage index"),
    (["--replicates", "0"], "replicates"),
    (["--iterations", "many"], "iterations"),
    (["--preset", "huge"], "unknown preset"),
    (["--repertoire", "/nowhere/hbr.npz"], "no such checkpoint"),
    (["--variant", "hte", "--repertoire", str(shipped_flat_path("2d"))], "needs an HBR"),
    (["--variant", "rte", "--repertoire", str(shipped_flat_path("aprol"))], "APROL"),
    (["--protocol", "nature"], "unknown protocol"),
    (["--damage-model", "floppy"], "damage_model"),
    (["--repertoire-dir", "/nowhere"], "not a folder"),
    (["--variant", "hte-spare", "--repertoire", str(shipped_flat_path("2d"))], "needs an HBR"),
    (["--variant", "hte-miss"], "unknown variant"),
])
def test_cli_errors_name_the_problem(args, message, tmp_path, capsys):
    assert maze_main([*args, "--out", str(tmp_path), "--no-progress"]) == 2
    assert message in capsys.readouterr().err
