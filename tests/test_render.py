"""Recording states in rollouts, rendering them headless with MuJoCo's renderer, and the render
CLI's argument checks and choice of OpenGL backend.

Rendering runs in subprocesses: MUJOCO_GL must be set before mujoco is imported, and the rest of
the suite has imported it already. Tests that draw take `gl_env` (tests/conftest.py: they skip
where no OpenGL starts, naming what to install); the others run everywhere.
"""

import ctypes.util
import json
import os
import subprocess
import sys
import textwrap

import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from hte_jax.errors import ConfigError
from hte_jax.sim.robot import load_robot
from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state
from hte_jax.viz import gl

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# The render CLI as a user starts it: MUJOCO_GL unset, the backend chosen by the CLI, and the user's
# XLA_FLAGS as collection found them (XLA's default code: these CLIs load the shipped HBR, tests/conftest.py).
PLAIN = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", gl.CHECKED)} | {"JAX_PLATFORMS": "cpu"}
# libglvnd's libEGL with no vendor driver: EGL cannot start, as on a machine without it.
NO_EGL = {"__EGL_VENDOR_LIBRARY_FILENAMES": "/nonexistent"}

# Renders one shipped Flat-2D elite (of 64 drawn) that walks 0.3 to 0.7 m, looking straight down on the middle
# of its path, one frame every 10 control steps; saves the frames and the recorded displacement.
CLIP = textwrap.dedent("""
    import sys
    import numpy as np, jax.numpy as jnp
    from hte_jax.flat.store import load_flat, shipped_flat_path
    from hte_jax.sim.robot import load_robot, RobotConfig
    from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state
    from hte_jax.viz.render import Camera, open_renderer, render_frames, render_model
    repertoire = load_flat(shipped_flat_path("2d"))[0][0]
    filled = np.asarray(repertoire.filled)
    robot = load_robot()
    some = np.random.default_rng(0).choice(int(filled.sum()), 64, replace=False)
    params = jnp.asarray(np.asarray(repertoire.genotypes)[filled][some])
    spec = RolloutSpec(num_steps=300, record_contacts=False, record_qpos_every=10)
    result = rollout(robot, params, jnp.zeros(6, bool), standing_state(robot), spec)
    moved = np.linalg.norm(np.asarray(result.final_state.qpos[:, :2]), axis=1)
    pick = int(np.flatnonzero((moved > 0.3) & (moved < 0.7))[0])
    qpos = np.concatenate([np.asarray(result.qpos[pick]), np.asarray(result.final_state.qpos[pick])[None]])
    start, end = qpos[0, :2], qpos[-1, :2]
    model = render_model(RobotConfig())
    renderer = open_renderer(model, 160, 120)
    camera = Camera("top", distance=2.0, centre=tuple(float(v) for v in (start + end) / 2))
    frames = render_frames(model, qpos, renderer, camera)
    renderer.close()
    np.savez(sys.argv[1], frames=frames, displacement=end - start, fovy=model.vis.global_.fovy)
""")


@pytest.fixture(scope="module")
def clip(tmp_path_factory, gl_env):
    out = tmp_path_factory.mktemp("render") / "clip.npz"
    proc = subprocess.run([sys.executable, "-c", CLIP, str(out)], cwd=ROOT, env=PLAIN | gl_env, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return np.load(out)


def _footprint(frame: np.ndarray) -> np.ndarray:
    """(col, row) centroid of the robot's blue base plate."""
    rgb = frame.astype(np.int32)
    rows, cols = np.nonzero((rgb[..., 2] - rgb[..., 0] > 60) & (rgb[..., 2] - rgb[..., 1] > 20))
    assert rows.size > 20, "the base plate is not visible"
    return np.asarray([cols.mean(), rows.mean()])


@pytest.mark.slow
def test_clip_frames_show_the_robot_moving_along_its_recorded_displacement(clip):
    frames, displacement = clip["frames"], clip["displacement"]
    assert frames.shape == (31, 120, 160, 3) and frames.dtype == np.uint8
    assert all(frame.std() > 10 for frame in frames), "a blank frame"
    differ = [np.abs(a.astype(int) - b.astype(int)).sum() > 0 for a, b in zip(frames[:-1], frames[1:])]
    assert all(differ), "two consecutive frames are identical"
    moved = _footprint(frames[-1]) - _footprint(frames[0])
    expected = np.asarray([displacement[0], -displacement[1]])  # image right = +x, image down = -y
    cosine = moved @ expected / (np.linalg.norm(moved) * np.linalg.norm(expected))
    assert cosine > 0.95
    # a plate 0.15 m above the floor seen from 2 m: pixels per metre = H / (2 (2 - 0.15) tan(fovy / 2))
    scale = 120 / (2 * (2.0 - 0.15) * np.tan(np.radians(float(clip["fovy"])) / 2))
    np.testing.assert_allclose(np.linalg.norm(moved), scale * np.linalg.norm(displacement), rtol=0.25)


@pytest.mark.slow
def test_recorded_states_are_the_rollout_and_recording_changes_nothing():
    """qpos recorded every 25 steps equals the base poses the rollout reports at those steps, and
    every other output is bit-identical with recording off (None then)."""
    robot = load_robot()
    params = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (2, 36)), jnp.float32)
    steps = (0, 25, 50, 75)
    plain = rollout(robot, params, jnp.zeros(6, bool), standing_state(robot), RolloutSpec(100, pose_steps=steps))
    recorded = rollout(robot, params, jnp.zeros(6, bool), standing_state(robot),
                       RolloutSpec(100, pose_steps=steps, record_qpos_every=25))
    assert plain.qpos is None and recorded.qpos.shape == (2, 4, 25)
    np.testing.assert_array_equal(recorded.qpos[..., :3], recorded.base_pos)
    np.testing.assert_array_equal(recorded.qpos[..., 3:7], recorded.base_quat)
    np.testing.assert_array_equal(recorded.final_state.qpos, plain.final_state.qpos)
    np.testing.assert_array_equal(recorded.foot_contacts, plain.foot_contacts)
    with pytest.raises(ConfigError, match="record_qpos_every"):
        RolloutSpec(100, record_qpos_every=-1)


def _render_cli(*args, env=PLAIN):
    return subprocess.run([sys.executable, "-m", "experiments.render", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=900)


@pytest.mark.slow
def test_render_skills_cli_writes_a_grid_gif(tmp_path, gl_env):
    out = tmp_path / "skills.gif"
    # A damage spelled as maze_eval spells it: the clips simulated and drawn with the short tibia, on a slippery floor.
    proc = _render_cli("skills", "--flat", "2d", "--count", "2", "--damage", "leg1:shortened=0.5:friction=0.8",
                       "--width", "64", "--height", "48",
                       "--fps", "10", "--no-progress", "--out", str(out), env=PLAIN | gl_env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == f"wrote {out}" and proc.stderr.strip() == ""
    with Image.open(out) as gif:
        assert gif.size == (128, 48) and gif.n_frames == 31  # two clips side by side, 3 s at 10 fps + the end


@pytest.mark.slow
def test_render_patterns_cli_labels_one_clip_per_pattern(tmp_path, gl_env):
    """One skill under three patterns: three labelled clips side by side; the clips differ (the
    patterns run different middle elites) and the label's dark pixels sit in the top-left corner."""
    out = tmp_path / "patterns.gif"
    proc = _render_cli("patterns", "--patterns", "any,63,47", "--damage", "leg1", "--width", "96", "--height", "64",
                       "--fps", "10", "--no-progress", "--out", str(out), env=PLAIN | gl_env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with Image.open(out) as gif:
        assert gif.size == (288, 64) and gif.n_frames == 31
        gif.seek(30)
        last = np.asarray(gif.convert("RGB")).astype(int)
    clips = [last[:, k * 96:(k + 1) * 96] for k in range(3)]
    assert np.abs(clips[1] - clips[2]).sum() > 0
    assert all((clip[:14, :60].sum(axis=-1) < 120).any() for clip in clips)  # dark label text


# libglvnd's libEGL without a vendor driver and MUJOCO_GL=egl: no backend starts, on any machine.
NO_GL = PLAIN | NO_EGL | {"MUJOCO_GL": "egl"}


@pytest.mark.parametrize("args, fragment", [
    (["skills", "--damage", "leg9"], "unknown damage"),
    (["skills", "--damage", "leg1:weak=2"], "fraction must be in (0, 1], got 2"),
    (["skills", "--damage", "leg1,leg2:removed"], "--damage: give one damage, got 2"),
    pytest.param(["skills", "--skills", "999999"], "out of range", marks=pytest.mark.slow),  # loads the shipped HBR
    pytest.param(["patterns", "--patterns", "any,64"], "unknown contact pattern '64': use 0..63 or any", marks=pytest.mark.slow),
])
def test_render_cli_bad_input_is_one_line_and_exit_2_before_opengl_is_needed(args, fragment):
    """Errors found in the files (the repertoire, the damage names) come before the missing OpenGL."""
    proc = _render_cli(args[0], "--width", "32", "--height", "24", "--fps", "10", "--no-progress", *args[1:], env=NO_GL)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and fragment in lines[0], lines


@pytest.mark.parametrize("value, fragment", [
    ("vulkan", "MUJOCO_GL='vulkan' is not a renderer"),
    pytest.param("egl", "MUJOCO_GL=egl does not start", marks=pytest.mark.slow),  # with NO_EGL
])
def test_render_cli_reports_a_renderer_that_cannot_start_in_one_line(value, fragment):
    """A MUJOCO_GL the user set is kept: not a renderer, or one that cannot start, is one line
    naming it (and what to install), exit 2, before anything is simulated."""
    proc = _render_cli("skills", "--flat", "2d", "--count", "1", "--no-progress", env=PLAIN | NO_EGL | {"MUJOCO_GL": value})
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and fragment in lines[0], lines
    assert value == "vulkan" or "libosmesa6" in lines[0]


# Runs render.main on each argument list (JSON) in one fresh interpreter whose choice of GL backend
# fails if it is made; prints each exit status and stderr, then which of mujoco / OpenGL got imported.
NO_GL_SCRIPT = textwrap.dedent("""
    import contextlib, io, json, sys
    from hte_jax.viz import gl
    def refuse(*args, **kwargs):
        raise AssertionError("the GL backend was chosen")
    gl.choose = refuse
    from experiments.render import main
    results = []
    for args in json.loads(sys.argv[1]):
        err = io.StringIO()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            try:
                code = main(args)
            except SystemExit as exit:
                code = exit.code
        results.append([code, err.getvalue()])
    print(json.dumps({"results": results, "imported": [m for m in ("mujoco", "OpenGL") if m in sys.modules]}))
""")
NO_GL_CASES = [
    (["--help"], 0, None), (["skills", "--help"], 0, None), (["episode", "--help"], 0, None),
    (["skills", "--fps", "7"], 2, "--fps must divide 100"), (["skills", "--out", "x.avi"], 2, "must end in .mp4 or .gif"),
    (["skills", "--camera", "side"], 2, "--camera must be one of"), (["skills", "--skills", "1,x"], 2, "--skills must be"),
    (["skills", "--hbr", "no/such/hbr.npz"], 2, "no such HBR file"), (["patterns", "--columns", "0"], 2, "--columns"),
    (["episode", "no/such/run"], 2, "no such run folder"), (["episode", ".", "--speed", "0"], 2, "--speed"),
]


def test_render_help_and_argument_errors_touch_no_opengl():
    """--help and the argument errors that need no file: one line, exit 2 (0 for help), no backend
    chosen, neither mujoco nor OpenGL imported (they work on a machine without either library)."""
    proc = subprocess.run([sys.executable, "-c", NO_GL_SCRIPT, json.dumps([a for a, _, _ in NO_GL_CASES])], cwd=ROOT,
                          env=PLAIN, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["imported"] == []
    for (args, code, fragment), (got, err) in zip(NO_GL_CASES, report["results"], strict=True):
        assert got == code, (args, err)
        if fragment is not None:
            lines = err.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("error:") and fragment in lines[0], (args, lines)


def test_without_egl_the_choice_falls_back_to_osmesa_or_names_what_to_install():
    """MUJOCO_GL unset and EGL unable to start (NO_EGL): OSMesa where its library is installed,
    otherwise one line saying why each failed and what to install, exit 2."""
    proc = subprocess.run([sys.executable, "-m", "hte_jax.viz.gl"], cwd=ROOT, env=PLAIN | NO_EGL, capture_output=True,
                          text=True, timeout=300)
    if ctypes.util.find_library("OSMesa") is not None:
        assert proc.returncode == 0 and proc.stdout.strip() == "osmesa", proc.stderr
    else:
        assert proc.returncode == 2
        (line,) = proc.stderr.strip().splitlines()
        assert line.startswith("error: cannot render: no headless OpenGL starts here (EGL: ")
        assert "OSMesa: libOSMesa not found" in line and "apt-get install libosmesa6" in line


def test_skill_and_pattern_choices_of_the_render_cli():
    """`render skills` takes --count skills spread over the repertoire or the numbers given; `render patterns`
    takes 0..63 or any, each checked with a one-line message."""
    from hte_jax.hbr.hierarchy import ANY_PATTERN
    from hte_jax.viz.skills import chosen, parse_patterns, pattern_label

    assert chosen(3, 10).tolist() == [0, 4, 9] and chosen(20, 4).tolist() == [0, 1, 2, 3]
    assert chosen(1, 10, [9, 0]).tolist() == [9, 0]
    with pytest.raises(ConfigError, match=r"^skill 10 out of range: the repertoire holds 10 skills \(0 .. 9\)$"):
        chosen(1, 10, [3, 10])
    with pytest.raises(ConfigError, match="--count must be >= 1, got 0"):
        chosen(0, 10)
    assert parse_patterns("63, any,0").tolist() == [63, ANY_PATTERN, 0]
    for bad in ("64", "-1", "x"):
        with pytest.raises(ConfigError, match=f"unknown contact pattern '{bad}': use 0..63 or any"):
            parse_patterns(f"1,{bad}")
    assert pattern_label(ANY_PATTERN) == "any pattern" and pattern_label(5) == "pattern 5 (000101)"


def test_choice_order_and_messages():
    """The user's MUJOCO_GL is tried alone; unset: EGL, then OSMesa, stopping at the first that starts."""
    tried = []

    def attempt(backend, env, works=("osmesa",)):
        tried.append(backend)
        return None if backend in works else f"{backend} missing"

    assert gl.choose({}, attempt) == "osmesa" and tried == ["egl", "osmesa"]
    tried.clear()
    assert gl.choose({"MUJOCO_GL": "OSMesa "}, attempt) == "osmesa" and tried == ["osmesa"]
    tried.clear()
    assert gl.choose({"MUJOCO_GL": "egl", gl.CHECKED: "egl"}, attempt) == "egl" and tried == []
    with pytest.raises(gl.RenderError, match=r"MUJOCO_GL=egl does not start \(egl missing\)"):
        gl.choose({"MUJOCO_GL": "egl"}, attempt)
    with pytest.raises(gl.RenderError, match=r"\(EGL: egl missing; OSMesa: osmesa missing\); install OSMesa"):
        gl.choose({}, lambda backend, env: f"{backend} missing")
