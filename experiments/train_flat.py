"""Train flat baseline repertoires: 2-D, 8-D, or APROL's 21 damaged 2-D repertoires in one batched run.

    python -m experiments.train_flat --variant 2d                 # cpu preset: 272 s on a 2-core CPU
    python -m experiments.train_flat --variant 8d --preset gpu    # the HBR top layer's budget
    python -m experiments.train_flat --variant aprol --preset gpu # 21 damages, one jitted call per block
    python -m experiments.train_flat --variant 2d --out runs/f --resume   # continue a killed run
    python -m experiments.train_flat --variant 2d --generations 50 --seed 3   # override any value
    python -m experiments.train_flat --variant 2d --solver-iterations 4 --ls-iterations 8   # the solver
    python -m experiments.train_flat --variant 2d --set solver.solver_iterations=4   # any setting, dotted

Writes config.json, checkpoint.npz, metrics.csv, repertoires.npz, summary.json and plots/ under
--out (default runs/flat-<variant>-<preset>). `--show-config` prints the resolved configuration.
Bad values give a one-line error and exit status 2. A resumed run keeps the solver settings it was
started with (4 / 8 for runs started before they were settings) unless they are given; a
different value is then an error. Times: benchmarks/cpu_commands.py (2026-11-26).
"""

from __future__ import annotations

import argparse
import json
import sys

from experiments.cli import (add_set_flag, checkpoint_saved, input_errors, interruptible, resumable_run,
                             resume_command, set_overrides)
from experiments.devices import add_device_flags, device_mesh, is_writer
from hte_jax.config import settings
from hte_jax.flat.training import PRESETS, VARIANTS, FlatConfig, preset, train_flat, with_overrides
from hte_jax.sim.robot import stored_solver

SETTINGS = [key for key in settings(FlatConfig) if key != "variant"]
CHECKPOINTS = {"checkpoint.npz": ""}  # the run's one checkpoint, of every repertoire


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--variant", default="2d", help=f"one of {', '.join(VARIANTS)} (default 2d)")
    p.add_argument("--preset", default="cpu", help=f"one of {', '.join(PRESETS)} (default cpu)")
    p.add_argument("--out", default=None, help="run folder (default runs/flat-<variant>-<preset>)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--show-config", action="store_true", help="print the resolved configuration and exit")
    add_device_flags(p)
    for key in SETTINGS:
        p.add_argument("--" + key.replace("_", "-"), dest=key, default=None, metavar="V", help=f"override {key}")
    add_set_flag(p)
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    out = args.out or f"runs/flat-{args.variant}-{args.preset}"
    with interruptible(lambda: checkpoint_saved(out, CHECKPOINTS), resume_command("experiments.train_flat", argv, out)):
        return _main(args, out)


def _main(args, out: str) -> int:
    with input_errors() as errors:
        mesh = device_mesh(args)  # first: --distributed must start before jax touches the devices
        config = preset(args.preset, args.variant)
        overrides = {k: getattr(args, k) for k in SETTINGS if getattr(args, k) is not None}
        overrides.update(set_overrides(args.set))
        stored = resumable_run(out, CHECKPOINTS) if args.resume else None
        if stored is not None:
            overrides = {**stored_solver(stored), **overrides}
        config = with_overrides(config, overrides)
        if args.show_config:
            print(json.dumps(config.to_dict(), indent=2))
            return 0
        outcome = train_flat(config, out, resume_run=args.resume, progress=not args.no_progress, mesh=mesh)
    if errors.failed:
        return 2
    if not is_writer():
        return 0
    summary = outcome.summary
    sizes = [s["size"] for s in summary["statistics"].values()]
    fitness = [s["mean_fitness"] for s in summary["statistics"].values()]
    print(
        f"{out}: {len(sizes)} repertoire(s), {sum(sizes)} elites (mean {sum(sizes) / len(sizes):.0f}), "
        f"x-y cells {[s['effective_size'] for s in summary['statistics'].values()][:7]}, "
        f"projected mean fitness {sum(fitness) / len(fitness):.3f}, {summary['evaluations']} evaluations"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
