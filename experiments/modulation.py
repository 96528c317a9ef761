"""Secondary-descriptor modulation (paper Fig. 4 and 5): re-execute top-layer skills with each of
the 64 contact patterns (or HTE's 36 candidates) held for their 3 steps, each step planned among the
pattern's elites to the skill's end (`hte_jax.hbr.composition`; `--composition waypoints`: the
paper's nearest elite to each waypoint).

    python -m experiments.modulation                   # cpu preset: 48 skills spread over the map, 174 s on 2 cores
    python -m experiments.modulation --preset gpu      # every skill of the shipped HBR (the paper's figures)
    python -m experiments.modulation --skills all      # every skill, on any machine
    python -m experiments.modulation --hbr runs/hbr-gpu --skills 200 --seed 1   # another sample
    python -m experiments.modulation --data runs/modulation/modulation.npz --radius 0.1 --out runs/mod-r01

Presets: cpu (default) re-executes 48 skills spread over the map of final positions (ordered along a
Z-order curve, every (skills / 48)-th from a start drawn with --seed: `hbr.modulation.spread_skills`),
so the figures keep their shape and each skill is equally likely to count in the summary's means;
gpu every skill (2813 x 64 on the shipped HBR). --skills N|all overrides the preset's count.

Writes under --out (default runs/modulation): modulation_map.png (Fig. 4), modulation_grid.png
(Fig. 5), modulation.json (summary, the skills' sample and per-skill counts) and modulation.npz
(every execution). Bad values give a one-line error and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

from experiments.cli import input_errors, interruptible
from hte_jax.errors import ConfigError
from hte_jax.flat.comparison import resolve
from hte_jax.hbr.composition import COMPOSITIONS, planning_table
from hte_jax.hbr.modulation import Modulation, modulate, spread_skills
from hte_jax.hbr.plots import plot_modulation_grid, plot_modulation_map
from hte_jax.hbr.store import load_hbr
from hte_jax.online.secondary import allowed_patterns
from hte_jax.qd.io import write_json
from hte_jax.sim.robot import load_robot
from hte_jax.sim.rollout import standing_state

# skills: how many to sample spread over the map (None: every skill); chunk: executions per jitted call
PRESETS = {"cpu": {"skills": 48, "chunk": 512}, "gpu": {"skills": None, "chunk": 4096}}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="cpu", choices=PRESETS,
                   help="cpu: 48 skills spread over the map (default); gpu: every skill")
    p.add_argument("--hbr", default=None, help="HBR file or run folder (default: the shipped one)")
    p.add_argument("--out", default="runs/modulation", help="output folder")
    p.add_argument("--skills", default=None, metavar="N|all",
                   help="N skills spread over the map (drawn with --seed), or all (default: the preset's)")
    p.add_argument("--seed", type=int, default=0, help="seed of the skills' sample (default 0)")
    p.add_argument("--radius", type=float, default=None,
                   help="Fig. 4 counts executions ending within this many metres of the skill's final position "
                        "(default: in the skill's own grid cell)")
    p.add_argument("--chunk", type=int, default=None, help="executions per jitted call (default: the preset's)")
    p.add_argument("--data", default=None, help="re-plot a modulation.npz written earlier (no simulation)")
    p.add_argument("--composition", default="planned", choices=COMPOSITIONS,
                   help="how a pattern's steps are chosen: planned to the skill's end (default) or the paper's waypoints")
    p.add_argument("--patterns", default="all", choices=("all", "candidates"),
                   help="all 64 contact patterns (paper Fig. 4, 5) or HTE's 36 candidates")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def skill_count(text: str | None, preset: str) -> int | None:
    """The number of skills --skills asks for (None: every skill); ConfigError if malformed."""
    if text is None:
        return PRESETS[preset]["skills"]
    if text == "all":
        return None
    try:
        count = int(text)
    except ValueError:
        raise ConfigError(f"--skills must be a positive integer or all, got {text!r}") from None
    if count < 1:
        raise ConfigError(f"--skills must be >= 1, got {count}")
    return count


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    with interruptible() as interrupt:
        chunk = PRESETS[args.preset]["chunk"] if args.chunk is None else args.chunk
        with input_errors(OSError, ValueError) as errors:  # ConfigError and CheckpointError too; a bad --data file
            if args.radius is not None and not args.radius > 0:
                raise ConfigError(f"--radius must be > 0, got {args.radius}")
            if chunk < 1:
                raise ConfigError(f"--chunk must be >= 1, got {chunk}")
            count = skill_count(args.skills, args.preset)
            hbr, task, _ = load_hbr(None if args.hbr is None else resolve(args.hbr))
            mod = None if args.data is None else Modulation.load(args.data)
        if errors.failed:
            return 2
        progress = not args.no_progress
        sample = None
        if mod is None:
            filled = int(np.asarray(hbr.top.filled).sum())
            skills = None
            if count is not None and count < filled:
                skills = spread_skills(hbr.top.filled, hbr.top.descriptors, count, args.seed)
                sample = {"skills": int(skills.size), "of": filled, "seed": args.seed}
            with tqdm(total=2, desc="standing state, planning table", disable=not progress, leave=False) as bar:
                robot = load_robot()
                start = jax.block_until_ready(standing_state(robot))
                bar.update()
                table = planning_table(hbr) if args.composition == "planned" else None
                bar.update()
            patterns = allowed_patterns() if args.patterns == "candidates" else None
            mod = modulate(robot, hbr, task, start, skills=skills, patterns=patterns, chunk=chunk, progress=progress,
                           table=table)
        out = Path(args.out)
        interrupt.saved = f"part of the figures and data written in {out}"
        out.mkdir(parents=True, exist_ok=True)
        with tqdm(total=2, desc="figures", unit="figure", disable=not progress, leave=False) as bar:
            plot_modulation_map(mod, out / "modulation_map.png", task.extent, args.radius)
            bar.update()
            plot_modulation_grid(mod, out / "modulation_grid.png", task.extent)
            bar.update()
        counts, summary = mod.counts(args.radius), mod.summary()
        write_json(out / "modulation.json", {
            "summary": summary, "composition": None if args.data is not None else args.composition, "sample": sample,
            "step_model": hbr.step_model is not None, "radius_m": args.radius,
            "per_skill": {"slot": mod.slots.tolist(), **{k: np.asarray(v).tolist() for k, v in counts.items()}}})
        if args.data is None:
            mod.save(out / "modulation.npz")
        print(json.dumps({k: v for k, v in summary.items() if k != "skills_showing_each_pattern"}, indent=2))
        if sample is not None:
            print(f"{sample['skills']} of {sample['of']} skills, spread over the map (seed {sample['seed']}); "
                  "--skills all (or --preset gpu) re-executes every skill")
        print(f"wrote figures and data under {out}")
        return 0


if __name__ == "__main__":
    sys.exit(main())
