"""Every command of `experiments/` end to end, in ONE process, on the devices that process sees
(`tests/test_commands.py` starts it with 2 forced CPU devices), with tiny settings.

    XLA_FLAGS=--xla_force_host_platform_device_count=2 python -m tests.commands_script OUT [--render]

Each command's `main(argv)` runs in turn (so programs compiled for one, the tiny HBR's rollouts
say, serve the next) on the outputs of the ones before: the tiny HBR, its sparing archive and
the flat repertoires make the repertoire seed folder that `maze_eval` runs on (in a maze whose
goal its episodes reach at once). After every command OUT/commands.json records each command's exit status (an
exception is recorded as its traceback's last line, and the next command still runs), wall and
CPU time; the test checks them and the files under OUT/<command>/.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import sys
import time
import traceback
from pathlib import Path

# train_hbr measures the tiny HBR's step model in several blocks of STEP_CHUNK samples; measure_steps
# re-measures it with its default chunk: one block of all 512 samples, 256 rows per device, the shape
# whose batched Cholesky deadlocked XLA's CPU pool before hte_jax sized it (hte_jax/cpu_pool.py).
STEP_CHUNK = 32
NEAR_GOAL = "near_goal_maze.json"  # the maze maze_eval runs in (`near_goal_maze`)


def commands(out: Path, render: bool) -> list[tuple[str, str, list[str]]]:
    """(name, module, argv) of every command, in the order they run."""
    hbr, seeds = out / "train_hbr", out / "seeds" / "0"
    quiet = ["--no-progress"]
    # maze_eval keeps its default action cap (80): several episodes under that cap hung on 2 cores before
    # their first action (issue 40). In the maze of `seed_folder` every episode ends at its goal after
    # its first valid action: the programs of the default cap, compiled and run to the episodes' end.
    planner = ["--damage", "leg1", "--replicates", "2", "--iterations", "10", "--roots", "1", "--depth", "3",
               "--candidates", "10", "--maze", str(out / NEAR_GOAL)]
    chunk = ["--set", f"step_chunk={STEP_CHUNK}"]
    # Compiling each MJX program for 2 devices is most of the cost: the HBR trains its layers'
    # generations (the crash of issue 36 came after them), the other trainings only their initial
    # batches (generations on several devices: tests/test_sharding.py).
    steps = [
        ("train_hbr", "train_hbr", ["--preset", "tiny", "--out", str(hbr), *chunk, *quiet]),
        *[(f"train_flat_{v}", "train_flat", ["--variant", v, "--preset", "tiny", "--generations", "0",
                                              "--out", str(out / f"train_flat_{v}"), *quiet])
          for v in ("2d", "8d", "aprol")],
        ("train_spare", "train_spare", ["--hbr", str(hbr), "--preset", "tiny", *chunk,
                                        "--set", "middle.generations=0", "--out", str(out / "train_spare"), *quiet]),
        ("measure_steps", "measure_steps", ["--hbr", str(hbr), "--out", str(out / "measure_steps" / "hbr.npz"),
                                            "--starts", "2", *quiet]),
        ("seed_folder", "", []),  # not a command: the repertoire seed folder maze_eval reads
        ("maze_eval", "maze_eval", ["--repertoire-dir", str(seeds.parent), "--variant", "hte-spare,rte-spare,2d-rte",
                                    *planner, "--out", str(out / "maze_eval"), *quiet]),
        ("modulation", "modulation", ["--hbr", str(hbr), "--skills", "2", "--patterns", "candidates",
                                      "--chunk", "16", "--out", str(out / "modulation"), *quiet]),
        ("repertoire_stats", "repertoire_stats", ["--hbr", str(hbr), "--flat8d", str(out / "train_flat_8d"),
                                                  "--flat2d", str(out / "train_flat_2d"),
                                                  "--out", str(out / "repertoire_stats")]),
        ("inspect_checkpoint", "inspect_checkpoint", [str(hbr / "middle" / "checkpoint.npz")]),
    ]
    if render:
        steps.append(("render", "render", ["skills", "--hbr", str(hbr), "--count", "1", "--width", "64",
                                           "--height", "48", "--fps", "5", "--out", str(out / "render" / "skills.gif"),
                                           *quiet]))
    return steps


def seed_folder(out: Path) -> int:
    """seeds/0/ with the files `maze_eval --repertoire-dir` reads: the tiny HBR, its spare archive beside it
    (hte-spare's sparing sets), the flat 2-D repertoire; and the maze `maze_eval` runs in (`NEAR_GOAL`)."""
    folder = out / "seeds" / "0"
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(out / "train_hbr" / "hbr.npz", folder / "hbr.npz")
    shutil.copyfile(out / "train_spare" / "spare.npz", folder / "spare.npz")
    shutil.copyfile(out / "train_flat_2d" / "repertoires.npz", folder / "flat2d.npz")
    (out / NEAR_GOAL).write_text(json.dumps(near_goal_maze()))
    return 0


def near_goal_maze() -> dict:
    """The paper's maze (its walls, boxes and start) with the goal at the start and a radius that
    holds the whole maze: an episode reaches it with its first valid action."""
    from hte_jax.online.maze import PAPER_MAZE

    x, y, _ = PAPER_MAZE.start
    return {"goal": [x, y], "goal_radius": 4.0}


def run(name: str, module: str, argv: list[str], out: Path) -> int | str:
    if not module:
        return seed_folder(out)
    main = getattr(__import__(f"experiments.{module}", fromlist=["main"]), "main")
    try:
        return int(main(argv) or 0)
    except SystemExit as stop:  # argparse
        return stop.code if isinstance(stop.code, int) else 1
    except Exception:  # noqa: BLE001 - recorded for the test, and the next command still runs
        traceback.print_exc()
        return traceback.format_exc().strip().splitlines()[-1]


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out")
    p.add_argument("--render", action="store_true", help="also `render` (needs a GL context: MUJOCO_GL set)")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    import jax

    record = {"devices": jax.device_count(), "commands": {}}
    for name, module, command in commands(out, args.render):
        began, cpu = time.perf_counter(), _cpu_seconds()
        print(f"== {name}: {' '.join(command)}", flush=True)
        status = run(name, module, command, out)
        record["commands"][name] = {"status": status, "wall_time_s": round(time.perf_counter() - began, 1),
                                    "cpu_s": round(_cpu_seconds() - cpu, 1)}
        (out / "commands.json").write_text(json.dumps(record, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
