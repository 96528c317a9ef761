"""Online adaptation speed: planning latency per action and whole-episode wall time, per batch size.

For each batch size E, E episodes (the paper's 7 damages cycled from leg1, so E = 1 is a leg-1
episode) of --variant run on the
shipped repertoires with the --preset planner. One action of a warm-up run compiles; then
--repeats timed runs follow. Reported per batch size: compile seconds, planning latency per
action (median and 95th percentile over every action of the timed runs; one action = one
planning call for all E episodes), execution seconds per action (median), and the wall time
of a whole run (median; a run ends when every episode has ended or after --max-actions).

    python benchmarks/adaptation.py --batch-sizes 1,210 --preset cpu --max-actions 3
    python benchmarks/adaptation.py --batch-sizes 1,210 --preset gpu
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np
from common import environment, result_path

from hte_jax.flat.store import shipped_flat_path
from hte_jax.online.arena import maze_robot, start_states
from hte_jax.online.episode import run_episodes, start_episodes
from hte_jax.online.evaluation import load_skills, preset, with_overrides
from hte_jax.online.variants import batch_rules
from hte_jax.online.variants import variant as variant_named
from hte_jax.online.maze import PAPER_MAZE
from hte_jax.sim.damage import paper_damage_masks


def measure(config, skills, variant: str, batch: int, repeats: int, seed: int) -> dict:
    damages = paper_damage_masks()[(np.arange(batch) + 1) % 7]
    variant_named(variant).check_skills(skills)
    rules, which = batch_rules([variant] * batch)
    adaptation = config.adaptation
    robot = maze_robot(PAPER_MAZE)
    start = start_states(PAPER_MAZE, damages)
    warm = start_episodes(adaptation, skills, start, damages, rules, np.asarray(which), jax.random.PRNGKey(seed))
    _, first = run_episodes(PAPER_MAZE, adaptation, robot, skills, warm, progress=False, max_steps=1)
    timed = []
    for r in range(repeats):
        episodes = start_episodes(adaptation, skills, start, damages, rules, np.asarray(which),
                                  jax.random.PRNGKey(seed + 1 + r))
        began = time.perf_counter()
        episodes, timings = run_episodes(PAPER_MAZE, adaptation, robot, skills, episodes, progress=False)
        timed.append({"wall_s": time.perf_counter() - began, "plan_s": timings.plan, "act_s": timings.act,
                      "actions": len(timings.plan), "reached": int(np.asarray(episodes.reached).sum())})
    plan = np.concatenate([r["plan_s"] for r in timed])
    act = np.concatenate([r["act_s"] for r in timed])
    return {
        "episodes": batch,
        "compile_s": first.plan[0] + first.act[0] - float(np.median(plan)) - float(np.median(act)),
        "plan_median_s": float(np.median(plan)),
        "plan_p95_s": float(np.percentile(plan, 95)),
        "act_median_s": float(np.median(act)),
        "run_wall_median_s": float(np.median([r["wall_s"] for r in timed])),
        "actions_per_run": [r["actions"] for r in timed],
        "reached_per_run": [r["reached"] for r in timed],
        "runs": timed,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch-sizes", default="1,210", help="comma-separated episode counts")
    parser.add_argument("--variant", default="hte")
    parser.add_argument("--preset", default="cpu", help="planner settings of experiments.maze_eval's preset")
    parser.add_argument("--max-actions", type=int, default=None, help="override the 80-action cap")
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--roots", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=2, help="timed runs per batch size (after one compiling run)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="JSON path (default benchmarks/results/...)")
    args = parser.parse_args(argv)
    overrides = {k: v for k, v in {"max_actions": args.max_actions, "iterations": args.iterations,
                                   "roots": args.roots, "variants": args.variant}.items() if v is not None}
    config = with_overrides(preset(args.preset), overrides)
    kind = variant_named(args.variant).repertoire
    path = shipped_flat_path(kind) if kind != "hbr" else None
    skills, info = load_skills(path, maps=kind == "aprol", composition=config.composition,
                               spare=variant_named(args.variant).spares)
    env = environment()
    rows = [measure(config, skills, args.variant, int(b), args.repeats, args.seed) for b in args.batch_sizes.split(",")]
    print(f"\n{args.variant} on {env['device']}, planner {config.planner.iterations} iterations x {config.planner.roots} trees, "
          f"{info['actions']} actions, cap {config.max_actions} actions")
    print(f"{'episodes':>8} {'compile s':>9} {'plan med s':>10} {'plan p95 s':>10} {'act med s':>9} {'run wall s':>10} {'actions':>8}")
    for row in rows:
        print(f"{row['episodes']:>8} {row['compile_s']:>9.1f} {row['plan_median_s']:>10.3f} {row['plan_p95_s']:>10.3f} "
              f"{row['act_median_s']:>9.3f} {row['run_wall_median_s']:>10.1f} {int(np.median(row['actions_per_run'])):>8}")
    out = args.out or result_path(f"adaptation_{args.variant}_{args.preset}", env)
    with open(out, "w") as handle:
        json.dump({"environment": env, "variant": args.variant, "preset": args.preset, "settings": config.to_dict(),
                   "repertoire": info, "rows": rows}, handle, indent=2)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
