"""A small MAP-Elites run used by the kill-and-resume test (run as a subprocess).

python -m tests.qd_run_script DIR [--kill-after-block K] [--resume]
"""

import argparse
import os
import signal
from pathlib import Path

import jax
import numpy as np

from hte_jax.qd import Grid, MapElites, MapElitesConfig, resume, run
from hte_jax.qd.tasks import planar_arm_evaluate

GENERATIONS = 60
BLOCK = 10


def make_algo() -> MapElites:
    config = MapElitesConfig(batch_size=64, init_size=64, mutation_rate=0.2, qd_offset=-np.pi)
    return MapElites(Grid(bins=(16, 16), low=(0.0, 0.0), high=(1.0, 1.0)), planar_arm_evaluate, 6, config)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("dir", type=Path)
    parser.add_argument("--kill-after-block", type=int, default=None)
    parser.add_argument("--resume", action="store_true")
    args = parser.parse_args()
    algo = make_algo()
    checkpoint = args.dir / "checkpoint.npz"
    state = resume(algo, checkpoint) if args.resume else algo.init(jax.random.PRNGKey(42))

    def on_block(block, state, row):
        if block == args.kill_after_block:
            os.kill(os.getpid(), signal.SIGKILL)  # a hard kill, right after the block's checkpoint

    run(algo, state, GENERATIONS, block_size=BLOCK, log_path=args.dir / "metrics.csv",
        checkpoint_path=checkpoint, progress=False, on_block=on_block)


if __name__ == "__main__":
    main()
