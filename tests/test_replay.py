"""Recorded maze episodes: `maze_eval --video` records states and writes videos, a replay shows
exactly the recorded base trajectory, recording changes no result, and `render episode` renders
headless (osmesa) or refuses bad input in one line with exit status 2.

One tiny run (HTE under a raised leg 1, 2 actions, a small planner) is made twice: with --video 1
and without. Rendering runs in subprocesses (MUJOCO_GL must be set before mujoco is imported).
"""

import json
import os
import subprocess
import sys

import imageio_ffmpeg
import numpy as np
import pytest
from PIL import Image

from experiments.maze_eval import main as maze_main
from hte_jax.geometry import heading
from hte_jax.online.recording import load_replay, recorded_episodes, replay_path
from hte_jax.qd.io import read_checkpoint
from hte_jax.viz.episode import episode_model, frame_states, frame_text
from hte_jax.viz.render import posed

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OSMESA = dict(os.environ, MUJOCO_GL="osmesa", JAX_PLATFORMS="cpu")
RUN = ["--variant", "hte", "--damage", "leg1", "--max-actions", "2", "--iterations", "8", "--roots", "1", "--depth", "4",
       "--no-progress"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """(run folder with --video 1, the same run without)."""
    root = tmp_path_factory.mktemp("replay")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MUJOCO_GL", "osmesa")  # for the video subprocess
        assert maze_main([*RUN, "--video", "1", "--out", str(root / "on")]) == 0
    assert maze_main([*RUN, "--out", str(root / "off")]) == 0
    return root / "on", root / "off"


def test_recording_changes_no_result(runs):
    on, off = runs
    recorded, _ = read_checkpoint(on / "episodes_0.npz")
    plain, _ = read_checkpoint(off / "episodes_0.npz")
    assert sorted(recorded) == sorted(plain)
    for name in plain:
        if name != "__metadata__":
            np.testing.assert_array_equal(recorded[name], plain[name], err_msg=name)
    for name in ("episodes.json", "summary.json", "statistics.json"):
        assert (on / name).read_text() == (off / name).read_text()
    assert not (off / "replays").exists() and not (off / "videos").exists()


def test_replay_reproduces_the_recorded_base_trajectory_exactly(runs):
    """Setting the recorded states in the render model (kinematics only) puts the base exactly where
    the episode's history says it was after every second; the annotations are the history's."""
    on, _ = runs
    arrays, _ = read_checkpoint(on / "episodes_0.npz")
    assert recorded_episodes(on) == {"hte": [0]}
    replay = load_replay(replay_path(on, "hte", 0))
    taken = int(arrays["taken"][0])
    assert replay.actions == taken == 2 and replay.info["damage"] == "leg1" and replay.info["episode"] == 0
    assert replay.qpos.shape == (taken * 100 + 1, 25)  # 25 states per simulated second, 4 s per action
    np.testing.assert_array_equal(replay.action, arrays["action"][0, :taken])
    np.testing.assert_array_equal(replay.patterns, arrays["patterns"][0, :taken])
    model = episode_model(replay)
    base = model.body("base_link").id
    seconds = replay.qpos[:: replay.states_per_action // 4]
    shown = np.array([np.r_[data.xpos[base, :2], heading(np.asarray(data.xquat[base]))] for data in posed(model, seconds)])
    track = arrays["trajectory"][0, : 4 * taken + 1]
    np.testing.assert_array_equal(shown[:, :2].astype(np.float32), track[:, :2])
    np.testing.assert_allclose(shown[:, 2], track[:, 2], atol=1e-6)
    # Frames every 5 states, the last one added; the panel names the action, the step's pattern and the end.
    states = frame_states(replay, 5)
    assert states[0] == 0 and states[-1] == 200 and (np.diff(states) <= 5).all()
    pattern = int(replay.patterns[1, 2])
    assert f"action 2 / 2\nskill {int(replay.action[1])}\nstep 3: pattern\n{pattern} = {pattern:06b}" in frame_text(replay, 160)
    assert "neutral pose" in frame_text(replay, 80)
    assert "goal not reached\nin 2 actions\n8 s" in frame_text(replay, 200)


def _video_frames(path):
    reader = imageio_ffmpeg.read_frames(str(path))
    width, height = next(reader)["size"]
    return np.stack([np.frombuffer(frame, np.uint8).reshape(height, width, 3) for frame in reader])


def _check_moving(frames):
    assert all(frame.std() > 10 for frame in frames), "a blank frame"
    assert all(np.abs(a.astype(int) - b.astype(int)).sum() > 0 for a, b in zip(frames[:8], frames[1:9]))


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # imageio-ffmpeg's reader is a subprocess
def test_maze_eval_video_writes_the_episode_video(runs):
    on, _ = runs
    frames = _video_frames(on / "videos" / "hte_ep0_leg1.mp4")
    # 8 simulated seconds at 4x and 25 frames/s, the end, then the end held 1 s
    assert frames.shape == (50 + 1 + 25, 360, 480, 3)
    _check_moving(frames[:51])


def _render_episode(*args, env=OSMESA):
    return subprocess.run([sys.executable, "-m", "experiments.render", "episode", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=900)


def test_render_episode_cli_writes_a_gif(runs, tmp_path):
    on, _ = runs
    out = tmp_path / "episode.gif"
    proc = _render_episode(str(on), "--episode", "0", "--camera", "track", "--width", "64", "--height", "48", "--fps", "5",
                           "--speed", "4", "--no-progress", "--out", str(out))
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == f"wrote {out}" and proc.stderr.strip() == ""
    with Image.open(out) as gif:
        # 8 simulated seconds at 4x and 5 frames/s, and the end; Pillow merges the 1 s hold into the end
        assert gif.size == (64, 48) and gif.n_frames == 8 * 5 // 4 + 1
        frames, duration = [], 0
        for k in range(gif.n_frames):
            gif.seek(k)
            frames.append(np.asarray(gif.convert("RGB")))
            duration += gif.info["duration"]
    assert duration == (8 * 5 // 4 + 1 + 5) * 200
    _check_moving(np.stack(frames))


@pytest.mark.parametrize("args, env, fragment", [
    (["{root}/nowhere"], OSMESA, "no such run folder"),
    (["{off}"], OSMESA, "maze_eval --video N"),
    (["{on}", "--episode", "5"], OSMESA, "episode 5 of hte is not recorded"),
    (["{on}", "--variant", "rte"], OSMESA, "recorded: hte: episodes 0)"),
    (["{on}", "--speed", "1", "--fps", "10"], OSMESA, "whole number"),
    (["{on}"], dict(OSMESA, MUJOCO_GL="vulkan"), "MUJOCO_GL"),
])
def test_render_episode_bad_input_is_one_line_and_exit_2(runs, args, env, fragment):
    on, off = runs
    args = [a.format(root=on.parent, on=on, off=off) for a in args]
    proc = _render_episode(*args, "--no-progress", "--out", str(on.parent / "bad.gif"), env=env)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and fragment in lines[0], lines


@pytest.mark.parametrize("count, message", [("-1", "--video must be an integer >= 0"), ("x", "--video must be")])
def test_maze_eval_bad_video_count(count, message, tmp_path, capsys):
    assert maze_main(["--video", count, "--out", str(tmp_path), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_maze_eval_reports_a_renderer_that_cannot_start(runs, tmp_path, capsys, monkeypatch):
    """Videos are rendered after the results are written: a renderer that cannot start is one line
    naming MUJOCO_GL and where the replays are, exit 2, every result written."""
    monkeypatch.setenv("MUJOCO_GL", "nonsense")
    out = tmp_path / "run"
    assert maze_main([*RUN, "--video", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "MUJOCO_GL" in err[0] and "replays" in err[0]
    assert json.loads((out / "summary.json").read_text())["variants"]["hte"]["episodes"] == 1
    assert recorded_episodes(out) == {"hte": [0]}
