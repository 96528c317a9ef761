"""Rendering speed: wall time to render and encode `--seconds` of video at a given size.

A shipped Flat-2D elite is simulated for the clip's length (not timed) with its state recorded
every frame; then, `--repeats` times, every frame is rendered with `mujoco.Renderer` (tracking
camera) and the clip is written as MP4. Prints a table and writes JSON (median of the repeats).

    python benchmarks/render_speed.py                       # 10 s at 480 x 360, 25 fps
    python benchmarks/render_speed.py --width 960 --height 720 --repeats 5

MUJOCO_GL is chosen as in `experiments.render` (hte_jax/viz/gl.py: EGL, then OSMesa) and recorded.
"""

from __future__ import annotations

import os
import sys

from hte_jax.viz import gl  # imports no mujoco

try:
    gl.setup()  # MUJOCO_GL, before mujoco is imported
except gl.RenderError as error:  # MUJOCO_GL is not a renderer
    print(f"error: {error}", file=sys.stderr)
    sys.exit(2)

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from common import environment, result_path  # noqa: E402

from hte_jax.flat.store import load_flat, shipped_flat_path  # noqa: E402
from hte_jax.sim.robot import STEPS_PER_SECOND, RobotConfig, load_robot  # noqa: E402
from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state  # noqa: E402
from hte_jax.viz.render import Camera, open_renderer, render_frames, render_model, write_video  # noqa: E402



def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=int, default=10)
    parser.add_argument("--fps", type=int, default=25, help="divides 100")
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=None, help="JSON path (default benchmarks/results/render_speed_...)")
    args = parser.parse_args(argv)
    if args.fps < 1 or STEPS_PER_SECOND % args.fps or args.seconds < 1 or args.repeats < 1:
        parser.error("--fps must divide 100; --seconds and --repeats must be >= 1")
    try:
        gl.require()
    except gl.RenderError as error:
        parser.exit(2, f"error: {error}\n")

    repertoire = load_flat(shipped_flat_path("2d"))[0][0]
    params = jnp.asarray(np.asarray(repertoire.genotypes)[np.asarray(repertoire.filled)][:1])
    robot = load_robot()
    spec = RolloutSpec(num_steps=args.seconds * STEPS_PER_SECOND, record_contacts=False,
                       record_qpos_every=STEPS_PER_SECOND // args.fps)
    qpos = np.asarray(rollout(robot, params, jnp.zeros(6, bool), standing_state(robot), spec).qpos[0])
    model = render_model(RobotConfig())
    renderer = open_renderer(model, args.width, args.height)
    render_s, encode_s = [], []
    try:
        render_frames(model, qpos[:2], renderer)  # first-frame setup (textures, context) not timed
        with tempfile.TemporaryDirectory() as scratch:
            for _ in range(args.repeats):
                start = time.perf_counter()
                frames = render_frames(model, qpos, renderer, Camera())
                middle = time.perf_counter()
                write_video(Path(scratch) / "clip.mp4", frames, args.fps)
                render_s.append(middle - start)
                encode_s.append(time.perf_counter() - middle)
    finally:
        renderer.close()
    env = environment()
    row = {
        "seconds_of_video": args.seconds, "fps": args.fps, "frames": int(qpos.shape[0]),
        "width": args.width, "height": args.height, "mujoco_gl": os.environ["MUJOCO_GL"],
        "render_s_median": statistics.median(render_s), "encode_s_median": statistics.median(encode_s),
        "total_s_median": statistics.median(r + e for r, e in zip(render_s, encode_s)),
        "render_s_all": render_s, "encode_s_all": encode_s,
    }
    row["frames_per_s"] = row["frames"] / row["render_s_median"]
    print(f"{'video':>8} {'size':>9} {'frames':>6} {'render s':>9} {'encode s':>9} {'total s':>8} {'frames/s':>9}")
    print(f"{args.seconds:>6} s {args.width}x{args.height:<4} {row['frames']:>6} {row['render_s_median']:>9.1f} "
          f"{row['encode_s_median']:>9.1f} {row['total_s_median']:>8.1f} {row['frames_per_s']:>9.1f}")
    out = Path(args.out) if args.out else result_path("render_speed", env)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"environment": env, "rows": [row]}, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
