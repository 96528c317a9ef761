"""Summarise an hte-jax checkpoint or repertoire file.

    python -m experiments.inspect_checkpoint runs/top/checkpoint.npz

Prints the format version, the stored metadata and every array's shape, plus the number of elites
and their fitness range for each repertoire the file holds. A missing, truncated, corrupt or foreign
file gives a one-line error and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from experiments.cli import input_errors, interruptible
from hte_jax.qd.io import CheckpointError, read_checkpoint


def describe(path: str) -> str:
    arrays, header = read_checkpoint(path)
    lines = [f"{path}: {header['format']} version {header['version']}"]
    if header.get("metadata"):
        lines.append("metadata: " + json.dumps(header["metadata"], sort_keys=True))
    lines += [f"  {name:40} {str(array.dtype):8} {tuple(array.shape)}" for name, array in sorted(arrays.items())]
    filled = next((a for n, a in arrays.items() if n.endswith("filled")), None)
    fitness = next((a for n, a in arrays.items() if n.endswith("fitnesses")), None)
    if filled is not None and fitness is not None:
        count = int(filled.sum())
        lines.append(f"elites: {count} of {filled.size} slots")
        if count:
            lines.append(f"fitness: min {fitness[filled].min():.4g}, mean {fitness[filled].mean():.4g}, "
                         f"max {fitness[filled].max():.4g}")
    for name in sorted(n for n in arrays if n.endswith("slots") and n[:-5] + "fitnesses" in arrays):
        prefix = name[:-5]  # a repertoire file's elites (`qd.io.elite_arrays`), per layer or damage
        fitness = arrays[prefix + "fitnesses"]
        line = f"elites{' ' + prefix.rstrip('_') if prefix else ''}: {fitness.size}"
        if fitness.size:
            line += f", fitness min {fitness.min():.4g}, mean {fitness.mean():.4g}, max {fitness.max():.4g}"
        lines.append(line)
    generation = next((a for n, a in arrays.items() if n.endswith("generation")), None)
    if generation is not None:
        lines.append(f"generation: {int(np.asarray(generation))}")
    return "\n".join(lines)


@interruptible()  # Ctrl-C: `interrupted: nothing written` (it only reads)
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("path")
    args = parser.parse_args(argv)
    with input_errors(CheckpointError) as errors:
        print(describe(args.path))
    return 2 if errors.failed else 0


if __name__ == "__main__":
    sys.exit(main())
