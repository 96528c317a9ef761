"""Throughput of batched hexapod rollouts versus batch size, with native MuJoCo as reference.

For batch sizes 1, 2, 4, ... each size runs in its own subprocess (so peak memory is
per size, an out-of-memory or hung size cannot take the sweep down, and the sweep
stops at the first size that does not fit). Per size: compile time, median run time
of --repeats runs, simulated physics steps/s, 3 s rollouts/s, peak memory. Then, in
the same run, native MuJoCo's multithreaded `mujoco.rollout` on the same robot with
all cores, as the reference line (open-loop position-servo targets from the same
controllers; see docs/design.md). --compare SETTING ("S/L[@tol=T][@dt=D][@impl=I]", see
physics_frontier.py) times a second MJX setting at every batch size, right after the first,
and prints the throughput ratio (first / compared) at each size; --impl warp with --compare 4/4
(or --compare 4/4@impl=warp) compares MJX's two implementations in the same run.

    python benchmarks/batch_size.py                      # CPU: 1 .. 1024
    python benchmarks/batch_size.py --max-batch 131072   # GPU
    python benchmarks/batch_size.py --min-batch 8192 --max-batch 131072 --compare 4/8   # new vs old default
    python benchmarks/batch_size.py --min-batch 8192 --max-batch 131072 --impl warp --compare 4/4 \
        --native-batches ''                                      # MJX's Warp backend vs its JAX one

Prints a table and writes JSON to benchmarks/results/.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time
from pathlib import Path

from common import earlier_result, environment, parse_setting, random_params, result_path, run_worker, setting_label

CONTROL_DT = 0.01


def _parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--min-batch", type=int, default=1)
    p.add_argument("--max-batch", type=int, default=None, help="default: 1024 on CPU, 131072 on GPU")
    p.add_argument("--steps", type=int, default=300, help="control steps per rollout (300 = 3 s)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per size (median reported)")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds allowed per batch size")
    p.add_argument("--solver-iterations", type=int, default=None)
    p.add_argument("--ls-iterations", type=int, default=None)
    p.add_argument("--no-joint-limits", action="store_true")
    p.add_argument("--impl", default=None, help="MJX's implementation, jax (default) or warp")
    p.add_argument("--compare", default=None, help="a second solver setting timed at every MJX batch size, e.g. 4/8")
    p.add_argument("--native-batches", type=str, default="64,256,1024,4096",
                   help="comma-separated batch sizes for native MuJoCo ('' to skip)")
    p.add_argument("--out", type=Path, default=None, help="JSON path (default: results/batch_size_<device>_<date>.json)")
    p.add_argument("--merge", type=Path, nargs="*", default=[],
                   help="JSON files of earlier partial sweeps on the same device to include")
    p.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--native-worker", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--worker-setting", default=None, help=argparse.SUPPRESS)
    return p.parse_args(argv)


def _robot_config(args, setting: str | None = None):
    """The robot of the flags, with a setting string ("S/L[@tol=T][@dt=D][@impl=I]") on top."""
    from hte_jax.sim.robot import RobotConfig

    overrides = {}
    if args.solver_iterations is not None:
        overrides["solver_iterations"] = args.solver_iterations
    if args.ls_iterations is not None:
        overrides["ls_iterations"] = args.ls_iterations
    if args.no_joint_limits:
        overrides["joint_limits"] = False
    if args.impl is not None:
        overrides["impl"] = args.impl
    if setting is not None:  # a setting string names its implementation (none: jax), whatever --impl says
        overrides.update({"impl": RobotConfig.impl, **parse_setting(setting)})
    return RobotConfig(**overrides)


def _worker(args) -> dict:
    """Time the MJX rollout at one batch size (runs in a subprocess)."""
    import jax
    import jax.numpy as jnp

    from hte_jax.sim.robot import load_robot
    from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state

    batch = args.worker
    robot = load_robot(_robot_config(args, args.worker_setting))
    init = standing_state(robot)
    params = jnp.asarray(random_params(batch))
    damage = jnp.zeros(6, bool)
    spec = RolloutSpec(num_steps=args.steps, pose_steps=(0, args.steps), record_contacts=True)

    t0 = time.perf_counter()
    lowered = rollout.lower(robot, params, damage, init, spec=spec)
    compiled = lowered.compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(robot, params, damage, init))  # warm-up
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        result = jax.block_until_ready(compiled(robot, params, damage, init))
        times.append(time.perf_counter() - t0)
    run_s = statistics.median(times)
    substeps = robot.config.substeps
    memory = compiled.memory_analysis()
    xla_bytes = None
    if memory is not None:
        xla_bytes = sum(
            getattr(memory, name, 0) or 0
            for name in ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes")
        )
    stats = jax.devices()[0].memory_stats() or {}
    return {
        "engine": "mjx",
        "impl": robot.config.impl,
        "batch": batch,
        "compile_s": compile_s,
        "run_s": run_s,
        "run_s_all": times,
        "steps_per_s": batch * args.steps * substeps / run_s,
        "rollouts_per_s": batch / run_s * (args.steps * CONTROL_DT / 3.0),
        "peak_device_bytes": stats.get("peak_bytes_in_use"),
        "xla_bytes": xla_bytes,
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "valid_fraction": float(result.valid.mean()),
    }


def _native_worker(args) -> dict:
    """Time native MuJoCo's threaded rollout at one batch size (runs in a subprocess)."""
    import mujoco
    import numpy as np
    from mujoco import rollout as mj_rollout

    import jax.numpy as jnp

    from hte_jax.sim.controller import target_table
    from hte_jax.sim.controller import SERVO_TIME_CONSTANT
    from hte_jax.sim.robot import build_spec, load_robot
    from hte_jax.sim.rollout import standing_state

    batch = args.native_worker
    config = _robot_config(args, args.worker_setting)
    spec = build_spec(config)
    for actuator in spec.actuators:  # same servo law, open loop: kp (target - q) - kv qdot
        actuator.set_to_position(kp=config.servo_gain / SERVO_TIME_CONSTANT, kv=config.servo_gain)
        actuator.forcerange = [-config.max_torque, config.max_torque]
        actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
    model = spec.compile()
    nthread = os.cpu_count() or 1
    datas = [mujoco.MjData(model) for _ in range(nthread)]

    init = standing_state(load_robot(config))
    data = mujoco.MjData(model)
    data.qpos[:] = np.asarray(init.qpos)
    data.qvel[:] = np.asarray(init.qvel)
    size = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    state0 = np.empty(size)
    mujoco.mj_getState(model, data, state0, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    initial = np.tile(state0, (batch, 1))
    tables = np.asarray(jnp.stack([target_table(jnp.asarray(p)) for p in random_params(min(batch, 64))]))
    tables = np.resize(tables, (batch, *tables.shape[1:]))  # (B, 100, 18), repeated
    rows = np.arange(args.steps) % tables.shape[1]
    control = np.repeat(tables[:, rows, :], config.substeps, axis=1).astype(np.float64)
    nstep = args.steps * config.substeps
    with mj_rollout.Rollout(nthread=nthread) as runner:
        runner.rollout(model, datas, initial, control, nstep=nstep)  # warm-up
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            runner.rollout(model, datas, initial, control, nstep=nstep)
            times.append(time.perf_counter() - t0)
    run_s = statistics.median(times)
    return {
        "engine": "native",
        "batch": batch,
        "threads": nthread,
        "run_s": run_s,
        "run_s_all": times,
        "steps_per_s": batch * nstep / run_s,
        "rollouts_per_s": batch / run_s * (args.steps * CONTROL_DT / 3.0),
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
    }


def _spawn(flag: str, batch: int, args, setting: str | None = None) -> dict:
    cmd = [sys.executable, __file__, flag, str(batch), "--steps", str(args.steps), "--repeats", str(args.repeats)]
    for name in ("solver_iterations", "ls_iterations"):
        if getattr(args, name) is not None:
            cmd += [f"--{name.replace('_', '-')}", str(getattr(args, name))]
    if args.no_joint_limits:
        cmd.append("--no-joint-limits")
    if args.impl is not None:
        cmd += ["--impl", args.impl]
    if setting is not None:
        cmd += ["--worker-setting", setting]
    return run_worker(cmd, args.timeout, {"batch": batch})


def _merged_rows(paths, env, settings) -> list:
    """Rows of earlier partial sweeps (a long sweep may be split across time-limited jobs)."""
    rows = []
    for path in paths:
        earlier = earlier_result(path, env)
        if earlier["settings"] != settings:
            raise SystemExit(f"{path} used settings {earlier['settings']}, not {settings}")
        rows += earlier["rows"]
    return rows


def _fmt_bytes(n) -> str:
    return "-" if n is None else f"{n / 2**20:,.0f} MiB"


def _table(rows) -> str:
    head = (f"{'engine':7} {'setting':>14} {'batch':>7} {'compile s':>9} {'run s':>8} {'steps/s':>11} {'rollouts/s':>10} "
            f"{'peak dev':>11} {'XLA bufs':>11} {'peak RSS':>11}")
    lines = [head, "-" * len(head)]
    for r in rows:
        if "error" in r:
            lines.append(f"{r.get('engine', 'mjx'):7} {r.get('setting', '-'):>14} {r['batch']:>7} {r['error']}")
            continue
        lines.append(
            f"{r['engine']:7} {r.get('setting', '-'):>14} {r['batch']:>7} {r.get('compile_s', float('nan')):>9.1f} {r['run_s']:>8.3f} "
            f"{r['steps_per_s']:>11,.0f} {r['rollouts_per_s']:>10,.1f} "
            f"{_fmt_bytes(r.get('peak_device_bytes')):>11} {_fmt_bytes(r.get('xla_bytes')):>11} "
            f"{_fmt_bytes(r.get('peak_rss_bytes')):>11}"
        )
    return "\n".join(lines)


def main(argv=None):
    args = _parse(argv)
    if args.worker is not None:
        print(json.dumps(_worker(args)))
        return
    if args.native_worker is not None:
        print(json.dumps(_native_worker(args)))
        return

    env = environment()
    config = _robot_config(args)
    label = setting_label(config)
    compare = None
    if args.compare is not None:
        compare = setting_label(_robot_config(args, args.compare))
    settings = {"steps": args.steps, "repeats": args.repeats, "timestep": config.timestep,
                "solver_iterations": config.solver_iterations, "ls_iterations": config.ls_iterations,
                "joint_limits": config.joint_limits, "compare": compare, "impl": config.impl}
    max_batch = args.max_batch or (1024 if env["platform"] == "cpu" else 131072)
    rows = _merged_rows(args.merge, env, settings)
    batch = args.min_batch
    while batch <= max_batch:
        row = {"setting": label, **_spawn("--worker", batch, args)}
        rows.append(row)
        print(_table([row]).splitlines()[-1], flush=True)
        if compare is not None and not any(r.get("setting") == compare and "error" in r for r in rows):
            other = {"setting": compare, **_spawn("--worker", batch, args, args.compare)}
            rows.append(other)
            ratio = "" if "error" in row or "error" in other else f"   {label} / {compare}: {row['steps_per_s'] / other['steps_per_s']:.2f}"
            print(_table([other]).splitlines()[-1] + ratio, flush=True)
        if "error" in row:
            break  # the first size that does not fit ends the sweep
        batch *= 2
    native_batches = [int(b) for b in args.native_batches.split(",") if b.strip()]
    for batch in native_batches:
        row = _spawn("--native-worker", batch, args)
        row.setdefault("engine", "native")
        rows.append(row)
        print(_table([row]).splitlines()[-1], flush=True)

    mjx_ok = [r for r in rows if r.get("engine") == "mjx" and "error" not in r and r.get("setting", label) == label]
    compared = {r["batch"]: r for r in rows if r.get("engine") == "mjx" and "error" not in r and r.get("setting") == compare}
    native_ok = [r for r in rows if r.get("engine") == "native" and "error" not in r]
    summary = {}
    if mjx_ok:
        best = max(mjx_ok, key=lambda r: r["steps_per_s"])
        summary["best_mjx_batch"] = best["batch"]
        summary["best_mjx_steps_per_s"] = best["steps_per_s"]
    if native_ok:
        best_native = max(native_ok, key=lambda r: r["steps_per_s"])
        summary["best_native_batch"] = best_native["batch"]
        summary["best_native_steps_per_s"] = best_native["steps_per_s"]
    if mjx_ok and native_ok:
        summary["mjx_over_native"] = summary["best_mjx_steps_per_s"] / summary["best_native_steps_per_s"]
    if compared:
        best_compare = max(compared.values(), key=lambda r: r["steps_per_s"])
        summary["compare_setting"] = compare
        summary["best_compare_batch"] = best_compare["batch"]
        summary["best_compare_steps_per_s"] = best_compare["steps_per_s"]
        summary["ratio_by_batch"] = {str(r["batch"]): r["steps_per_s"] / compared[r["batch"]]["steps_per_s"]
                                     for r in mjx_ok if r["batch"] in compared}

    print()
    print(f"{env['device']} ({env['platform']}), jax {env['jax']}, mujoco {env['mujoco']}, "
          f"{env['cpu_count']} cores, {args.steps} control steps, median of {args.repeats}")
    print(_table(rows))
    for key, value in summary.items():
        print(f"{key}: {value:,.3f}" if isinstance(value, float) else f"{key}: {value}")

    out = args.out or result_path("batch_size", env)
    out.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "environment": env,
        "settings": settings,
        "rows": rows,
        "summary": summary,
    }
    out.write_text(json.dumps(payload, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
