"""Where a physics step of the Warp backend goes, at several batch sizes, on one GPU (a study, not the product).

Three timings per batch B, each per physics step (median of --repeats):
  project  the project's `rollout` (3 s of random controllers: servo law, validity, one MJX step per control step)
  mjx      a jitted `lax.scan` of bare `mjx.step` (Warp backend, one FFI call per step, no control law)
  graph    MuJoCo Warp alone: k steps captured in one CUDA graph, replayed, no JAX and no Python per step
           (k = 1, 10, 100)
project - mjx is the control law's share; mjx - graph(k=1) what one FFI call adds to a step (Python callback,
while-loop sync); graph(1) - graph(100) what a graph launch adds. A step that k physics steps share one call
(control in Warp) could save at most mjx - graph(k).

    python studies/warp_step_floor.py --batches 1024,8192,16384,32768 --out floor.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        tick = time.perf_counter()
        fn()
        times.append(time.perf_counter() - tick)
    return statistics.median(times)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batches", default="1024,8192,16384,32768")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", default="warp_step_floor.json")
    args = p.parse_args(argv)

    import jax
    import jax.numpy as jnp
    import mujoco
    import numpy as np
    import warp as wp

    from benchmarks.common import environment
    from hte_jax.sim.mjx_import import mjx
    from hte_jax.sim.robot import RobotConfig, load_robot, mj_model, warp_capacity
    from hte_jax.sim.rollout import RolloutSpec, empty_data, rollout, standing_state
    from hte_jax.warp_calls import waited
    from mujoco.mjx.third_party import mujoco_warp as mjw

    config = RobotConfig(impl="warp")
    robot = load_robot(config)
    model = mj_model(config)
    contacts, constraint_rows = warp_capacity(config)
    start = standing_state(robot)
    spec = RolloutSpec(num_steps=args.steps, record_contacts=False)
    rows = []
    for batch in [int(b) for b in args.batches.split(",")]:
        key = jax.random.PRNGKey(batch)
        params = jax.random.uniform(key, (batch, 36), minval=0.0, maxval=1.0)
        no_damage = jnp.zeros(6, bool)
        waited(rollout, robot, params, no_damage, start, spec)  # compile
        project = _median_seconds(lambda: waited(rollout, robot, params, no_damage, start, spec), args.repeats)

        @jax.jit
        def bare(qpos, qvel, batch=batch):
            template = empty_data(robot, batch)  # as `rollout` makes it: Warp's buffers for the batch's rows

            def one(q, v):
                d = template.replace(qpos=q, qvel=v, ctrl=jnp.zeros(model.nu, jnp.float32))
                return jax.lax.scan(lambda d, _: (mjx.step(robot.model, d), None), d, None, length=args.steps)[0].qpos

            return jax.vmap(one)(qpos, qvel)

        qpos = jnp.broadcast_to(start.qpos, (batch, model.nq))
        qvel = jnp.broadcast_to(start.qvel, (batch, model.nv))
        waited(bare, qpos, qvel)
        mjx_s = _median_seconds(lambda: waited(bare, qpos, qvel), args.repeats)

        mjd = mujoco.MjData(model)
        mjd.qpos[:] = np.asarray(start.qpos)
        m = mjw.put_model(model)
        d = mjw.put_data(model, mjd, nworld=batch, naconmax=batch * contacts, njmax=constraint_rows)
        graphs = {}
        for k in (1, 10, 100):
            mjw.step(m, d)  # kernels built before the capture
            with wp.ScopedCapture() as capture:
                for _ in range(k):
                    mjw.step(m, d)
            graph = capture.graph

            def replay(graph=graph, k=k):
                for _ in range(args.steps // k):
                    wp.capture_launch(graph)
                wp.synchronize()

            replay()
            graphs[k] = _median_seconds(replay, args.repeats)
        row = {"batch": batch, "project_ms_per_step": 1e3 * project / args.steps,
               "mjx_ms_per_step": 1e3 * mjx_s / args.steps,
               **{f"graph{k}_ms_per_step": 1e3 * s / (args.steps // k * k) for k, s in graphs.items()}}
        rows.append(row)
        print(" ".join(f"{name}={value:.4f}" if isinstance(value, float) else f"{name}={value}"
                       for name, value in row.items()), flush=True)
    Path(args.out).write_text(json.dumps({"environment": environment(), "steps": args.steps,
                                          "repeats": args.repeats, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
