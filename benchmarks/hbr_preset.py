"""Wall time of a whole HBR training preset (one run: each preset is minutes to hours long).

Runs `train_hbr` for --preset into --out and records the wall time of every layer (including
compilation), the total, the evaluations and the resulting repertoire's statistics.

    python benchmarks/hbr_preset.py --preset cpu --out runs/bench-cpu
    python benchmarks/hbr_preset.py --preset gpu --out runs/bench-gpu
"""

from __future__ import annotations

import argparse
import json
import time

from common import environment, result_path

from hte_jax.hbr.training import preset, train_hbr


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--out", required=True, help="run folder (must not hold a run)")
    parser.add_argument("--json", default=None, help="JSON path (default benchmarks/results/...)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    env = environment()
    began = time.perf_counter()
    outcome = train_hbr(preset(args.preset), args.out, progress=not args.no_progress)
    total = time.perf_counter() - began
    layers = outcome.summary["layers"]
    stats = outcome.summary["statistics"]
    print(f"\npreset {args.preset} on {env['device']}: total {total:.1f} s")
    print(f"{'layer':8}{'evaluations':>13}{'wall s':>9}{'eval/s':>10}{'elites':>9}")
    for name, layer in layers.items():
        print(f"{name:8}{layer['evaluations']:13d}{layer['wall_time_s']:9.1f}"
              f"{layer['evaluations'] / layer['wall_time_s']:10.1f}{layer['filled']:9d}")
    print(f"middle contact patterns: {stats['middle']['contact_patterns']}; top mean fitness "
          f"{stats['top']['mean_fitness']:.4f}")
    path = args.json or result_path(f"hbr_preset_{args.preset}", env)
    with open(path, "w") as handle:
        json.dump({"environment": env, "preset": args.preset, "total_wall_s": total, "layers": layers,
                   "statistics": stats}, handle, indent=2)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
