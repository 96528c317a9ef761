"""Train a hierarchical behavioural repertoire: bottom, middle and top layers.

    python -m experiments.train_hbr                       # cpu preset: a small HBR, 629 s on a 2-core CPU
    python -m experiments.train_hbr --preset gpu          # the shipped HBR's budget: 477 s on one H200
    python -m experiments.train_hbr --preset tiny         # a first look: every phase at tiny sizes
    python -m experiments.train_hbr --preset paper --out runs/paper   # the paper's budget
    python -m experiments.train_hbr --out runs/hbr --resume          # continue a killed run
    python -m experiments.train_hbr --middle-generations 100 --seed 3   # override any value
    python -m experiments.train_hbr --solver-iterations 4 --ls-iterations 8   # the physics' solver
    python -m experiments.train_hbr --set middle.parents.selection=density    # any setting, dotted

Writes config.json, per-layer checkpoints and metrics CSVs, hbr.npz, summary.json and plots/
under --out (default runs/hbr-<preset>). Every preset value has a flag; `--show-config` prints
the resolved configuration and exits. Bad values give a one-line error and exit status 2.
Times: benchmarks/cpu_commands.py (2026-11-26).
A resumed run keeps the solver settings it was started with (4 / 8 for runs started before they
were settings) unless they are given; a different value is then an error.
"""

from __future__ import annotations

import argparse
import json
import sys

from experiments.cli import (add_set_flag, checkpoint_saved, input_errors, interruptible, resumable_run,
                             resume_command, set_overrides)
from experiments.devices import add_device_flags, device_mesh, is_writer
from hte_jax.config import settings
from hte_jax.hbr.training import LAYERS, PRESETS, HBRConfig, preset, train_hbr, with_overrides
from hte_jax.sim.robot import stored_solver


CHECKPOINTS = {f"{layer}/checkpoint.npz": f"layer {layer}" for layer in LAYERS}  # in training order


def _flag(key: str) -> str:
    return "--" + key.replace(".", "-").replace("_", "-")


def _settings() -> list[tuple[str, type]]:
    """(override key, type) of every setting: "seed", "middle.generations", "solver_iterations" ..."""
    return [(key, field.type) for key, field in settings(HBRConfig).items()]


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="cpu", help=f"one of {', '.join(PRESETS)} (default cpu)")
    p.add_argument("--out", default=None, help="run folder (default runs/hbr-<preset>)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--show-config", action="store_true", help="print the resolved configuration and exit")
    add_device_flags(p)
    for key, kind in _settings():
        p.add_argument(_flag(key), dest=key, default=None, metavar=str(kind).upper(), help=f"override {key}")
    add_set_flag(p)
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    out = args.out or f"runs/hbr-{args.preset}"
    with interruptible(lambda: checkpoint_saved(out, CHECKPOINTS), resume_command("experiments.train_hbr", argv, out)):
        return _main(args, out)


def _main(args, out: str) -> int:
    with input_errors() as errors:
        mesh = device_mesh(args)  # first: --distributed must start before jax touches the devices
        config: HBRConfig = preset(args.preset)
        overrides = {key: getattr(args, key) for key, _ in _settings() if getattr(args, key) is not None}
        overrides.update(set_overrides(args.set))
        stored = resumable_run(out, CHECKPOINTS) if args.resume else None
        if stored is not None:
            overrides = {**stored_solver(stored), **overrides}
        config = with_overrides(config, overrides)
        if args.show_config:
            print(json.dumps(config.to_dict(), indent=2))
            return 0
        outcome = train_hbr(config, out, resume_run=args.resume, progress=not args.no_progress, mesh=mesh)
    if errors.failed:
        return 2
    if not is_writer():
        return 0
    stats = outcome.summary["statistics"]
    print(
        f"{out}: bottom {stats['bottom']['elites']} primitives, middle {stats['middle']['elites']} motions "
        f"({stats['middle']['contact_patterns']} contact patterns), top {stats['top']['elites']} skills "
        f"(mean fitness {stats['top']['mean_fitness']:.3f})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
