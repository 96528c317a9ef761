"""Train flat baseline repertoires: 2-D, 8-D, or APROL's 21 damaged 2-D repertoires in one batched run.

    python -m experiments.train_flat --variant 2d                 # cpu preset: 272 s on a 2-core CPU
    python -m experiments.train_flat --variant 8d --preset gpu    # the HBR top layer's budget
    python -m experiments.train_flat --variant aprol --preset gpu # 21 damages, one jitted call per block
    python -m experiments.train_flat --variant 2d --out runs/f --resume   # continue a killed run
    python -m experiments.train_flat --variant 2d --generations 50 --seed 3   # override any value
    python -m experiments.train_flat --variant 2d --solver-iterations 4 --ls-iterations 8   # the solver
    python -m experiments.train_flat --variant 2d --set solver.solver_iterations=4   # any setting, dotted

Writes config.json, checkpoint.npz, metrics.csv, repertoires.npz, summary.json and plots/ under
--out (default runs/flat-<variant>-<preset>); `--show-config` prints the resolved configuration. A
resumed run keeps its solver settings (4 / 8 if it predates them); another value given is an error.
Bad values give a one-line error and exit status 2. Times: benchmarks/cpu_commands.py.
"""

from __future__ import annotations

import argparse
import sys

from experiments.cli import add_training_flags, train_command
from hte_jax.config import settings
from hte_jax.flat.training import PRESETS, VARIANTS, FlatConfig, preset, train_flat, with_overrides

SETTINGS = [key for key in settings(FlatConfig) if key != "variant"]
CHECKPOINTS = {"checkpoint.npz": ""}  # the run's one checkpoint, of every repertoire


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--variant", default="2d", help=f"one of {', '.join(VARIANTS)} (default 2d)")
    add_training_flags(p, PRESETS, "run folder (default runs/flat-<variant>-<preset>)", "no progress bar",
                       dict.fromkeys(SETTINGS, "V"))
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    out = args.out or f"runs/flat-{args.variant}-{args.preset}"

    def report(outcome) -> None:
        statistics = outcome.summary["statistics"].values()
        sizes, fitness = [s["size"] for s in statistics], [s["mean_fitness"] for s in statistics]
        print(f"{out}: {len(sizes)} repertoire(s), {sum(sizes)} elites (mean {sum(sizes) / len(sizes):.0f}), "
              f"x-y cells {[s['effective_size'] for s in statistics][:7]}, "
              f"projected mean fitness {sum(fitness) / len(fitness):.3f}, {outcome.summary['evaluations']} evaluations")

    return train_command("experiments.train_flat", args, argv, out, CHECKPOINTS, SETTINGS,
                         lambda: preset(args.preset, args.variant), with_overrides, train_flat, report)


if __name__ == "__main__":
    sys.exit(main())
