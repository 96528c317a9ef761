"""Evaluations per second of each HBR layer, for several batch sizes.

One MAP-Elites generation of a layer (selection, mutation, the batched MJX evaluation, archive or
grid insertion) is timed as a compiled `run_block` of one generation; the table reports the median
of --repeats runs as evaluations/s and simulated steps/s. Archive capacities, the middle layer's
number of samples and the top grid come from --preset; lower layers are filled by one random
batch each (lookup cost depends on capacity, not on contents).

    python benchmarks/hbr_layers.py                                      # CPU: batch 64, 256
    python benchmarks/hbr_layers.py --preset gpu --batch-sizes 1024 4096 16384 32768   # GPU
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
from common import environment, result_path

from hte_jax.hbr.training import LAYERS, layer_algorithms, preset, with_overrides
from hte_jax.sim import load_robot, standing_state


def steps_per_evaluation(config, layer: str) -> int:
    return {"bottom": 100, "middle": 100 * config.middle_samples, "top": 300}[layer]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--layers", nargs="+", default=list(LAYERS), choices=LAYERS)
    parser.add_argument("--out", default=None, help="JSON path (default benchmarks/results/...)")
    args = parser.parse_args(argv)

    env = environment()
    base = preset(args.preset)
    robot = load_robot()
    start = standing_state(robot)
    key = jax.random.PRNGKey(0)

    def sized(batch):
        return with_overrides(base, {f"{layer}.{field}": batch for layer in LAYERS for field in ("batch_size", "init_size")})

    # Lower layers: one random batch each, at the smallest batch size, those the benchmarked layers
    # stand on (middle: bottom; top: bottom and middle).
    lower = {}
    seed_config = sized(min(args.batch_sizes))
    for layer in LAYERS[:max(LAYERS.index(name) for name in args.layers)]:
        algo = layer_algorithms(seed_config, robot, start, lower)[layer]()
        lower[layer] = algo.init(key).repertoire

    rows = []
    for layer in args.layers:
        for batch in args.batch_sizes:
            config = sized(batch)
            algo = layer_algorithms(config, robot, start, lower)[layer]()
            t0 = time.perf_counter()
            state = jax.block_until_ready(algo.init(key))
            init_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            state, _ = jax.block_until_ready(algo.run_block(state, 1))
            first_s = time.perf_counter() - t0
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                state, _ = jax.block_until_ready(algo.run_block(state, 1))
                times.append(time.perf_counter() - t0)
            median = statistics.median(times)
            row = {
                "layer": layer,
                "batch": batch,
                "generation_s": median,
                "generation_s_all": times,
                "evaluations_per_s": batch / median,
                "steps_per_s": batch * steps_per_evaluation(config, layer) / median,
                "init_plus_compile_s": init_s,
                "first_generation_plus_compile_s": first_s,
            }
            rows.append(row)
            print(f"{layer:7} batch {batch:6d}: {row['evaluations_per_s']:10.1f} eval/s "
                  f"{row['steps_per_s'] / 1e3:9.1f} k steps/s  (generation {median:.3f} s)", flush=True)

    print(f"\n{'layer':8}{'batch':>8}{'eval/s':>12}{'k steps/s':>12}{'gen s':>9}")
    for r in rows:
        print(f"{r['layer']:8}{r['batch']:8d}{r['evaluations_per_s']:12.1f}{r['steps_per_s'] / 1e3:12.1f}{r['generation_s']:9.3f}")
    settings = {"preset": args.preset, "middle_samples": base.middle_samples, "repeats": args.repeats,
                "capacities": {"bottom": base.bottom.capacity, "middle": base.middle.capacity}}
    path = args.out or result_path("hbr_layers", env)
    with open(path, "w") as handle:
        json.dump({"environment": env, "settings": settings, "rows": rows}, handle, indent=2)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
