"""Measure where every top-layer skill of an HBR ends when executed with each contact pattern.

    python -m experiments.pattern_ends                       # the shipped HBR and its spare archive
    python -m experiments.pattern_ends --hbr runs/hbr-gpu --table planned --max-lifted 2

The intact robot executes each skill from the standing state with each candidate pattern held for
its three steps, planning every step among the pattern's sparing set (`--table sparing`, with the
spare.npz beside the HBR when there is one) or among its elites (`--table planned`), exactly as
the variants that plan with measured ends execute it online (`hte-measured`, `perfect-measured`).
Writes pattern_ends_<table>.npz beside the HBR file (or --out), which `maze_eval` then reads.
Bad values give a one-line error and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from experiments.cli import input_errors, interruptible
from hte_jax.errors import ConfigError
from hte_jax.flat.comparison import resolve
from hte_jax.hbr.composition import planning_table, skill_ends
from hte_jax.hbr.pattern_ends import TABLES, ends_file, measure_pattern_ends, save_pattern_ends
from hte_jax.hbr.sparing import lifted_legs, sparing_table
from hte_jax.hbr.store import load_hbr, load_spare, shipped_hbr_path, spare_beside
from hte_jax.online.variants import CANDIDATE_PATTERNS
from hte_jax.sim.robot import RobotConfig, load_robot
from hte_jax.sim.rollout import standing_state


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hbr", default=None, help="HBR file or run folder (default: the shipped one)")
    p.add_argument("--table", default="sparing", choices=TABLES, help="planning table of the steps (default sparing)")
    p.add_argument("--spare", default=None, help="spare archive for --table sparing (default: spare.npz beside the HBR)")
    p.add_argument("--max-lifted", type=int, default=6,
                   help="measure the candidate patterns lifting at most this many legs (default 6: all 36)")
    p.add_argument("--chunk", type=int, default=4096, help="executions per jitted batch (default 4096)")
    p.add_argument("--out", default=None, help="output file (default: pattern_ends_<table>.npz beside the HBR)")
    p.add_argument("--no-progress", action="store_true")
    return p


@interruptible()  # Ctrl-C: `interrupted: nothing written` (the file is written at the end)
def main(argv=None) -> int:
    args = parser().parse_args(argv)
    with input_errors() as errors:
        if args.max_lifted < 1:
            raise ConfigError(f"--max-lifted must be >= 1, got {args.max_lifted}")
        if args.chunk < 1:
            raise ConfigError(f"--chunk must be >= 1, got {args.chunk}")
        path = shipped_hbr_path() if args.hbr is None else resolve(args.hbr)
        hbr, task, _ = load_hbr(path)
        spare = None
        if args.table == "sparing":
            spare = args.spare or spare_beside(path)
            if spare:
                hbr = load_spare(spare, hbr)
        table = sparing_table(hbr) if args.table == "sparing" else planning_table(hbr)
        patterns = CANDIDATE_PATTERNS[lifted_legs(CANDIDATE_PATTERNS).sum(axis=-1) <= args.max_lifted]
        robot = load_robot(RobotConfig())
        began = time.perf_counter()
        ends = measure_pattern_ends(robot, hbr, task, standing_state(robot), table, args.table, patterns,
                                    chunk=args.chunk, progress=not args.no_progress)
        seconds = time.perf_counter() - began
    if errors.failed:
        return 2
    out = Path(args.out) if args.out else Path(path).parent / ends_file(args.table)
    stored = np.asarray(skill_ends(hbr.top.descriptors[ends.slots], hbr.top.extras["arrival_yaw"][ends.slots],
                                   task.extent))[:, :2]
    gap = np.linalg.norm(ends.ends[..., :2] - stored[None], axis=-1)[ends.valid]
    summary = {"skills": int(ends.slots.size), "patterns": ends.patterns.tolist(), "table": args.table,
               "spare": str(spare) if spare else None, "valid_share": float(ends.valid.mean()),
               "median_distance_to_stored_end_m": float(np.median(gap)) if gap.size else float("nan"),
               "seconds": seconds}
    save_pattern_ends(out, ends, metadata={"summary": summary})
    print(f"{ends.slots.size} skills x {ends.patterns.size} patterns in {seconds:.0f} s: {100 * ends.valid.mean():.1f} % "
          f"valid, measured ends a median {summary['median_distance_to_stored_end_m']:.3f} m from the stored ends; "
          f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
