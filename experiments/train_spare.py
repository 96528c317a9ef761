"""Train the spare archive of an HBR: a second middle layer, on the HBR's own bottom layer, whose
contact threshold is strict (5 %), so that its steps keep their lifted legs really off the floor.

    python -m experiments.train_spare                                   # the shipped HBR, cpu preset
    python -m experiments.train_spare --hbr runs/hbr-gpu --preset gpu --out runs/spare-gpu
    python -m experiments.train_spare --out runs/spare --resume          # continue a killed run
    python -m experiments.train_spare --hbr runs/hbr-gpu --preset gpu --impl warp   # MJX's Warp backend
    cp runs/spare-gpu/spare.npz runs/hbr-gpu/                            # used by default beside hbr.npz

The spare variants (`hte-spare`, `perfect-spare`) plan a chosen pattern's steps among the elites, of
the HBR and of this archive, with under 5 % contact on each leg the pattern lifts. Writes config.json,
middle/ (checkpoint, metrics.csv), spare.npz and summary.json under --out. Bad values give a one-line
error and exit status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from experiments.cli import (add_setting_flags, checkpoint_saved, input_errors, interruptible, resumable_run,
                             resume_command, set_overrides)
from hte_jax.errors import ConfigError
from hte_jax.flat.comparison import resolve
from hte_jax.hbr.spare import SPARE_L, STRICT_CONTACT
from hte_jax.hbr.store import load_hbr, shipped_hbr_path
from hte_jax.hbr.training import PRESETS, preset, train_spare, with_overrides
from hte_jax.sim.robot import SolverConfig, stored_solver

CHECKPOINTS = {"middle/checkpoint.npz": "the spare archive"}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hbr", default=None, help="HBR file or run folder (default: the shipped one)")
    p.add_argument("--preset", default="cpu", choices=sorted(PRESETS), help="middle-layer budget (default cpu)")
    p.add_argument("--out", default="runs/spare", help="run folder (default runs/spare)")
    p.add_argument("--threshold", type=float, default=STRICT_CONTACT, help="contact threshold (default 0.05)")
    p.add_argument("--l", type=float, default=SPARE_L, help="archive distance threshold (default 0.035)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--impl", default=None,
                   help="MJX implementation, jax or warp (default: the HBR's; on --resume, the run's)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--no-progress", action="store_true")
    add_setting_flags(p, {})  # --set
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    with interruptible(lambda: checkpoint_saved(args.out, CHECKPOINTS),
                       resume_command("experiments.train_spare", argv, args.out)):
        with input_errors() as errors:
            if not 0.0 < args.threshold < 1.0:
                raise ConfigError(f"--threshold must be in (0, 1), got {args.threshold}")
            if args.l <= 0.0:
                raise ConfigError(f"--l must be > 0, got {args.l}")
            stored = resumable_run(args.out, CHECKPOINTS) if args.resume else None
            path = shipped_hbr_path() if args.hbr is None else resolve(args.hbr)
            hbr, _, meta = load_hbr(path)
            solver = stored_solver(meta.get("training", {}).get("config", {}))
            if args.impl is not None:
                solver["impl"] = args.impl
            elif stored is not None:
                solver["impl"] = stored_solver(stored.get("hbr_config", {}))["impl"]
            base = dataclasses.replace(preset(args.preset), seed=args.seed, solver=SolverConfig(**solver))
            base = with_overrides(base, set_overrides(args.set))  # the preset's other settings (middle.*, step_chunk)
            summary = train_spare(hbr, base, args.out, threshold=args.threshold, l=args.l, resume_run=args.resume,
                                  progress=not args.no_progress)
        if errors.failed:
            return 2
        lifting = summary["lifting_each_leg"]
        print(f"spare archive: {summary['elites']} elites over {summary['patterns']} patterns; elites lifting each "
              f"leg: {lifting['spare']} (the HBR's own: {lifting['hbr']}); wrote {args.out}/spare.npz")
        return 0


if __name__ == "__main__":
    sys.exit(main())
