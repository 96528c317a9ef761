"""Secondary-descriptor modulation (paper Fig. 4 and 5): re-execute every top-layer skill with each
of the 64 contact patterns (or HTE's 36 candidates) held for its 3 steps, each step planned among the
pattern's elites to the skill's end (`hte_jax.hbr.composition`; `--composition waypoints`: the paper's
nearest elite to each waypoint).

    python -m experiments.modulation                         # the shipped HBR, all skills (GPU: seconds)
    python -m experiments.modulation --hbr runs/hbr-gpu --max-skills 50   # a subset (CPU: minutes)
    python -m experiments.modulation --data runs/modulation/modulation.npz --radius 0.1 --out runs/mod-r01

Writes under --out (default runs/modulation): modulation_map.png (Fig. 4), modulation_grid.png
(Fig. 5), modulation.json (summary and per-skill counts) and modulation.npz (every execution).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from experiments.cli import Interruption, fail, input_errors, interruptible
from hte_jax.flat.comparison import resolve
from hte_jax.hbr.composition import COMPOSITIONS, planning_table
from hte_jax.hbr.modulation import Modulation, modulate
from hte_jax.hbr.plots import plot_modulation_grid, plot_modulation_map
from hte_jax.hbr.store import load_hbr
from hte_jax.online.secondary import allowed_patterns
from hte_jax.qd.io import CheckpointError, write_json
from hte_jax.sim.robot import load_robot
from hte_jax.sim.rollout import standing_state


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hbr", default=None, help="HBR file or run folder (default: the shipped one)")
    p.add_argument("--out", default="runs/modulation", help="output folder")
    p.add_argument("--max-skills", type=int, default=None, help="only the first N skills (by cell)")
    p.add_argument("--radius", type=float, default=None,
                   help="Fig. 4 counts executions ending within this many metres of the skill's final position "
                        "(default: in the skill's own grid cell)")
    p.add_argument("--chunk", type=int, default=4096, help="executions per jitted call")
    p.add_argument("--data", default=None, help="re-plot a modulation.npz written earlier (no simulation)")
    p.add_argument("--composition", default="planned", choices=COMPOSITIONS,
                   help="how a pattern's steps are chosen: planned to the skill's end (default) or the paper's waypoints")
    p.add_argument("--patterns", default="all", choices=("all", "candidates"),
                   help="all 64 contact patterns (paper Fig. 4, 5) or HTE's 36 candidates")
    p.add_argument("--no-progress", action="store_true")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    with interruptible() as interrupt:
        return _main(args, interrupt)


def _main(args, interrupt: Interruption) -> int:
    if args.max_skills is not None and args.max_skills < 1:
        return fail(f"--max-skills must be >= 1, got {args.max_skills}")
    if args.radius is not None and not args.radius > 0:
        return fail(f"--radius must be > 0, got {args.radius}")
    if args.chunk < 1:
        return fail(f"--chunk must be >= 1, got {args.chunk}")
    with input_errors(CheckpointError) as errors:
        hbr, task, _ = load_hbr(None if args.hbr is None else resolve(args.hbr))
    if errors.failed:
        return 2
    if args.data is not None:
        with input_errors(OSError, ValueError) as errors:
            mod = Modulation.load(args.data)
        if errors.failed:
            return 2
    else:
        robot = load_robot()
        skills = np.flatnonzero(np.asarray(hbr.top.filled))[: args.max_skills]
        table = planning_table(hbr) if args.composition == "planned" else None
        patterns = allowed_patterns() if args.patterns == "candidates" else None
        mod = modulate(robot, hbr, task, standing_state(robot), skills=skills, patterns=patterns, chunk=args.chunk,
                       progress=not args.no_progress, table=table)
    out = Path(args.out)
    interrupt.saved = f"part of the figures and data written in {out}"
    out.mkdir(parents=True, exist_ok=True)
    plot_modulation_map(mod, out / "modulation_map.png", task.extent, args.radius)
    plot_modulation_grid(mod, out / "modulation_grid.png", task.extent)
    counts = mod.counts(args.radius)
    summary = mod.summary()
    write_json(out / "modulation.json", {
        "summary": summary,
        "composition": None if args.data is not None else args.composition,
        "step_model": hbr.step_model is not None,
        "radius_m": args.radius,
        "per_skill": {"slot": mod.slots.tolist(), **{k: np.asarray(v).tolist() for k, v in counts.items()}},
    })
    if args.data is None:
        mod.save(out / "modulation.npz")
    print(json.dumps({k: v for k, v in summary.items() if k != "skills_showing_each_pattern"}, indent=2))
    print(f"wrote figures and data under {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
