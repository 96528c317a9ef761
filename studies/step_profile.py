"""What the project's rollout runs per control step besides MuJoCo Warp's physics, on one GPU (a study).

For each batch: the rollout's time per step (median of --repeats) with contacts recorded and not, then one traced
rollout (`jax.profiler`): per device stream, the kernels by summed time with their count per step, and the device's
busy time per step against the wall time per step.

    python studies/step_profile.py --batches 1260,16384 --trace /tmp/trace --out step_profile.json
"""

from __future__ import annotations

import argparse
import gzip
import json
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _kernels(folder: Path, steps: int) -> dict:
    path = max(folder.rglob("perfetto_trace.json.gz"))
    with gzip.open(path, "rt") as handle:
        events = json.load(handle)
    events = events["traceEvents"] if isinstance(events, dict) else events
    names = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
    per = defaultdict(lambda: defaultdict(lambda: [0.0, 0]))
    for e in events:
        if e.get("ph") == "X" and "dur" in e:
            where = names.get(e["pid"], str(e["pid"]))
            cell = per[where][e.get("name", "?")[:90]]
            cell[0] += e["dur"]
            cell[1] += 1
    out = {}
    for where, ops in per.items():
        total = sum(v[0] for v in ops.values())
        out[where] = {"us_per_step": round(total / steps, 2), "events_per_step": round(sum(v[1] for v in ops.values()) / steps, 1),
                      "top": [[name, round(us / steps, 2), round(n / steps, 2)]
                              for name, (us, n) in sorted(ops.items(), key=lambda kv: -kv[1][0])[:40]]}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batches", default="1260,16384")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--trace", default="/tmp/step_trace")
    p.add_argument("--out", default="step_profile.json")
    p.add_argument("--graph-mode", default="warp", choices=("warp", "jax"), help="MJX's Warp graph mode")
    p.add_argument("--conditional", type=int, default=1, help="MuJoCo Warp's conditional graph nodes (0: off)")
    p.add_argument("--no-trace", action="store_true")
    args = p.parse_args(argv)

    import jax
    import jax.numpy as jnp

    from benchmarks.common import environment
    from hte_jax.sim.robot import RobotConfig, load_robot
    from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state
    from hte_jax.warp_calls import waited

    from hte_jax.sim.mjx_import import mjx
    from hte_jax.sim.robot import Robot, mj_model, without_solver_cap_notices
    from mujoco.mjx.warp import types as warp_types

    config = RobotConfig(impl="warp")
    robot = load_robot(config)
    mode = getattr(warp_types.GraphMode, args.graph_mode.upper())
    model = without_solver_cap_notices(mjx.put_model(mj_model(config), impl="warp", graph_mode=mode))
    options = model.opt._impl.replace(graph_conditional=bool(args.conditional))
    robot = Robot(model=model.replace(opt=model.opt.replace(_impl=options)), info=robot.info)
    print("graph mode", model.opt._impl.graph_mode, "conditional", options.graph_conditional, flush=True)
    start = standing_state(robot)
    rows = []
    for batch in [int(b) for b in args.batches.split(",")]:
        params = jax.random.uniform(jax.random.PRNGKey(batch), (batch, 36))
        no_damage = jnp.zeros(6, bool)
        row = {"batch": batch}
        for label, spec in (("contacts", RolloutSpec(num_steps=args.steps)),
                            ("no_contacts", RolloutSpec(num_steps=args.steps, record_contacts=False))):
            waited(rollout, robot, params, no_damage, start, spec)
            times = []
            for _ in range(args.repeats):
                tick = time.perf_counter()
                waited(rollout, robot, params, no_damage, start, spec)
                times.append(time.perf_counter() - tick)
            row[f"{label}_ms_per_step"] = round(1e3 * statistics.median(times) / args.steps, 4)
        if args.no_trace:
            rows.append(row)
            print(json.dumps(row), flush=True)
            continue
        folder = Path(args.trace) / str(batch)
        spec = RolloutSpec(num_steps=args.steps)
        with jax.profiler.trace(str(folder), create_perfetto_trace=True):
            waited(rollout, robot, params, no_damage, start, spec)
        row["trace"] = _kernels(folder, args.steps)
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "trace"}), flush=True)
        for where, cell in row["trace"].items():
            print(f"  {where}: {cell['us_per_step']} us/step, {cell['events_per_step']} events/step", flush=True)
            for name, us, n in cell["top"][:25]:
                print(f"    {us:8.2f} us {n:6.2f}x  {name}", flush=True)
    Path(args.out).write_text(json.dumps({"environment": environment(), "steps": args.steps, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
