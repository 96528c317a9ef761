"""See the robot: videos of repertoire skills rendered with MuJoCo's renderer, headless.

    python -m experiments.render skills                                # 6 skills of the shipped HBR
    python -m experiments.render skills --damage leg1 --count 9        # the same under a raised leg 1
    python -m experiments.render skills --flat 2d --camera top         # elites of the shipped Flat-2D
    python -m experiments.render skills --hbr runs/hbr-gpu --skills 10,200,1500 --out runs/render/mine.gif

`skills` simulates each chosen skill for 3 s from standing (top-layer skills of an HBR, or the
controllers of a flat repertoire, intact or under a named damage), records the state every frame
and lays the clips out on a grid: a tracking camera (or `--camera top`, looking down), damaged legs
in red. MP4 through imageio-ffmpeg, GIF through Pillow (by the --out suffix). Headless OpenGL:
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

from hte_jax.errors import ConfigError  # noqa: E402
from hte_jax.flat.comparison import resolve  # noqa: E402
from hte_jax.flat.store import load_flat, shipped_flat_path  # noqa: E402
from hte_jax.hbr.execution import execute_skill  # noqa: E402
from hte_jax.hbr.store import load_hbr  # noqa: E402
from hte_jax.qd.io import CheckpointError  # noqa: E402
from hte_jax.sim.damage import parse_damage  # noqa: E402
from hte_jax.sim.robot import DAMAGE_MODELS, RobotConfig, load_robot  # noqa: E402
from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state  # noqa: E402
from hte_jax.viz.render import CAMERAS, Camera, RenderError, open_renderer, render_model, render_frames, tile, write_video  # noqa: E402

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
def _hbr_states(robot, hbr, genotypes, damage, every: int):
    result = execute_skill(robot, hbr, genotypes, standing_state(robot, damage), damage, record_every=every)
    steps = jnp.swapaxes(result.steps.qpos, 0, 1)  # (B, 3, F, 25)
    return jnp.concatenate([steps.reshape(steps.shape[0], -1, steps.shape[-1]), result.state.qpos[:, None]], axis=1)


def skill_states(args) -> tuple[np.ndarray, np.ndarray]:
    """Recorded qpos (N, T, 25) of the chosen skills and the damage mask (6,)."""
    if args.fps < 1 or CONTROL_HZ % args.fps:
        raise ConfigError(f"--fps must divide {CONTROL_HZ}, got {args.fps}")
    damage = parse_damage(args.damage)
    robot = load_robot(RobotConfig(damage_model=args.damage_model))
    every = CONTROL_HZ // args.fps
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
    path = None if args.hbr is None else resolve(args.hbr)
    if path is not None and not Path(path).is_file():
        raise CheckpointError(f"{path}: no such HBR file")
    hbr, _, _ = load_hbr(path)
    genotypes = np.asarray(hbr.top.genotypes)[np.asarray(hbr.top.filled)]
    chosen = _chosen(args.count, len(genotypes), args.skills)
    batch = jnp.broadcast_to(jnp.asarray(damage), (chosen.size, damage.size))
    return np.asarray(_hbr_states(robot, hbr, jnp.asarray(genotypes[chosen]), batch, every)), damage


def render_skills(args) -> Path:
    camera = Camera(args.camera, distance=1.2 if args.camera == "track" else 2.0)
    if args.columns < 1:
        raise ConfigError(f"--columns must be >= 1, got {args.columns}")
    if Path(args.out).suffix not in (".mp4", ".gif"):
        raise ConfigError(f"--out must end in .mp4 or .gif, got {args.out!r}")
    states, damage = skill_states(args)
    model = render_model(RobotConfig(damage_model=args.damage_model), damage)
    renderer = open_renderer(model, args.width, args.height)
    try:
        with tqdm(total=states.shape[0] * states.shape[1], desc="render", unit="frame",
                  disable=args.no_progress) as bar:
            clips = [render_frames(model, qpos, renderer, camera, bar) for qpos in states]
    finally:
        renderer.close()
    return write_video(args.out, tile(clips, min(args.columns, len(clips))), args.fps)


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        written = render_skills(args)
    except (ConfigError, CheckpointError, RenderError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"wrote {written}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
