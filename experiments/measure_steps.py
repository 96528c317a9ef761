"""Measure every middle elite's 1 s step from several start states and store it in an HBR file.

    python -m experiments.measure_steps --hbr runs/hbr-gpu/hbr.npz          # in place (GPU: about a minute)
    python -m experiments.measure_steps --hbr old.npz --out new.npz --starts 8

The step model (`hbr.composition.measure_steps`) predicts each elite's step in planned composition;
`train_hbr` measures it (`step_starts`), so this command is for HBR files trained before it existed.
Start 0 is the neutral pose, the others a random elite.
"""

from __future__ import annotations

import argparse
import sys
import time

import jax

from experiments.cli import add_device_flags, device_mesh, input_errors, interruptible, is_writer, show_progress
from hte_jax.errors import ConfigError
from hte_jax.flat.comparison import resolve
from hte_jax.hbr.composition import measure_steps
from hte_jax.hbr.store import load_hbr, save_hbr, shipped_hbr_path
from hte_jax.sim.mjx_import import require_impl
from hte_jax.sim.robot import RobotConfig, load_robot, stored_solver
from hte_jax.sim.rollout import standing_state

CHROME = {"kind", "kind_version", "capacity", "middle_task", "top_task"}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hbr", default=None, help="HBR file or run folder (default: the shipped one)")
    p.add_argument("--out", default=None, help="where to write the HBR with its step model (default: in place)")
    p.add_argument("--starts", type=int, default=8, help="start states per elite (default 8)")
    p.add_argument("--seed", type=int, default=0, help="PRNG seed of the drawn start states")
    p.add_argument("--chunk", type=int, default=8192, help="rollouts per jitted call")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_device_flags(p)
    return p


@interruptible()  # Ctrl-C: `interrupted: nothing written` (the HBR file is replaced at the end)
def main(argv=None) -> int:
    args = parser().parse_args(argv)
    with input_errors() as errors:
        for name, low in (("starts", 1), ("chunk", 1), ("seed", 0)):
            if getattr(args, name) < low:
                raise ConfigError(f"--{name} must be >= {low}, got {getattr(args, name)}")
        mesh = device_mesh(args)  # first: --distributed must start before jax touches the devices
        path = shipped_hbr_path() if args.hbr is None else resolve(args.hbr)
        hbr, top_task, meta = load_hbr(path)
        solver = stored_solver(meta.get("training", {}).get("config", {}))
        require_impl(solver["impl"])  # the HBR's backend, here
        robot = load_robot(RobotConfig(**solver))
    if errors.failed:
        return 2
    began = time.perf_counter()
    model = measure_steps(robot, hbr.middle_params, hbr.middle.filled, hbr.middle_task, standing_state(robot),
                          jax.random.PRNGKey(args.seed), starts=args.starts, chunk=args.chunk, mesh=mesh,
                          progress=show_progress(args))
    model = jax.device_get(model)
    if not is_writer():
        return 0
    seconds = time.perf_counter() - began
    extra = {k: v for k, v in meta.items() if k not in CHROME}
    extra["step_model"] = {"starts": args.starts, "seed": args.seed, "device": jax.devices()[0].device_kind,
                           "wall_time_s": seconds}
    out = path if args.out is None else args.out
    save_hbr(out, hbr.replace(step_model=model), top_task, extra)
    print(f"measured {int(hbr.middle.filled.sum())} middle elites from {args.starts} start states in {seconds:.0f} s; "
          f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
