"""Recorded maze episodes: `maze_eval --video` records states and writes videos, a replay shows
exactly the recorded base trajectory, recording changes no result, and `render episode` renders
headless or refuses bad input in one line with exit status 2.

One tiny run (HTE under a raised leg 1, 2 actions, a small planner) is made twice: with --video 1
and without. Rendering runs in subprocesses (MUJOCO_GL must be set before mujoco is imported).
Where no OpenGL starts, the run keeps its replays (no videos) and the tests that draw skip
(`gl_env`, tests/conftest.py); the others run everywhere.
"""

import contextlib
import io
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
from hte_jax.viz import gl
from hte_jax.viz.episode import episode_model, frame_states, frame_text
from hte_jax.viz.render import posed

# With test_benchmarks (its adaptation benchmark runs this episode): one worker compiles the programs once.
pytestmark = pytest.mark.xdist_group("adaptation_episode")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# The render CLI as a user starts it: MUJOCO_GL unset, the backend chosen by the CLI, and the user's
# XLA_FLAGS as collection found them (XLA's default code: these CLIs load the shipped HBR, tests/conftest.py).
PLAIN = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", gl.CHECKED)} | {"JAX_PLATFORMS": "cpu"}
# libglvnd's libEGL without a vendor driver and MUJOCO_GL=egl: no backend starts, on any machine.
NO_GL = {"__EGL_VENDOR_LIBRARY_FILENAMES": "/nonexistent", "MUJOCO_GL": "egl"}
# The episode of tests/test_benchmarks.py's adaptation benchmark (HTE, one leg-1 episode, 2 actions, a planner of
# 8 iterations x 1 tree): the run without --video and that benchmark share their compiled programs.
TASK = ["--variant", "hte", "--damage", "leg1", "--max-actions", "2", "--iterations", "8", "--roots", "1"]
RUN = [*TASK, "--no-progress"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """(run folder with --video 1, the same run without, the latter's stderr with progress bars on).
    maze_eval chooses the GL backend itself: the user's MUJOCO_GL is taken out."""
    root = tmp_path_factory.mktemp("replay")
    with pytest.MonkeyPatch.context() as patch:
        for name in ("MUJOCO_GL", gl.CHECKED):
            patch.delenv(name, raising=False)
        assert maze_main([*RUN, "--video", "1", "--out", str(root / "on")]) == 0
        progress = io.StringIO()
        with contextlib.redirect_stderr(progress):
            assert maze_main([*TASK, "--out", str(root / "off")]) == 0
    return root / "on", root / "off", progress.getvalue()


@pytest.mark.slow
def test_recording_changes_no_result(runs):
    on, off, _ = runs
    recorded, _ = read_checkpoint(on / "episodes_0.npz")
    plain, _ = read_checkpoint(off / "episodes_0.npz")
    assert sorted(recorded) == sorted(plain)
    for name in plain:
        if name != "__metadata__":
            np.testing.assert_array_equal(recorded[name], plain[name], err_msg=name)
    for name in ("episodes.json", "summary.json", "statistics.json"):
        assert (on / name).read_text() == (off / name).read_text()
    assert not (off / "replays").exists() and not (off / "videos").exists()


@pytest.mark.slow
def test_no_video_bar_without_videos(runs):
    """--video 0 (the default): progress bars for the episodes, none for videos."""
    _, _, progress = runs
    assert "hte" in progress and "video" not in progress


@pytest.mark.slow
def test_replay_reproduces_the_recorded_base_trajectory_exactly(runs):
    """Setting the recorded states in the render model (kinematics only) puts the base exactly where
    the episode's history says it was after every second; the annotations are the history's."""
    on, _, _ = runs
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


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # imageio-ffmpeg's reader is a subprocess
def test_maze_eval_video_writes_the_episode_video(gl_env, runs):
    on, _, _ = runs
    frames = _video_frames(on / "videos" / "hte_ep0_leg1.mp4")
    # 8 simulated seconds at 4x and 25 frames/s, the end, then the end held 1 s
    assert frames.shape == (50 + 1 + 25, 360, 480, 3)
    _check_moving(frames[:51])


def _render_episode(*args, env=PLAIN):
    return subprocess.run([sys.executable, "-m", "experiments.render", "episode", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=900)


@pytest.mark.slow
def test_render_episode_cli_writes_a_gif(gl_env, runs, tmp_path):
    on, _, _ = runs
    out = tmp_path / "episode.gif"
    proc = _render_episode(str(on), "--episode", "0", "--camera", "track", "--width", "64", "--height", "48", "--fps", "5",
                           "--speed", "4", "--no-progress", "--out", str(out), env=PLAIN | gl_env)
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


@pytest.mark.slow
@pytest.mark.parametrize("args, env, fragment", [
    (["{root}/nowhere"], PLAIN, "no such run folder"),
    (["{off}"], PLAIN | NO_GL, "maze_eval --video N"),
    (["{on}", "--episode", "5"], PLAIN | NO_GL, "episode 5 of hte is not recorded"),
    (["{on}", "--variant", "rte"], PLAIN | NO_GL, "recorded: hte: episodes 0)"),
    (["{on}", "--speed", "1", "--fps", "10"], PLAIN | NO_GL, "whole number"),
    (["{on}"], PLAIN | {"MUJOCO_GL": "vulkan"}, "MUJOCO_GL='vulkan' is not a renderer"),
    (["{on}"], PLAIN | NO_GL, "MUJOCO_GL=egl does not start"),
])
def test_render_episode_bad_input_is_one_line_and_exit_2(runs, args, env, fragment):
    """Bad input, found before OpenGL is needed (the same line where none starts: NO_GL), and a
    renderer that cannot start: one line, exit 2."""
    on, off, _ = runs
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


@pytest.mark.slow
def test_maze_eval_without_opengl_keeps_its_results_and_says_how_to_render_later(tmp_path, capsys, monkeypatch):
    """Videos are rendered after the results are written: where no OpenGL starts (NO_GL) the run
    succeeds (exit 0) with every result and its replays, and one line says the videos were not
    rendered, why, what to install, and the command that renders them later; that command, given
    OpenGL, is the one that renders (test_render_episode_cli_writes_a_gif)."""
    for name, value in NO_GL.items():
        monkeypatch.setenv(name, value)
    out = tmp_path / "run"
    assert maze_main([*RUN, "--video", "1", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("videos not rendered: MUJOCO_GL=egl does not start"), err
    assert "libosmesa6" in err[0]
    assert err[0].endswith(f"render them later with: python -m experiments.render episode {out} --variant hte --episode 0")
    assert captured.out.strip().endswith(f"wrote {out}")
    assert json.loads((out / "summary.json").read_text())["variants"]["hte"]["episodes"] == 1
    assert recorded_episodes(out) == {"hte": [0]} and not (out / "videos").exists()
