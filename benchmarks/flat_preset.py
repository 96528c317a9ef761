"""Wall time of a flat-repertoire training preset (one run per call: presets are minutes long).

Runs `train_flat` for --variant / --preset / --seed into --out and records the wall time
(including compilation), evaluations, evaluations per second and the repertoires' Table 2
statistics.

    python benchmarks/flat_preset.py --variant 2d --preset cpu --out runs/bench-flat2d-cpu
    python benchmarks/flat_preset.py --variant aprol --preset gpu --out runs/bench-aprol-gpu
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

from common import environment, result_path

from hte_jax.flat.training import preset, train_flat


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variant", default="2d")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="run folder (must not hold a run)")
    parser.add_argument("--json", default=None, help="JSON path (default benchmarks/results/...)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    env = environment()
    config = dataclasses.replace(preset(args.preset, args.variant), seed=args.seed)
    began = time.perf_counter()
    outcome = train_flat(config, args.out, progress=not args.no_progress)
    total = time.perf_counter() - began
    summary = outcome.summary
    stats = summary["statistics"]
    sizes = [s["size"] for s in stats.values()]
    cells = [s["effective_size"] for s in stats.values()]
    fitness = [s["mean_fitness"] for s in stats.values()]
    print(f"\nflat {args.variant}, preset {args.preset}, seed {args.seed} on {env['device']}: {total:.1f} s, "
          f"{summary['evaluations']} evaluations ({summary['evaluations'] / total:.1f} eval/s incl. compilation)")
    print(f"{len(sizes)} repertoire(s): elites {min(sizes)}..{max(sizes)}, x-y cells {min(cells)}..{max(cells)}, "
          f"projected mean fitness {min(fitness):.3f}..{max(fitness):.3f}")
    path = args.json or result_path(f"flat_preset_{args.variant}_{args.preset}_seed{args.seed}", env)
    with open(path, "w") as handle:
        json.dump({"environment": env, "variant": args.variant, "preset": args.preset, "seed": args.seed,
                   "total_wall_s": total, "evaluations": summary["evaluations"],
                   "evaluations_per_s": summary["evaluations"] / total, "statistics": stats}, handle, indent=2)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
