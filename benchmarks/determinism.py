"""Are two training runs with the same seed bit-identical on this device? And at what cost?

Trains one HBR layer (default: the bottom layer of --preset) twice in one process and compares
the repertoires array by array; prints the wall time of each run. Run it with and without
XLA_FLAGS=--xla_gpu_deterministic_ops=true to see what deterministic GPU kernels cost.

    python benchmarks/determinism.py --preset gpu --generations 16
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np
from common import environment, result_path

from hte_jax.hbr.training import layer_algorithms, preset
from hte_jax.qd.loop import run
from hte_jax.sim import load_robot, standing_state


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--generations", type=int, default=4)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    env = environment()
    config = preset(args.preset)
    robot = load_robot()
    start = standing_state(robot)
    results, times = [], []
    for _ in range(2):
        algo = layer_algorithms(config, robot, start, {})["bottom"]()
        began = time.perf_counter()
        state = algo.init(jax.random.PRNGKey(config.seed))
        state = run(algo, state, args.generations, block_size=config.bottom.block_size, progress=False)
        results.append(jax.device_get(state.repertoire))
        times.append(time.perf_counter() - began)
    leaves = zip(jax.tree.leaves(results[0]), jax.tree.leaves(results[1]))
    identical = all(np.array_equal(a, b, equal_nan=True) for a, b in leaves)
    elites = [int(r.filled.sum()) for r in results]
    flags = os.environ.get("XLA_FLAGS", "")
    print(f"{env['device']}: identical={identical} elites={elites} times={[round(t, 1) for t in times]} XLA_FLAGS={flags!r}")
    path = args.out or result_path("determinism", env)
    with open(path, "w") as handle:
        json.dump({"environment": env, "preset": args.preset, "generations": args.generations, "xla_flags": flags,
                   "identical": identical, "elites": elites, "wall_s": times}, handle, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
