"""See the robot: videos of repertoire skills rendered with MuJoCo's renderer, headless.

    python -m experiments.render skills                                # 6 skills of the shipped HBR: 77 s on 2 cores
    python -m experiments.render skills --damage leg1 --count 9        # the same under a raised leg 1
    python -m experiments.render skills --damage leg2:shortened=0.5:friction=0.6  # a short tibia, a slippery floor
    python -m experiments.render skills --flat 2d --camera top         # elites of the shipped Flat-2D
    python -m experiments.render skills --hbr runs/hbr-gpu --skills 10,200,1500 --out runs/render/mine.gif
    python -m experiments.render patterns --skill 1400 --damage leg1   # one skill, several contact patterns
    python -m experiments.render episode runs/maze-eval --variant hte --episode 0  # a recorded maze episode

`skills`: each chosen skill (top-layer skills of an HBR, or a flat repertoire's controllers, intact
or under a damage) simulated for 3 s from standing, the clips on a grid: a tracking camera (or
`--camera top`), damaged legs in red. --damage: one damage as `maze_eval --damage` spells it,
<legs>[:<model>[=<fraction>]][:friction=<scale>] (none, leg<i>, legs<i>+<j>; raised, locked, removed,
shortened=<f>, weak=<f>; the model defaults to --damage-model). `patterns`: one HBR skill executed with several contact
patterns held for its three steps ("any": RTE's nearest elite of any pattern), each clip labelled.
`episode`: a maze episode recorded by `maze_eval --video N` (<run>/replays/; --episode I is the
variant's I-th episode of the run), the maze seen from above (or --camera track), the goal in green,
the path as a blue trail, a panel naming the action, skill and each step's contact pattern; --speed:
simulated seconds per video second (default 4). MP4 (imageio-ffmpeg) or GIF (Pillow) by the --out suffix.

Headless OpenGL, chosen when MUJOCO_GL is unset: EGL (a GPU driver, or Mesa's software EGL), else
OSMesa (Debian package libosmesa6); when neither starts, one line says what to install. Arguments and
files are checked before OpenGL is needed. Bad input gives a one-line error and exit 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from experiments.cli import input_errors, interruptible
from hte_jax.control_step import STEPS_PER_SECOND
from hte_jax.errors import ConfigError, require_choice, require_int, require_number
from hte_jax.qd.io import CheckpointError
from hte_jax.viz import gl
from hte_jax.viz.camera import CAMERAS, Camera
from hte_jax.warp_calls import waited

# Nothing above imports mujoco or OpenGL: gl.setup() must choose MUJOCO_GL first. The modules that
# simulate and render are imported inside the commands, after it.
DAMAGE_MODELS = ("the model of a --damage that names none: raised (the damaged leg blocked in the air, default), "
                 "locked (its standing pose) or removed")
VIDEO_SUFFIXES = (".mp4", ".gif")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("skills", help="a grid video of repertoire skills")
    source = s.add_mutually_exclusive_group()
    source.add_argument("--hbr", default=None, help="HBR file or run folder (default: the shipped HBR)")
    source.add_argument("--flat", default=None, help="flat repertoire file, or 2d / 8d for the shipped ones")
    s.add_argument("--count", type=int, default=6, help="skills, spread evenly over the repertoire (default 6)")
    s.add_argument("--skills", default=None, help="comma-separated skill numbers (0 .. filled - 1) instead of --count")
    q = sub.add_parser("patterns", help="one HBR skill executed with several contact patterns, side by side")
    q.add_argument("--hbr", default=None, help="HBR file or run folder (default: the shipped HBR)")
    q.add_argument("--skill", type=int, default=None, help="skill number (default: the middle one)")
    q.add_argument("--patterns", default="any,63,47,61,45,31,59",
                   help="comma-separated contact patterns 0..63 (leg 0 = most significant bit) or any")
    for clips, columns, name in ((s, 3, "skills"), (q, 4, "patterns")):
        clips.add_argument("--damage", default="none", help="one damage, <legs>[:<model>[=<fraction>]][:friction=<scale>]: "
                           "e.g. leg1, leg0:removed, leg2:shortened=0.5:friction=0.6 (default none)")
        clips.add_argument("--damage-model", default="raised", help=DAMAGE_MODELS)
        clips.add_argument("--camera", default="track", help=f"one of {', '.join(CAMERAS)}")
        clips.add_argument("--width", type=int, default=320)
        clips.add_argument("--height", type=int, default=240)
        clips.add_argument("--fps", type=int, default=25, help="frames per simulated second (divides 100)")
        clips.add_argument("--columns", type=int, default=columns)
        clips.add_argument("--out", default=f"runs/render/{name}.mp4", help=".mp4 or .gif")
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
    for command in (s, q, e):
        command.add_argument("--no-progress", action="store_true")
    return p


def _skill_numbers(text: str | None) -> list[int] | None:
    if text is None:
        return None
    try:
        return [int(k) for k in text.split(",")]
    except ValueError:
        raise ConfigError(f"--skills must be comma-separated integers, got {text!r}") from None


def check_arguments(args) -> None:
    """The checks that need no simulation and no OpenGL (run before the GL backend is chosen)."""
    require_int("--width", args.width)
    require_int("--height", args.height)
    require_choice("--camera", args.camera, CAMERAS)
    if args.out is not None and Path(args.out).suffix not in VIDEO_SUFFIXES:
        raise ConfigError(f"--out must end in .mp4 or .gif, got {args.out!r}")
    if args.command == "episode":
        if args.fps < 1:
            raise ConfigError(f"--fps must be >= 1, got {args.fps}")
        require_number("--speed", args.speed, 0.0, open_low=True)
        if not Path(args.run).is_dir():
            raise ConfigError(f"{args.run}: no such run folder")
        return
    if args.fps < 1 or STEPS_PER_SECOND % args.fps:
        raise ConfigError(f"--fps must divide {STEPS_PER_SECOND}, got {args.fps}")
    require_int("--columns", args.columns)
    if args.hbr is not None and not Path(args.hbr).exists():
        raise CheckpointError(f"{args.hbr}: no such HBR file")
    if args.command == "skills":
        if args.flat is not None and args.flat not in ("2d", "8d") and not Path(args.flat).exists():
            raise CheckpointError(f"{args.flat}: no such repertoire file")
        if _skill_numbers(args.skills) is None and args.count < 1:
            raise ConfigError(f"--count must be >= 1, got {args.count}")


def chosen_damage(args):
    """The one damage `args.damage` spells (`damage.parse_damages` under `args.damage_model`): its leg mask where
    that says the same (`damage.mask_if_plain`), else an unbatched `Damage`; ConfigError for a bad spelling.
    It imports mujoco: after `gl.setup()`."""
    from hte_jax.sim.damage import mask_if_plain, parse_damages

    damages = parse_damages(args.damage, args.damage_model)
    if len(damages) != 1:
        raise ConfigError(f"--damage: give one damage, got {len(damages)} ({', '.join(damages)})")
    return mask_if_plain(next(iter(damages.values())), args.damage_model)


def _elites(args):
    """(the HBR, None for a flat repertoire; the genotypes of its elites) that --hbr / --flat name."""
    from hte_jax.flat.comparison import resolve
    from hte_jax.flat.store import load_flat, shipped_flat_path
    from hte_jax.hbr.store import load_hbr

    flat = getattr(args, "flat", None)
    if flat is None:
        path = None if args.hbr is None else resolve(args.hbr)
        if path is not None and not Path(path).is_file():
            raise CheckpointError(f"{path}: no such HBR file")
        hbr = load_hbr(path)[0]
        repertoire = hbr.top
    else:
        path = shipped_flat_path(flat) if flat in ("2d", "8d") else resolve(flat)
        if not Path(path).is_file():
            raise CheckpointError(f"{path}: no such repertoire file")
        hbr, repertoire = None, load_flat(path)[0][0]
    return hbr, np.asarray(repertoire.genotypes)[np.asarray(repertoire.filled)]


def skills_video(args) -> Path:
    """`skills` / `patterns`: load and check what `args` names, simulate the clips, render the grid, write the video."""
    import jax.numpy as jnp

    from hte_jax.sim.damage import batch_damage
    from hte_jax.sim.robot import RobotConfig, load_robot
    from hte_jax.viz import skills
    from hte_jax.viz.render import write_video

    config = RobotConfig(damage_model=args.damage_model)
    damage = chosen_damage(args)
    labels = held = None
    hbr, genotypes = _elites(args)
    if args.command == "patterns":
        patterns = skills.parse_patterns(args.patterns)
        skill = len(genotypes) // 2 if args.skill is None else args.skill
        picked = np.repeat(skills.chosen(1, len(genotypes), [skill]), patterns.size)
        labels = [skills.pattern_label(int(p)) for p in patterns]
        held = jnp.asarray(np.repeat(patterns[:, None], 3, axis=1))
    else:
        picked = skills.chosen(args.count, len(genotypes), _skill_numbers(args.skills))
    gl.require()  # every input is checked: OpenGL is needed from here on
    robot, every = load_robot(config), STEPS_PER_SECOND // args.fps
    batch = batch_damage(damage, picked.size)
    clips = jnp.asarray(genotypes[picked])
    states = np.asarray(waited(skills.flat_states, robot, clips, batch, every) if hbr is None
                        else waited(skills.hbr_states, robot, hbr, clips, batch, every, held))
    camera = Camera(args.camera, distance=1.2 if args.camera == "track" else 2.0)
    with tqdm(total=states.shape[0] * states.shape[1], desc="render", unit="frame", disable=args.no_progress) as bar:
        frames = skills.render_grid(states, damage, config, camera, args.width, args.height, args.columns, labels, bar)
    return write_video(args.out, frames, args.fps)


def _numbers(numbers: list[int]) -> str:
    if len(numbers) > 2 and numbers == list(range(numbers[0], numbers[-1] + 1)):
        return f"{numbers[0]}..{numbers[-1]}"
    return ", ".join(map(str, numbers))


def chosen_replay(args):
    """The recorded episode (a Replay) `args` names in run folder `args.run`; ConfigError listing what is there."""
    from hte_jax.online.recording import REPLAY_DIR, load_replay, recorded_episodes, replay_path

    run = Path(args.run)
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


def file_label(label: str) -> str:
    """A damage's label as a file name's part: "leg2:shortened=0.5:friction=0.6" -> "leg2_shortened0.5_friction0.6"."""
    return label.replace(":", "_").replace("=", "")


def episode_video(args) -> Path:
    """`episode`: load and check the chosen recorded episode, then render it and write its video."""
    from hte_jax.viz.episode import frame_states, render_episode
    from hte_jax.viz.render import write_video

    replay = chosen_replay(args)
    stride = args.speed * STEPS_PER_SECOND / replay.every / args.fps  # recorded states per frame
    if not (stride >= 1 and abs(stride - round(stride)) < 1e-9):
        raise ConfigError(f"--speed {args.speed} at --fps {args.fps} shows {stride:g} recorded states per frame "
                          f"({STEPS_PER_SECOND // replay.every} per simulated second); choose them to make it a whole number >= 1")
    gl.require()  # every input is checked: OpenGL is needed from here on
    info = replay.info
    out = args.out or Path(args.run) / "videos" / f"{info['variant']}_ep{info['episode']}_{file_label(info['damage'])}.mp4"
    frames = frame_states(replay, round(stride))
    with tqdm(total=len(frames), desc="render", unit="frame", disable=args.no_progress) as bar:
        video = render_episode(replay, args.width, args.height, args.camera, round(stride), hold=args.fps, progress=bar)
    return write_video(out, video, args.fps)


@interruptible()  # Ctrl-C: `interrupted: nothing written` (the video is written at the end)
def main(argv=None) -> int:
    args = parser().parse_args(argv)
    with input_errors(ConfigError, CheckpointError, gl.RenderError) as errors:
        check_arguments(args)
        gl.setup()  # MUJOCO_GL, before mujoco is imported; none starts: gl.require() says why, after the checks
        written = episode_video(args) if args.command == "episode" else skills_video(args)
    if errors.failed:
        return 2
    print(f"wrote {written}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
