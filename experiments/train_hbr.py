"""Train a hierarchical behavioural repertoire: bottom, middle and top layers.

    python -m experiments.train_hbr                       # cpu preset: a small HBR, 629 s on a 2-core CPU
    python -m experiments.train_hbr --preset gpu          # the shipped HBR's budget: 477 s on one H200
    python -m experiments.train_hbr --preset tiny         # a first look: every phase at tiny sizes
    python -m experiments.train_hbr --preset paper --out runs/paper   # the paper's budget
    python -m experiments.train_hbr --out runs/hbr --resume          # continue a killed run
    python -m experiments.train_hbr --middle-generations 100 --seed 3   # override any value
    python -m experiments.train_hbr --solver-iterations 4 --ls-iterations 8   # the physics' solver
    python -m experiments.train_hbr --set middle.eta_m=20 --set top.block_size=5   # any setting, dotted

Writes config.json, per-layer checkpoints and metrics CSVs, hbr.npz, summary.json and plots/ under
--out (default runs/hbr-<preset>); `--show-config` prints the resolved configuration. A resumed run
keeps its solver settings (4 / 8 if it predates them); another value given is an error. Bad values
give a one-line error and exit status 2. Times: benchmarks/cpu_commands.py.
"""

from __future__ import annotations

import argparse
import sys

from experiments.cli import add_training_flags, train_command
from hte_jax.config import settings
from hte_jax.hbr.training import LAYERS, PRESETS, HBRConfig, preset, train_hbr, with_overrides

# a flag per setting: "seed", "middle.generations" (--middle-generations), "solver_iterations" ...
SETTINGS = {key: str(field.type).upper() for key, field in settings(HBRConfig).items()}
CHECKPOINTS = {f"{layer}/checkpoint.npz": f"layer {layer}" for layer in LAYERS}  # in training order


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_training_flags(p, PRESETS, "run folder (default runs/hbr-<preset>)", "no progress bars", SETTINGS)
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    out = args.out or f"runs/hbr-{args.preset}"

    def report(outcome) -> None:
        stats = outcome.summary["statistics"]
        print(f"{out}: bottom {stats['bottom']['elites']} primitives, middle {stats['middle']['elites']} motions "
              f"({stats['middle']['contact_patterns']} contact patterns), top {stats['top']['elites']} skills "
              f"(mean fitness {stats['top']['mean_fitness']:.3f})")

    return train_command("experiments.train_hbr", args, argv, out, CHECKPOINTS, SETTINGS,
                         lambda: preset(args.preset), with_overrides, train_hbr, report)


if __name__ == "__main__":
    sys.exit(main())
