"""Throughput on 1, 2, 4, ... devices: a top-layer MAP-Elites generation and a maze_eval episode
batch, each spread over N devices by `hte_jax.sharding`, with parallel efficiency against 1 device.

Every device count runs in its own subprocess (a fresh backend per N). Per N: the bare MJX rollout
of `benchmarks/batch_size.py` at --batch (simulated steps/s; one device runs batch_size.py's very
program), and compile time,
median of --repeats timed runs, evaluations/s and simulated control steps/s of a top-layer
generation (--batch skills of 3 s on the shipped HBR's lower layers), and episodes/s and simulated
control steps/s of one action of an episode batch (--episodes episodes of HTE on the shipped HBR,
7 damages). Efficiency = throughput(N) / (N x throughput(1)). --impl jax,warp measures every device
count under each of MJX's implementations (RobotConfig.impl) in turn, in the same run, and prints
the throughput ratios of each implementation to the first.

    python benchmarks/scaling.py                                   # GPU: all visible devices, batch 32768, 210 episodes
    python benchmarks/scaling.py --cpu-devices 4 --batch 64 --episodes 14 --repeats 3   # CPU, 4 fake devices
    python benchmarks/scaling.py --devices 1 --impl jax,warp       # GPU: MJX's two backends, same run

Prints a table and writes JSON to benchmarks/results/.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

from common import environment, random_params, result_path, run_worker

SECONDS_PER_SKILL = 3
CONTROL_STEPS_PER_S = 100
SECONDS_PER_ACTION = 4  # a skill and the neutral second after it


def _parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--devices", default=None, help="comma-separated device counts (default 1, 2, 4, ... up to all)")
    p.add_argument("--cpu-devices", type=int, default=0, help="fake this many CPU devices (XLA host platform)")
    p.add_argument("--batch", type=int, default=32768, help="top-layer generation batch size")
    p.add_argument("--episodes", type=int, default=210, help="episodes of the maze_eval batch (0: skip)")
    p.add_argument("--iterations", type=int, default=1000, help="planner iterations of the episode batch")
    p.add_argument("--repeats", type=int, default=5, help="timed runs per measurement (median reported)")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds allowed per device count")
    p.add_argument("--impl", default="jax", help="comma-separated MJX implementations, each measured at every "
                                                 "device count (jax, warp; default jax)")
    p.add_argument("--out", type=Path, default=None, help="JSON path (default: results/scaling_<device>_<date>.json)")
    p.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    return p.parse_args(argv)


def _timed(fn, repeats):
    import jax

    tick = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - tick
    times = []
    for _ in range(repeats):
        tick = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - tick)
    return first, statistics.median(times)


def _worker(args) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from hte_jax import sharding
    from hte_jax.config import with_overrides
    from hte_jax.hbr.store import load_hbr
    from hte_jax.hbr.training import PRESETS, layer_algorithms
    from hte_jax.online.evaluation import EvalConfig, run_batch
    from hte_jax.online.mcts import PlannerConfig
    from hte_jax.sim.robot import RobotConfig, SolverConfig, load_robot
    from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state

    devices = args.worker
    mesh = sharding.batch_mesh(devices)
    impl = args.impl
    row = {"devices": devices, "impl": impl, "batch": args.batch, "episodes": args.episodes}

    # the bare MJX rollout of benchmarks/batch_size.py (3 s, random controllers) through the sharded
    # path: on one device the same program, so its steps/s is batch_size.py's
    rollout_robot = load_robot(RobotConfig(impl=impl))
    params = jnp.asarray(random_params(args.batch))
    steps = SECONDS_PER_SKILL * CONTROL_STEPS_PER_S
    spec = RolloutSpec(num_steps=steps, pose_steps=(0, steps), record_contacts=True)
    init, damage = standing_state(rollout_robot), jnp.zeros(6, bool)
    rollout_robot, init, damage, params = sharding.put_replicated((rollout_robot, init, damage, params), mesh)

    def bare():
        with sharding.spread_over(mesh):
            return rollout(rollout_robot, params, damage, init, spec)

    first, run_s = _timed(bare, args.repeats)
    row |= {"rollout_compile_s": first - run_s, "rollout_s": run_s,
            "rollout_steps_per_s": args.batch * steps * rollout_robot.config.substeps / run_s}

    hbr, _, _ = load_hbr(None)
    base = PRESETS["tiny"]
    config = with_overrides(base, {"top.batch_size": args.batch, "top.init_size": args.batch,
                                   "middle_samples": hbr.middle_task.samples,
                                   "contact_threshold": hbr.middle_task.contact_threshold, "solver.impl": impl})
    robot = load_robot(config.robot)
    algo = layer_algorithms(config, robot, standing_state(robot), {"bottom": hbr.bottom, "middle": hbr.middle},
                            mesh)["top"]()
    state = algo.place(algo.init(jax.random.PRNGKey(0)))
    first, run_s = _timed(lambda: algo.run_block(state, 1), args.repeats)
    row |= {"generation_compile_s": first - run_s, "generation_s": run_s,
            "evaluations_per_s": args.batch / run_s,
            "generation_steps_per_s": args.batch * SECONDS_PER_SKILL * CONTROL_STEPS_PER_S / run_s}

    if args.episodes:
        damages = ["none", "leg0", "leg1", "leg2", "leg3", "leg4", "legs1+4"]
        replicates = -(-args.episodes // len(damages))
        eval_config = EvalConfig(variants="hte", damages=",".join(damages), replicates=replicates, max_actions=1,
                                 planner=PlannerConfig(iterations=args.iterations, roots=4), solver=SolverConfig(impl=impl))
        run_batch(eval_config, None, ["hte"], progress=False, mesh=mesh)  # compiles
        times = []
        for _ in range(args.repeats):
            result = run_batch(eval_config, None, ["hte"], progress=False, mesh=mesh)
            times.append(result.timings.plan[0] + result.timings.act[0])
        count = int(np.asarray(result.episodes.taken).shape[0])
        action_s = statistics.median(times)
        row |= {"episodes": count, "action_s": action_s, "episodes_per_s": count / action_s,
                "episode_steps_per_s": count * SECONDS_PER_ACTION * CONTROL_STEPS_PER_S / action_s}
    return row


def main(argv=None):
    args = _parse(argv)
    if args.worker is not None:
        print(json.dumps(_worker(args)))
        return
    if args.cpu_devices:
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={args.cpu_devices}"
        os.environ["JAX_PLATFORMS"] = "cpu"
    import jax

    env = environment()
    visible = jax.device_count()
    counts = ([int(n) for n in args.devices.split(",")] if args.devices
              else [n for n in (2**k for k in range(12)) if n <= visible])
    impls = [impl.strip() for impl in args.impl.split(",") if impl.strip()]
    rows = []
    for n in counts:
        for impl in impls:
            cmd = [sys.executable, __file__, "--worker", str(n), "--batch", str(args.batch), "--episodes",
                   str(args.episodes), "--iterations", str(args.iterations), "--repeats", str(args.repeats),
                   "--impl", impl]
            rows.append(run_worker(cmd, args.timeout, {"devices": n, "impl": impl}))
            print(json.dumps(rows[-1]), flush=True)
    keys = ("rollout_steps_per_s", "evaluations_per_s", "episodes_per_s")
    for row in rows:
        ones = next((r for r in rows if r["devices"] == 1 and r["impl"] == row["impl"] and "error" not in r), None)
        first = next((r for r in rows if r["devices"] == row["devices"] and r["impl"] == impls[0] and "error" not in r), None)
        for key in keys:
            if ones is not None and "error" not in row and key in row:
                row[key.replace("_per_s", "_efficiency")] = row[key] / (row["devices"] * ones[key])
            if len(impls) > 1 and first is not None and "error" not in row and key in row:
                row[key.replace("_per_s", f"_over_{impls[0]}")] = row[key] / first[key]
    print(f"\n{'impl':>5} {'devices':>7} {'rollout steps/s':>15} {'eff':>5}  {'gen s':>8} {'evals/s':>10} {'steps/s':>12} {'eff':>5}   {'action s':>8} "
          f"{'episodes/s':>10} {'steps/s':>10} {'eff':>5}")
    for r in rows:
        if "error" in r:
            print(f"{r['impl']:>5} {r['devices']:>7} error: {r['error']}")
            continue
        line = (f"{r['impl']:>5} {r['devices']:>7} {r['rollout_steps_per_s']:>15,.0f} {r.get('rollout_steps_efficiency', float('nan')):>5.2f}  "
                f"{r['generation_s']:>8.3f} {r['evaluations_per_s']:>10,.0f} "
                f"{r['generation_steps_per_s']:>12,.0f} {r.get('evaluations_efficiency', float('nan')):>5.2f}")
        if "action_s" in r:
            line += (f"   {r['action_s']:>8.3f} {r['episodes_per_s']:>10,.1f} {r['episode_steps_per_s']:>10,.0f} "
                     f"{r.get('episodes_efficiency', float('nan')):>5.2f}")
        print(line)
    if len(impls) > 1:
        print(f"\nthroughput over {impls[0]} at the same device count (rollout, top-layer generation, episodes):")
        for r in rows:
            if r["impl"] != impls[0] and "error" not in r:
                ratios = [r.get(key.replace("_per_s", f"_over_{impls[0]}")) for key in keys]
                print(f"{r['impl']:>5} {r['devices']:>7}  " + "  ".join("-" if v is None else f"{v:.2f}" for v in ratios))
    env["devices_visible"] = visible
    out = args.out or result_path("scaling", env)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"environment": env, "settings": vars(args) | {"out": str(out)}, "rows": rows},
                              indent=2, default=str) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
