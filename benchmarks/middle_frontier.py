"""Speed-versus-turn frontier: what the HBR's middle layer stores against what its representation
and the flat controller can do (issue 4 study; see docs/design.md).

For each |yaw| bin of 1 s motions: the fastest motion in the HBR's middle layer, and the fastest
found by a dedicated search (`hte_jax.hbr.frontier`: MAP-Elites on a 1-D |yaw| grid, fitness =
speed) in (a) the HBR's middle representation (18 bottom-descriptor targets -> that HBR's leg
primitives) and (b) the flat 36-parameter controller. Same search, budget and evaluation for both.

    python benchmarks/middle_frontier.py                                    # CPU, small
    python benchmarks/middle_frontier.py --batch 8192 --generations 120 --block 20   # GPU
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np
from common import environment, result_path

from hte_jax.hbr import load_hbr
from hte_jax.hbr.analysis import speed_by_turn
from hte_jax.hbr.frontier import frontier_search
from hte_jax.hbr.middle import GENES, MiddleTask, decode, leg_controllers
from hte_jax.qd.loop import run
from hte_jax.sim import load_robot, standing_state
from hte_jax.sim.controller import NUM_PARAMS


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hbr", default=None, help="HBR file (default: the shipped one)")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--generations", type=int, default=20)
    parser.add_argument("--block", type=int, default=5)
    parser.add_argument("--samples", type=int, default=5, help="chained 1 s samples per evaluation")
    parser.add_argument("--bins", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="JSON path (default benchmarks/results/...)")
    args = parser.parse_args(argv)
    env = environment()
    robot = load_robot()
    start = standing_state(robot)
    hbr, _, _ = load_hbr(args.hbr)
    task = MiddleTask(samples=args.samples)
    representations = {  # name -> (genes, mutation rate of the layer that searches it, genotype -> controller)
        "hbr_middle": (GENES, 0.11, lambda g: leg_controllers(hbr.bottom, decode(g))),
        "flat": (NUM_PARAMS, 0.14, lambda g: g),
    }
    stored = speed_by_turn(hbr, args.bins)
    result = {"environment": env, "settings": vars(args), "stored_middle": stored, "searches": {}}
    for name, (genes, rate, to_controllers) in representations.items():
        algo = frontier_search(robot, start, task, to_controllers, genes, batch_size=args.batch, mutation_rate=rate,
                               bins=args.bins)
        began = time.perf_counter()
        state = algo.init(jax.random.PRNGKey(args.seed))
        curve = []
        for done in range(0, args.generations, args.block):
            state = run(algo, state, min(done + args.block, args.generations), block_size=args.block, progress=False)
            best = np.where(np.asarray(state.repertoire.filled), np.asarray(state.repertoire.fitnesses), np.nan)
            curve.append({"generation": int(state.generation), "best_speed": [None if np.isnan(b) else float(b) for b in best]})
        result["searches"][name] = {"genes": genes, "mutation_rate": rate, "wall_s": time.perf_counter() - began,
                                    "evaluations": algo.evaluations(state), "best_speed": curve[-1]["best_speed"],
                                    "curve": curve}

    def cell(value):
        return f"{value:9.3f}" if value is not None and np.isfinite(value) else f"{'-':>9}"

    print(f"\nfastest 1 s motion (m/s) per |yaw| bin, {args.samples} chained samples, on {env['device']}")
    print(f"{'|yaw| rad/s':>13}{'stored':>9}{'HBR repr':>9}{'flat':>9}")
    for i, row in enumerate(stored):
        low, high = row["turn"]
        print(f"{low:6.2f}-{high:<6.2f}{cell(row['speed_max'])}{cell(result['searches']['hbr_middle']['best_speed'][i])}"
              f"{cell(result['searches']['flat']['best_speed'][i])}")
    path = args.out or result_path("middle_frontier", env)
    with open(path, "w") as handle:
        json.dump(result, handle, indent=2)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
