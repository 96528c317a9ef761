"""Damages spelled on `experiments.maze_eval`'s command line (`--damage leg0:removed,leg1:shortened=0.5:friction=0.6`)
through the online path: the episodes run on the damaged robots, their records, summaries, batch files and replays
name each damage, the replay's render model is the damaged robot, `--resume` reproduces the stored damages and
refuses others; bad spellings are one line and exit status 2, before anything is simulated."""

import dataclasses
import json

import mujoco
import numpy as np
import pytest

from experiments.maze_eval import main as maze_main
from hte_jax.online.recording import load_replay, recorded_episodes, replay_path
from hte_jax.qd.io import read_checkpoint
from hte_jax.online.evaluation import EvalConfig
from hte_jax.sim.damage import DAMAGE_SUITE, parse_damages
from hte_jax.sim.robot import FOOT_RADIUS, NUM_LEGS
from hte_jax.viz import gl
from hte_jax.viz.episode import episode_model
from tests.commands_script import near_goal_maze

EXIT_BAD_INPUT = 2
DAMAGES = "leg0:removed,leg1:shortened=0.5:friction=0.6"
LABELS = ["leg0:removed", "leg1:shortened=0.5:friction=0.6"]
# No OpenGL backend starts (tests/test_replay.py): --video keeps its replays and renders no video.
NO_GL = {"__EGL_VENDOR_LIBRARY_FILENAMES": "/nonexistent", "MUJOCO_GL": "egl"}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """(run folder, its arguments but --out): 2D-RTE, one episode per damage in a maze whose goal holds the
    start (each ends after its first valid action), both episodes recorded."""
    root = tmp_path_factory.mktemp("damages")
    maze = root / "near_goal_maze.json"
    maze.write_text(json.dumps(near_goal_maze()))
    args = ["--variant", "2d-rte", "--damage", DAMAGES, "--replicates", "1", "--max-actions", "2", "--iterations", "10",
            "--roots", "1", "--depth", "3", "--candidates", "10", "--maze", str(maze), "--no-progress"]
    with pytest.MonkeyPatch.context() as patch:
        for name, value in NO_GL.items():
            patch.setenv(name, value)
        patch.delenv(gl.CHECKED, raising=False)
        assert maze_main([*args, "--video", "2", "--out", str(root / "run")]) == 0
    return root / "run", args


def _feet_height(model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    """(6,) height of each foot sphere's bottom above the floor in `model` posed at `qpos`."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    return np.array([data.geom_xpos[model.geom(f"foot_{leg}").id][2] for leg in range(NUM_LEGS)]) - FOOT_RADIUS


@pytest.mark.slow
def test_spelled_damages_run_and_are_named_in_every_output(run):
    out, _ = run
    assert json.loads((out / "config.json").read_text())["damages"] == DAMAGES
    records = json.loads((out / "episodes.json").read_text())["episodes"]
    assert [r["damage"] for r in records] == LABELS and all(r["actions_taken"] >= 1 for r in records)
    assert list(json.loads((out / "summary.json").read_text())["variants"]["2d-rte"]["damages"]) == LABELS
    arrays, header = read_checkpoint(out / "episodes_0.npz")
    assert header["metadata"]["damages"] == LABELS and header["metadata"]["damage_models"] == ["removed", "shortened"]
    np.testing.assert_array_equal(arrays["damage"], np.eye(NUM_LEGS, dtype=bool)[:2])
    np.testing.assert_array_equal(arrays["damage_fraction"], np.float32([1.0, 0.5]))
    np.testing.assert_array_equal(arrays["damage_friction"], np.float32([1.0, 0.6]))

    assert recorded_episodes(out) == {"2d-rte": [0, 1]}
    spelled = parse_damages(DAMAGES)
    replays = [load_replay(replay_path(out, "2d-rte", episode)) for episode in (0, 1)]
    for replay, label in zip(replays, LABELS):
        assert replay.info["damage"] == label
        for field in ("legs", "model", "fraction", "friction"):
            np.testing.assert_array_equal(getattr(replay.robot_damage, field), getattr(spelled[label], field))
    removed, shortened = (episode_model(replay) for replay in replays)
    # The same legs under a model that edits nothing: the robot's own model values.
    intact = episode_model(dataclasses.replace(replays[1], info={
        **replays[1].info, "damage_model": "raised", "damage_fraction": 1.0, "damage_friction": 1.0}))
    leg0 = [removed.body(f"leg_0_{link}").id for link in (1, 2, 3)]
    assert (removed.body_mass[leg0] == 0).all() and (intact.body_mass[leg0] > 0).all()
    tibia = shortened.geom("leg_1_3").id
    np.testing.assert_allclose(shortened.geom_size[tibia, 1:], intact.geom_size[tibia, 1:] * [1.0, 0.5])
    floor = shortened.geom("floor").id
    np.testing.assert_allclose(shortened.geom_friction[floor], intact.geom_friction[floor] * 0.6, rtol=1e-6)
    # What the simulation did, seen in the recorded states: the removed leg's foot sank into the floor (no contact
    # acts on it) where the others stayed on it; the short foot stayed on the floor where a whole tibia's foot
    # would have been deep inside it.
    lowest_removed = np.stack([_feet_height(removed, qpos) for qpos in replays[0].qpos]).min(axis=0)
    assert lowest_removed[0] < -0.03 and (lowest_removed[1:] > -0.015).all(), lowest_removed
    lowest_short = np.stack([_feet_height(shortened, qpos) for qpos in replays[1].qpos]).min(axis=0)
    lowest_whole = np.stack([_feet_height(intact, qpos) for qpos in replays[1].qpos]).min(axis=0)
    assert (lowest_short > -0.015).all() and lowest_whole[1] < -0.03, (lowest_short, lowest_whole)


@pytest.mark.slow
def test_resume_reproduces_the_stored_damages_and_refuses_others(run, capsys):
    out, args = run
    before = {name: json.loads((out / name).read_text()) for name in ("episodes.json", "summary.json")}
    capsys.readouterr()
    assert maze_main([*args, "--out", str(out), "--resume"]) == 0
    assert f"batch 0 (2d-rte on seed 0): read from {out / 'episodes_0.npz'}" in capsys.readouterr().out
    for name, saved in before.items():
        assert json.loads((out / name).read_text()) == saved, name
    changed = [*args[:args.index("--damage") + 1], "leg0:removed,leg1:shortened=0.4:friction=0.6",
               *args[args.index("--damage") + 2:]]
    assert maze_main([*changed, "--out", str(out), "--resume"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {out} was started with a different configuration (differs in: damages)"]


@pytest.mark.parametrize("damage, fragment", [
    ("leg0:shortened=1.5", "fraction must be in (0, 1], got 1.5"),
    ("leg0:removed=0.5", "damage model 'removed' takes no fraction"),
    ("leg0:floppy", "unknown damage model 'floppy'"),
    ("leg6:removed", "unknown damage 'leg6'"),
    ("leg1:friction=0", "friction scale must be > 0"),
    ("leg1:weak", "needs a fraction"),
    ("leg1:removed:locked", "names two damage models"),
    ("leg1,1", "names the damage 'leg1' twice"),
])
def test_a_bad_damage_is_one_line_and_exit_2(damage, fragment, tmp_path, capsys):
    assert maze_main(["--damage", damage, "--out", str(tmp_path), "--no-progress"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and fragment in err[0], err
    assert not (tmp_path / "config.json").exists()


def test_the_stored_configuration_keeps_the_spelling_and_the_model(capsys):
    assert maze_main(["--damage", "all:locked,none:friction=0.5", "--damage-model", "removed", "--show-config"]) == 0
    config = json.loads(capsys.readouterr().out)
    assert config["damages"] == "all:locked,none:friction=0.5" and config["damage_model"] == "removed"


def test_the_damage_suite_is_one_word_on_the_command_line(capsys):
    assert maze_main(["--damage", "suite", "--damage-model", "locked", "--show-config"]) == 0
    config = json.loads(capsys.readouterr().out)
    assert config["damages"] == "suite" and config["damage_model"] == "locked"
    assert EvalConfig.from_dict(config).damage_list == DAMAGE_SUITE
