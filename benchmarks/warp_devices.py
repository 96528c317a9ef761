"""Minimal reproduction: MJX's Warp backend (impl='warp') stepped on N devices, each variant in its own
process with a timeout, so that a crash (SIGSEGV: exit -11) or a hang is recorded instead of ending the run.

Variants (the batch of B bodies, K steps of `mjx.step` in a `lax.scan`, on the first N devices):
  empty       no MJX, no Warp: `jax.shard_map` of a function that uses a zero-sized replicated array
              (MJX's Warp models and data hold such arrays); jax 0.11.2's Shardy crashed on it (SIGSEGV)
  single      one device: jit(scan(vmap(mjx.step))), the reference every other variant is compared with
  shard_map   the batch split over a 1-D mesh by a plain `jax.shard_map`, the Warp model and data replicated
  map_rows    the same through `sharding.map_rows`, which makes the zero-sized arrays (arguments and constants)
              inside the shard_map instead of passing them in
  jit         jit with the batch's NamedSharding (XLA's partitioner places the FFI calls)
  per_device  one jit program per device: the rows split on the host, placed with `jax.device_put`
  rollout_single  the project's hexapod rollout of random controllers on one device
  rollout     the same under `sharding.spread_over` (`sharding.map_rows`), as the commands run it on N devices

    python benchmarks/warp_devices.py --devices 2                          # GPUs
    python benchmarks/warp_devices.py --cpu-devices 2 --batch 8 --steps 5  # Warp's CPU kernels, 2 fake devices

Prints one JSON line per variant (exit code, seconds, largest |final qpos - the first variant's of its model|)
and writes them to --out.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

VARIANTS = ("empty", "single", "shard_map", "map_rows", "jit", "per_device", "rollout_single", "rollout")

# A tiny model: three free bodies (sphere, box, capsule) falling on a plane, so the step has contacts.
XML = """
<mujoco>
  <worldbody>
    <geom type="plane" size="5 5 .1"/>
    <body pos="0 0 .3"><freejoint/><geom type="sphere" size=".05"/></body>
    <body pos=".2 0 .3"><freejoint/><geom type="box" size=".05 .05 .05"/></body>
    <body pos="-.2 0 .3"><freejoint/><geom type="capsule" size=".03 .05"/></body>
  </worldbody>
</mujoco>
"""


def _parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--devices", type=int, default=2, help="devices of the multi-device variants")
    p.add_argument("--cpu-devices", type=int, default=0, help="fake this many CPU devices (XLA host platform)")
    p.add_argument("--batch", type=int, default=64, help="bodies' worlds stepped together (a multiple of --devices)")
    p.add_argument("--steps", type=int, default=20, help="mjx.step calls in the scan")
    p.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated, of: " + ", ".join(VARIANTS))
    p.add_argument("--timeout", type=float, default=300.0, help="seconds allowed per variant")
    p.add_argument("--out", type=Path, default=None, help="JSON lines written here too")
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    p.add_argument("--save", default=None, help=argparse.SUPPRESS)
    return p.parse_args(argv)


def _tiny(batch):
    """The tiny model under Warp, a function making its data for some rows, and the batch's start positions
    (the bodies dropped from slightly different heights)."""
    import jax.numpy as jnp
    import mujoco

    from hte_jax.sim.mjx_import import mjx

    model = mujoco.MjModel.from_xml_string(XML)
    heights = jnp.linspace(0.0, 0.05, batch)
    qpos = jnp.broadcast_to(jnp.asarray(model.qpos0, jnp.float32), (batch, model.nq))
    qpos = qpos.at[:, 2].add(heights).at[:, 9].add(heights).at[:, 16].add(heights)
    return mjx.put_model(model, impl="warp"), lambda rows: mjx.make_data(model, impl="warp", naconmax=rows * 8,
                                                                         njmax=64), qpos


def _stepper(steps):
    import jax

    from hte_jax.sim.mjx_import import mjx

    def run(mx, data, qpos):
        batched = jax.vmap(lambda q: data.replace(qpos=q))(qpos)
        stepped, _ = jax.lax.scan(lambda d, _: (jax.vmap(mjx.step, in_axes=(None, 0))(mx, d), None), batched,
                                  None, length=steps)
        return stepped.qpos

    return run


def _worker(args) -> dict:
    import jax
    import numpy as np
    from jax.sharding import NamedSharding, PartitionSpec

    from hte_jax import sharding
    from hte_jax.sim.mjx_import import _start_warp

    variant, n = args.worker, args.devices
    if variant != "empty":
        _start_warp()
    devices = jax.devices()[:n]
    tick = time.perf_counter()
    if variant == "empty":
        mesh = sharding.batch_mesh(n)
        split = jax.shard_map(lambda e, x: x * 2.0 + e.sum(), mesh=mesh, in_specs=(PartitionSpec(), PartitionSpec("batch")),
                              out_specs=PartitionSpec("batch"), check_vma=False)
        out = jax.jit(split)(np.zeros((0, 3), np.float32), np.arange(args.batch, dtype=np.float32))
    elif variant.startswith("rollout"):
        out = _rollout(args, variant, devices)
    else:
        mx, make_data, qpos = _tiny(args.batch)
        data = make_data(args.batch)
        run = _stepper(args.steps)
        if variant == "single":
            out = jax.jit(run)(mx, data, qpos)
        elif variant == "shard_map":
            mesh = sharding.batch_mesh(n)
            split = jax.shard_map(run, mesh=mesh, in_specs=(PartitionSpec(), PartitionSpec(), PartitionSpec("batch")),
                                  out_specs=PartitionSpec("batch"), check_vma=False)
            mx, data = sharding.put_replicated((mx, data), mesh)
            out = jax.jit(split)(mx, data, sharding.put_batch(qpos, mesh))
        elif variant == "map_rows":  # the data's contact buffer sized for one device's rows
            mesh = sharding.batch_mesh(n)
            shared = sharding.put_replicated((mx, make_data(args.batch // n)), mesh)
            with sharding.spread_over(mesh):
                out = jax.jit(lambda s, q: sharding.map_rows(lambda s, q: run(*s, q), s, q))(
                    shared, sharding.put_batch(qpos, mesh))
        elif variant == "jit":
            mesh = sharding.batch_mesh(n)
            mx, data = sharding.put_replicated((mx, data), mesh)
            qpos = jax.device_put(qpos, NamedSharding(mesh, PartitionSpec("batch", None)))
            out = jax.jit(run, out_shardings=NamedSharding(mesh, PartitionSpec("batch", None)))(mx, data, qpos)
        elif variant == "per_device":
            rows = np.array_split(np.asarray(qpos), n)
            compiled = jax.jit(run)
            parts = [compiled(*jax.device_put((mx, make_data(len(r)), r), d)) for r, d in zip(rows, devices)]
            out = np.concatenate([np.asarray(p) for p in parts])
        else:
            raise SystemExit(f"unknown variant {variant!r}")
    out = np.asarray(jax.block_until_ready(out))
    np.save(args.save, out)
    return {"variant": variant, "devices": 1 if variant.endswith("single") else n, "seconds": time.perf_counter() - tick,
            "finite": bool(np.isfinite(out).all())}


def _rollout(args, variant, devices):
    """The project's rollout of random controllers from the standing state (3 s is 300 steps; here --steps)."""
    import jax.numpy as jnp
    import numpy as np

    from hte_jax import sharding
    from hte_jax.sim.robot import RobotConfig, load_robot
    from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state

    robot = load_robot(RobotConfig(impl="warp"))
    init = standing_state(robot)
    params = np.random.default_rng(0).uniform(size=(args.batch, 36)).astype(np.float32)
    spec = RolloutSpec(num_steps=args.steps, record_contacts=False)
    damage = jnp.zeros(6, bool)
    if variant == "rollout_single":
        return rollout(robot, jnp.asarray(params), damage, init, spec).final_state.qpos
    mesh = sharding.batch_mesh(len(devices))
    placed = sharding.put_replicated((robot, jnp.asarray(params), damage, init), mesh)
    with sharding.spread_over(mesh):
        return rollout(*placed, spec).final_state.qpos


def main(argv=None):
    args = _parse(argv)
    if args.cpu_devices:
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={args.cpu_devices}"
        os.environ["JAX_PLATFORMS"] = "cpu"
    if args.worker is not None:
        print(json.dumps(_worker(args)), flush=True)
        return
    import mujoco
    import numpy as np

    versions = {"mujoco": mujoco.__version__}
    for name in ("jax", "jaxlib", "warp"):
        try:
            versions[name] = __import__(name).__version__
        except ImportError:
            versions[name] = None
    print(json.dumps({"versions": versions, "settings": {k: str(v) for k, v in vars(args).items()}}), flush=True)
    rows, reference = [], {}
    env = dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false", PYTHONFAULTHANDLER="1")
    with tempfile.TemporaryDirectory() as tmp:
        for variant in [v.strip() for v in args.variants.split(",") if v.strip()]:
            save = Path(tmp) / f"{variant}.npy"
            cmd = [sys.executable, __file__, "--worker", variant, "--devices", str(args.devices), "--batch",
                   str(args.batch), "--steps", str(args.steps), "--save", str(save)]
            tick = time.perf_counter()
            try:
                proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout, env=env)
                row = {"variant": variant, "exit": proc.returncode}
                lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
                if proc.returncode == 0 and lines:
                    row |= json.loads(lines[-1])
                else:
                    row["stderr_tail"] = proc.stderr.strip().splitlines()[-25:]
            except subprocess.TimeoutExpired:
                row = {"variant": variant, "exit": None, "error": f"timeout after {args.timeout:.0f} s"}
            row["wall_s"] = round(time.perf_counter() - tick, 1)
            if save.exists():  # compared with the first variant of its model that finished
                qpos = np.load(save)
                kind = "rollout" if variant.startswith("rollout") else "empty" if variant == "empty" else "tiny"
                if kind in reference:
                    row["against"], first = reference[kind]
                    row["max_abs_diff"] = float(np.abs(qpos - first).max())
                else:
                    reference[kind] = (variant, qpos)
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("".join(json.dumps(r) + "\n" for r in rows))


if __name__ == "__main__":
    main()
