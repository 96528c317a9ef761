"""QD bookkeeping versus evaluation time per generation, for the three container kinds.

For each container (the top layer's 100x100 grid, the flat 8-D grid of 640 000 cells, and a
9-D unstructured archive like the middle layer's) and batch sizes 256 ... 65536:

* ask: uniform selection + polynomial mutation of a batch;
* insert: adding an evaluated batch to a half-filled container, in place (donated buffers);
* metrics: coverage / QD score / fitness statistics;
* eval: one batched 3 s hexapod rollout of the same batch size (MJX), the generation's evaluation.

Times are medians of --repeats runs of jitted, compiled functions. Prints a table, writes JSON.

    python benchmarks/qd_overhead.py                     # CPU: batch <= 4096, rollouts <= 256
    python benchmarks/qd_overhead.py --max-batch 65536 --eval-max-batch 65536   # GPU
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from common import environment, result_path

from hte_jax.qd import Archive, Evaluation, Grid, MapElites, MapElitesConfig, repertoire_metrics
from hte_jax.qd.tasks import planar_arm_evaluate

GENOTYPE_DIM = 36


def containers(archive_capacity: int) -> dict:
    return {
        "grid_2d_100x100": Grid(bins=(100, 100), low=(-1.5, -1.5), high=(1.5, 1.5)),
        "grid_8d_640k": Grid(bins=(100, 100) + (2,) * 6, low=(-1.5, -1.5) + (0.0,) * 6, high=(1.5, 1.5) + (1.0,) * 6),
        f"archive_9d_{archive_capacity}": Archive(
            capacity=archive_capacity, low=(0.0,) * 9, high=(1.0,) * 9, l=0.05, chunk_size=512
        ),
    }


def random_evaluation(key, container, batch: int) -> tuple[jax.Array, Evaluation]:
    key_g, key_d, key_f, key_b = jax.random.split(key, 4)
    low = jnp.asarray(container.low)
    high = jnp.asarray(container.high)
    desc = low + jax.random.uniform(key_d, (batch, len(container.low))) * (high - low)
    if isinstance(container, Grid) and len(container.bins) > 2:  # contact bits are 0 or 1
        desc = desc.at[:, 2:].set(jax.random.bernoulli(key_b, 0.5, (batch, 6)).astype(jnp.float32))
    fitness = -jax.random.uniform(key_f, (batch,)) * jnp.pi
    return jax.random.uniform(key_g, (batch, GENOTYPE_DIM)), Evaluation(fitness, desc, jnp.ones(batch, bool))


def half_filled(container, seed: int = 0):
    """A repertoire about half full (archives: half their capacity), filled with random elites."""
    rep = container.empty(GENOTYPE_DIM)
    add = jax.jit(container.add)
    key = jax.random.PRNGKey(seed)
    target = container.capacity // 2
    while int(rep.size) < target:
        key, sub = jax.random.split(key)
        genotypes, evaluation = random_evaluation(sub, container, min(8192, container.capacity))
        rep, _ = add(rep, genotypes, evaluation)
        if isinstance(container, Archive) and int(rep.size) >= target:
            break
    return rep


def timed(fn, *args, repeats: int) -> float:
    jax.block_until_ready(fn(*args))  # compile + warm up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def timed_insert(container, rep, genotypes, evaluation, repeats: int) -> float:
    """Median time of an insertion that updates the repertoire in place (donated buffers),
    as it does inside the MAP-Elites loop's scan."""
    insert = jax.jit(lambda r, g, e: container.add(r, g, e)[0], donate_argnums=0)
    rep = jax.tree.map(jnp.copy, rep)
    rep = jax.block_until_ready(insert(rep, genotypes, evaluation))  # compile + warm up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        rep = jax.block_until_ready(insert(rep, genotypes, evaluation))
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def rollout_seconds(batch: int, repeats: int) -> float:
    from hte_jax.sim import RolloutSpec, load_robot, rollout, standing_state

    robot = load_robot()
    init = standing_state(robot)
    params = jax.random.uniform(jax.random.PRNGKey(0), (batch, 36))
    spec = RolloutSpec(num_steps=300, pose_steps=(0, 100, 200, 300))
    return timed(lambda p: rollout(robot, p, jnp.zeros(6, bool), init, spec), params, repeats=repeats)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--min-batch", type=int, default=256)
    parser.add_argument("--max-batch", type=int, default=4096)
    parser.add_argument("--eval-max-batch", type=int, default=256, help="largest batch whose rollout is timed")
    parser.add_argument("--archive-capacity", type=int, default=32768)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)

    env = environment()
    batches = []
    b = args.min_batch
    while b <= args.max_batch:
        batches.append(b)
        b *= 4
    eval_s = {b: rollout_seconds(b, args.repeats) for b in batches if b <= args.eval_max_batch}

    rows = []
    header = f"{'container':24} {'batch':>6} {'ask ms':>8} {'insert ms':>10} {'metrics ms':>10} {'eval s':>8} {'QD share':>9}"
    print(header)
    print("-" * len(header))
    for name, container in containers(args.archive_capacity).items():
        rep = half_filled(container)
        metrics = jax.jit(lambda r: repertoire_metrics(r, -np.pi))
        for batch in batches:
            algo = MapElites(container, planar_arm_evaluate, GENOTYPE_DIM,
                             MapElitesConfig(batch_size=batch, init_size=batch))
            emitter_state = algo.empty_state(jax.random.PRNGKey(0)).emitter_state
            ask = jax.jit(lambda rep, key: algo.ask(rep, emitter_state, key)[0])
            genotypes, evaluation = random_evaluation(jax.random.PRNGKey(1), container, batch)
            row = {
                "container": name,
                "batch": batch,
                "filled": int(rep.size),
                "ask_s": timed(ask, rep, jax.random.PRNGKey(2), repeats=args.repeats),
                "insert_s": timed_insert(container, rep, genotypes, evaluation, args.repeats),
                "metrics_s": timed(metrics, rep, repeats=args.repeats),
                "eval_s": eval_s.get(batch),
            }
            bookkeeping = row["ask_s"] + row["insert_s"] + row["metrics_s"]
            row["bookkeeping_s"] = bookkeeping
            row["bookkeeping_share"] = None if row["eval_s"] is None else bookkeeping / (bookkeeping + row["eval_s"])
            rows.append(row)
            share = "-" if row["bookkeeping_share"] is None else f"{100 * row['bookkeeping_share']:.2f} %"
            ev = "-" if row["eval_s"] is None else f"{row['eval_s']:.3f}"
            print(f"{name:24} {batch:>6} {1e3 * row['ask_s']:>8.2f} {1e3 * row['insert_s']:>10.2f} "
                  f"{1e3 * row['metrics_s']:>10.2f} {ev:>8} {share:>9}", flush=True)

    print(f"\n{env['device']} ({env['platform']}), jax {env['jax']}, medians of {args.repeats}; "
          "QD share = (ask + insert + metrics) / (that + one 3 s rollout of the batch)")
    out = args.out or result_path("qd_overhead", env)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"environment": env, "settings": vars(args) | {"out": str(out)}, "rows": rows}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
