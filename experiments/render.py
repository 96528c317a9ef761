"""See the robot: videos of repertoire skills rendered with MuJoCo's renderer, headless.

    python -m experiments.render skills                                # 6 skills of the shipped HBR
    python -m experiments.render skills --damage leg1 --count 9        # the same under a raised leg 1
    python -m experiments.render skills --flat 2d --camera top         # elites of the shipped Flat-2D
    python -m experiments.render skills --hbr runs/hbr-gpu --skills 10,200,1500 --out runs/render/mine.gif
    python -m experiments.render patterns --skill 1400 --damage leg1   # one skill, several contact patterns
    python -m experiments.render episode runs/maze-eval --variant hte --episode 0  # a recorded maze episode

`skills` simulates each chosen skill for 3 s from standing (top-layer skills of an HBR, or the
controllers of a flat repertoire, intact or under a named damage), records the state every frame
and lays the clips out on a grid: a tracking camera (or `--camera top`, looking down), damaged legs
in red. `patterns` executes one HBR skill with several contact patterns held for its three steps
(what HTE chooses from; "any" is RTE's nearest elite of any pattern), each clip labelled.
`episode` replays a maze episode recorded by `python -m experiments.maze_eval --video N` (the
replay files under <run>/replays/; --episode I is the variant's I-th episode of the run): the
whole maze seen from above (or --camera track), the goal in green, the path so far as a blue
trail, and a panel naming the action, the executed skill and each step's contact pattern;
--speed simulated seconds per video second (default 4). MP4 through imageio-ffmpeg, GIF through
Pillow (by the --out suffix). Headless OpenGL:
MUJOCO_GL=egl where a GPU driver is present, otherwise osmesa (Debian package libosmesa6); the
default is chosen for you when MUJOCO_GL is unset. Bad input gives a one-line error and exit 2.
"""

from __future__ import annotations

import os
import sys

GL_BACKENDS = ("egl", "osmesa", "glfw", "glx")
if "MUJOCO_GL" not in os.environ:  # must be set before mujoco is imported
    os.environ["MUJOCO_GL"] = "egl" if os.path.exists("/dev/nvidia0") else "osmesa"
elif __name__ == "__main__" and os.environ["MUJOCO_GL"].lower().strip() not in GL_BACKENDS:
    print(f"error: MUJOCO_GL={os.environ['MUJOCO_GL']!r} is not a renderer; use egl (GPU driver) or osmesa (CPU, "
          "Debian package libosmesa6), or unset it", file=sys.stderr)
    sys.exit(2)

import argparse  # noqa: E402
import functools  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

from experiments.cli import input_errors, interruptible  # noqa: E402
from hte_jax.errors import ConfigError  # noqa: E402
from hte_jax.flat.comparison import resolve  # noqa: E402
from hte_jax.flat.store import load_flat, shipped_flat_path  # noqa: E402
from hte_jax.hbr.execution import ANY_PATTERN, execute_skill  # noqa: E402
from hte_jax.hbr.middle import NUM_PATTERNS  # noqa: E402
from hte_jax.hbr.store import load_hbr  # noqa: E402
from hte_jax.online.recording import REPLAY_DIR, Replay, load_replay, recorded_episodes, replay_path  # noqa: E402
from hte_jax.qd.io import CheckpointError  # noqa: E402
from hte_jax.sim.damage import parse_damage  # noqa: E402
from hte_jax.sim.robot import DAMAGE_MODELS, RobotConfig, load_robot  # noqa: E402
from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state  # noqa: E402
from hte_jax.viz.episode import frame_states, render_episode  # noqa: E402
from hte_jax.viz.render import (  # noqa: E402
    CAMERAS, Camera, RenderError, label, open_renderer, render_frames, render_model, tile, write_video,
)

CONTROL_HZ = 100
SKILL_STEPS = 300  # 3 s


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("skills", help="a grid video of repertoire skills")
    source = s.add_mutually_exclusive_group()
    source.add_argument("--hbr", default=None, help="HBR file or run folder (default: the shipped HBR)")
    source.add_argument("--flat", default=None, help="flat repertoire file, or 2d / 8d for the shipped ones")
    s.add_argument("--count", type=int, default=6, help="skills, spread evenly over the repertoire (default 6)")
    s.add_argument("--skills", default=None, help="comma-separated skill numbers (0 .. filled - 1) instead of --count")
    s.add_argument("--damage", default="none", help="none, leg0..leg5, legs<i>+<j> (default none)")
    s.add_argument("--damage-model", default="raised", help=f"one of {', '.join(DAMAGE_MODELS)}")
    s.add_argument("--camera", default="track", help=f"one of {', '.join(CAMERAS)}")
    s.add_argument("--width", type=int, default=320)
    s.add_argument("--height", type=int, default=240)
    s.add_argument("--fps", type=int, default=25, help="frames per simulated second (divides 100)")
    s.add_argument("--columns", type=int, default=3)
    s.add_argument("--out", default="runs/render/skills.mp4", help=".mp4 or .gif")
    s.add_argument("--no-progress", action="store_true")
    q = sub.add_parser("patterns", help="one HBR skill executed with several contact patterns, side by side")
    q.add_argument("--hbr", default=None, help="HBR file or run folder (default: the shipped HBR)")
    q.add_argument("--skill", type=int, default=None, help="skill number (default: the middle one)")
    q.add_argument("--patterns", default="any,63,47,61,45,31,59",
                   help="comma-separated contact patterns 0..63 (leg 0 = most significant bit) or any")
    for flag, default in (("--damage", "none"), ("--damage-model", "raised"), ("--camera", "track"), ("--width", 320),
                          ("--height", 240), ("--fps", 25), ("--columns", 4), ("--out", "runs/render/patterns.mp4")):
        q.add_argument(flag, type=type(default), default=default)
    q.add_argument("--no-progress", action="store_true")
    e = sub.add_parser("episode", help="a maze episode replayed from a maze_eval run folder (recorded with --video)")
    e.add_argument("run", help="run folder of python -m experiments.maze_eval --video N")
    e.add_argument("--variant", default=None, help="variant (default: the first recorded, in name order)")
    e.add_argument("--episode", type=int, default=0, help="the variant's episode number in the run (default 0, its first)")
    e.add_argument("--camera", default="top", help=f"one of {', '.join(CAMERAS)} (default top: the whole maze)")
    e.add_argument("--width", type=int, default=480)
    e.add_argument("--height", type=int, default=360)
    e.add_argument("--fps", type=int, default=25, help="video frames per second (default 25)")
    e.add_argument("--speed", type=float, default=4.0, help="simulated seconds per video second (default 4)")
    e.add_argument("--out", default=None, help=".mp4 or .gif (default <run>/videos/<variant>_ep<I>_<damage>.mp4)")
    e.add_argument("--no-progress", action="store_true")
    return p


def _chosen(count: int, filled: int, skills: str | None) -> np.ndarray:
    if skills is not None:
        try:
            chosen = np.asarray([int(k) for k in skills.split(",")], np.int64)
        except ValueError:
            raise ConfigError(f"--skills must be comma-separated integers, got {skills!r}") from None
        bad = chosen[(chosen < 0) | (chosen >= filled)]
        if bad.size:
            raise ConfigError(f"skill {int(bad[0])} out of range: the repertoire holds {filled} skills (0 .. {filled - 1})")
        return chosen
    if count < 1:
        raise ConfigError(f"--count must be >= 1, got {count}")
    return np.unique(np.linspace(0, filled - 1, min(count, filled)).round().astype(np.int64))


@functools.partial(jax.jit, static_argnames=("every",))
def _flat_states(robot, params, damage, every: int):
    start = standing_state(robot, damage)
    spec = RolloutSpec(num_steps=SKILL_STEPS, record_contacts=False, record_qpos_every=every)
    result = rollout(robot, params, damage, start, spec)
    return jnp.concatenate([result.qpos, result.final_state.qpos[:, None]], axis=1)


@functools.partial(jax.jit, static_argnames=("every",))
def _hbr_states(robot, hbr, genotypes, damage, every: int, patterns=None):
    result = execute_skill(robot, hbr, genotypes, standing_state(robot, damage), damage, patterns, record_every=every)
    steps = jnp.swapaxes(result.steps.qpos, 0, 1)  # (B, 3, F, 25)
    return jnp.concatenate([steps.reshape(steps.shape[0], -1, steps.shape[-1]), result.state.qpos[:, None]], axis=1)


def _setup(args):
    if args.fps < 1 or CONTROL_HZ % args.fps:
        raise ConfigError(f"--fps must divide {CONTROL_HZ}, got {args.fps}")
    damage = parse_damage(args.damage)
    return damage, load_robot(RobotConfig(damage_model=args.damage_model)), CONTROL_HZ // args.fps


def _load_hbr(path_arg):
    path = None if path_arg is None else resolve(path_arg)
    if path is not None and not Path(path).is_file():
        raise CheckpointError(f"{path}: no such HBR file")
    hbr, _, _ = load_hbr(path)
    return hbr, np.asarray(hbr.top.genotypes)[np.asarray(hbr.top.filled)]


def _parse_patterns(text: str) -> np.ndarray:
    patterns = []
    for item in text.split(","):
        item = item.strip()
        if item == "any":
            patterns.append(ANY_PATTERN)
        elif item.isdigit() and int(item) < NUM_PATTERNS:
            patterns.append(int(item))
        else:
            raise ConfigError(f"unknown contact pattern {item!r}: use 0..{NUM_PATTERNS - 1} or any")
    return np.asarray(patterns, np.int32)


def _pattern_label(pattern: int) -> str:
    return "any pattern" if pattern == ANY_PATTERN else f"pattern {pattern} ({pattern:06b})"


def pattern_states(args) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Recorded qpos (P, T, 25) of one skill under each pattern, the damage (6,) and clip labels."""
    patterns = _parse_patterns(args.patterns)
    damage, robot, every = _setup(args)
    hbr, genotypes = _load_hbr(args.hbr)
    skill = len(genotypes) // 2 if args.skill is None else args.skill
    skill = int(_chosen(1, len(genotypes), str(skill))[0])
    count = patterns.size
    batch = jnp.broadcast_to(jnp.asarray(damage), (count, damage.size))
    held = jnp.asarray(np.repeat(patterns[:, None], 3, axis=1))
    genes = jnp.asarray(np.repeat(genotypes[skill][None], count, axis=0))
    states = np.asarray(_hbr_states(robot, hbr, genes, batch, every, held))
    return states, damage, [_pattern_label(int(p)) for p in patterns]


def skill_states(args) -> tuple[np.ndarray, np.ndarray]:
    """Recorded qpos (N, T, 25) of the chosen skills and the damage mask (6,)."""
    damage, robot, every = _setup(args)
    if args.flat is not None:
        path = shipped_flat_path(args.flat) if args.flat in ("2d", "8d") else resolve(args.flat)
        if not Path(path).is_file():
            raise CheckpointError(f"{path}: no such repertoire file")
        flat, _ = load_flat(path)
        repertoire = flat[0]
        params = np.asarray(repertoire.genotypes)[np.asarray(repertoire.filled)]
        chosen = _chosen(args.count, len(params), args.skills)
        batch = jnp.broadcast_to(jnp.asarray(damage), (chosen.size, damage.size))
        return np.asarray(_flat_states(robot, jnp.asarray(params[chosen]), batch, every)), damage
    hbr, genotypes = _load_hbr(args.hbr)
    chosen = _chosen(args.count, len(genotypes), args.skills)
    batch = jnp.broadcast_to(jnp.asarray(damage), (chosen.size, damage.size))
    return np.asarray(_hbr_states(robot, hbr, jnp.asarray(genotypes[chosen]), batch, every)), damage


def render_clips(args) -> Path:
    """Simulate what `args.command` asks for, render every clip and write the grid video."""
    camera = Camera(args.camera, distance=1.2 if args.camera == "track" else 2.0)
    if args.columns < 1:
        raise ConfigError(f"--columns must be >= 1, got {args.columns}")
    if Path(args.out).suffix not in (".mp4", ".gif"):
        raise ConfigError(f"--out must end in .mp4 or .gif, got {args.out!r}")
    if args.command == "patterns":
        states, damage, labels = pattern_states(args)
    else:
        (states, damage), labels = skill_states(args), None
    model = render_model(RobotConfig(damage_model=args.damage_model), damage)
    renderer = open_renderer(model, args.width, args.height)
    try:
        with tqdm(total=states.shape[0] * states.shape[1], desc="render", unit="frame",
                  disable=args.no_progress) as bar:
            clips = [render_frames(model, qpos, renderer, camera, bar) for qpos in states]
    finally:
        renderer.close()
    if labels is not None:
        clips = [label(clip, text) for clip, text in zip(clips, labels)]
    return write_video(args.out, tile(clips, min(args.columns, len(clips))), args.fps)


def _numbers(numbers: list[int]) -> str:
    if len(numbers) > 2 and numbers == list(range(numbers[0], numbers[-1] + 1)):
        return f"{numbers[0]}..{numbers[-1]}"
    return ", ".join(map(str, numbers))


def chosen_replay(args) -> Replay:
    """The recorded episode `args` names in run folder `args.run`; ConfigError listing what is there."""
    run = Path(args.run)
    if not run.is_dir():
        raise ConfigError(f"{run}: no such run folder")
    available = recorded_episodes(run)
    if not available:
        raise ConfigError(f"{run} holds no recorded episodes ({REPLAY_DIR}/); record them with "
                          f"python -m experiments.maze_eval --video N --out {run} ...")
    listed = "; ".join(f"{v}: episodes {_numbers(n)}" for v, n in available.items())
    variant = next(iter(available)) if args.variant is None else args.variant
    if variant not in available:
        raise ConfigError(f"no recorded episode of variant {variant!r} in {run} (recorded: {listed})")
    if args.episode not in available[variant]:
        raise ConfigError(f"episode {args.episode} of {variant} is not recorded in {run} (recorded: {listed}; "
                          "maze_eval --video N records the first N episodes of each variant)")
    return load_replay(replay_path(run, variant, args.episode))


def episode_video(args) -> Path:
    """Render the chosen recorded episode and write its video."""
    if args.fps < 1:
        raise ConfigError(f"--fps must be >= 1, got {args.fps}")
    if args.out is not None and Path(args.out).suffix not in (".mp4", ".gif"):
        raise ConfigError(f"--out must end in .mp4 or .gif, got {args.out!r}")
    replay = chosen_replay(args)
    stride = args.speed * CONTROL_HZ / replay.every / args.fps  # recorded states per frame
    if not (stride >= 1 and abs(stride - round(stride)) < 1e-9):
        raise ConfigError(f"--speed {args.speed} at --fps {args.fps} shows {stride:g} recorded states per frame "
                          f"({CONTROL_HZ // replay.every} per simulated second); choose them to make it a whole number >= 1")
    info = replay.info
    out = args.out or Path(args.run) / "videos" / f"{info['variant']}_ep{info['episode']}_{info['damage']}.mp4"
    frames = frame_states(replay, round(stride))
    with tqdm(total=len(frames), desc="render", unit="frame", disable=args.no_progress) as bar:
        video = render_episode(replay, args.width, args.height, args.camera, round(stride), hold=args.fps, progress=bar)
    return write_video(out, video, args.fps)


@interruptible()  # Ctrl-C: `interrupted: nothing written` (the video is written at the end)
def main(argv=None) -> int:
    args = parser().parse_args(argv)
    with input_errors(ConfigError, CheckpointError, RenderError) as errors:
        written = episode_video(args) if args.command == "episode" else render_clips(args)
    if errors.failed:
        return 2
    print(f"wrote {written}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
