"""Evaluations per second of each HBR layer, for several batch sizes and device counts, and where a
generation's time goes.

One MAP-Elites generation of a layer (selection, mutation, the batched MJX evaluation, archive or
grid insertion) is timed as a compiled `run_block` of one generation; the table reports the median
of --repeats runs as evaluations/s and simulated steps/s. Archive capacities, the middle layer's
number of samples and the top grid come from --preset; lower layers are filled by one random
batch each (lookup cost depends on capacity, not on contents). --devices N measures on the first N
devices (one mesh, the batch's rollouts split over it, as `train_hbr --devices N`; one count per run:
a process keeps the size of its mesh);
--parts also times the generation's three steps as separate compiled programs on the same devices:
`ask` (selection and variation), `evaluate` (the rollouts and what turns them into fitness and
descriptors) and `tell` (insertion); --trace DIR records one more generation with `jax.profiler` per
row (a Perfetto trace a researcher opens at ui.perfetto.dev) and reports each traced device's busy
time and its longest operations.

    python benchmarks/hbr_layers.py                                      # CPU: batch 64, 256
    python benchmarks/hbr_layers.py --preset gpu --batch-sizes 1024 4096 16384 32768   # GPU
    python benchmarks/hbr_layers.py --preset gpu --impl warp --layers middle top --batch-sizes 16384 32768 \\
        --devices 2 --parts --trace runs/traces                          # then --devices 1: what does not split
"""

from __future__ import annotations

import argparse
import gzip
import json
import statistics
import time
from collections import defaultdict
from pathlib import Path

import jax
from common import environment, result_path

from hte_jax.hbr.training import LAYERS, layer_algorithms, preset, with_overrides
from hte_jax.sharding import batch_mesh
from hte_jax.sim import load_robot, standing_state
from hte_jax.sim.mjx_import import require_impl
from hte_jax.warp_calls import waited

TOP_OPERATIONS = 12  # the longest operations a trace summary lists per device


def steps_per_evaluation(config, layer: str) -> int:
    return {"bottom": 100, "middle": 100 * config.middle_samples, "top": 300}[layer]


def timed(fn, *args, repeats: int) -> tuple[float, float, list[float], object]:
    """Seconds of a first call of `fn(*args)` (compiling it), the median of `repeats` calls after it and their
    times, each `waited` for; and the last result."""
    times = []
    for _ in range(1 + repeats):
        t0 = time.perf_counter()
        out = waited(fn, *args)
        times.append(time.perf_counter() - t0)
    return times[0], statistics.median(times[1:]), times[1:], out


def part_seconds(algo, state, repeats: int) -> dict:
    """Median seconds of one generation's `ask`, `evaluate` and `tell`, each a compiled program of its own."""
    key_ask, key_eval = jax.random.split(state.key)
    _, ask_s, _, (genotypes, emitter_state) = timed(jax.jit(algo.ask), state.repertoire, state.emitter_state, key_ask,
                                                 repeats=repeats)
    _, evaluate_s, _, evaluation = timed(jax.jit(algo.evaluate_batch), key_eval, genotypes, repeats=repeats)
    _, tell_s, _, _ = timed(jax.jit(algo.tell), state.repertoire, emitter_state, genotypes, evaluation, repeats=repeats)
    return {"ask_s": ask_s, "evaluate_s": evaluate_s, "tell_s": tell_s}


def trace_summary(folder: Path) -> dict:
    """Per traced process of the Perfetto trace under `folder` (a device, the host): the summed seconds of its
    complete events, their count, and the longest operations by summed seconds."""
    path = max(folder.rglob("perfetto_trace.json.gz"))  # the latest trace under it
    with gzip.open(path, "rt") as handle:
        events = json.load(handle)
    events = events["traceEvents"] if isinstance(events, dict) else events
    names = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
    busy, count, by_name = defaultdict(float), defaultdict(int), defaultdict(lambda: defaultdict(float))
    for e in events:
        if e.get("ph") == "X" and "dur" in e:
            where = names.get(e["pid"], str(e["pid"]))
            busy[where] += e["dur"] / 1e6
            count[where] += 1
            by_name[where][e.get("name", "?")] += e["dur"] / 1e6
    return {where: {"seconds": round(busy[where], 4), "events": count[where],
                    "longest": [[name, round(sec, 4)] for name, sec in
                                sorted(by_name[where].items(), key=lambda kv: -kv[1])[:TOP_OPERATIONS]]}
            for where in sorted(busy)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--impl", default=None, help="MJX implementation, jax or warp (default: the preset's)")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--devices", type=int, default=None, help="devices to spread the batch over (default: all)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--layers", nargs="+", default=list(LAYERS), choices=LAYERS)
    parser.add_argument("--parts", action="store_true", help="also time ask, evaluate and tell apart")
    parser.add_argument("--trace", default=None, help="folder for one traced generation per row (jax.profiler)")
    parser.add_argument("--out", default=None, help="JSON path (default benchmarks/results/...)")
    args = parser.parse_args(argv)

    env = environment()
    base = preset(args.preset)
    if args.impl is not None:
        base = with_overrides(base, {"solver.impl": args.impl})
    require_impl(base.robot.impl)
    mesh = batch_mesh(args.devices)
    devices = int(mesh.devices.size)
    robot = load_robot(base.robot)
    start = standing_state(robot)
    key = jax.random.PRNGKey(0)

    def sized(batch):
        return with_overrides(base, {f"{layer}.{field}": batch for layer in LAYERS for field in ("batch_size", "init_size")})

    # Lower layers: one random batch each, at the smallest batch size, those the benchmarked layers
    # stand on (middle: bottom; top: bottom and middle).
    lower = {}
    seed_config = sized(min(args.batch_sizes))
    for layer in LAYERS[:max(LAYERS.index(name) for name in args.layers)]:
        algo = layer_algorithms(seed_config, robot, start, lower, mesh)[layer]()
        lower[layer] = waited(algo.init, key).repertoire

    rows = []
    for layer in args.layers:
        for batch in args.batch_sizes:
            config = sized(batch)
            algo = layer_algorithms(config, robot, start, lower, mesh)[layer]()
            t0 = time.perf_counter()
            state = waited(lambda: algo.place(algo.init(key)))
            init_s = time.perf_counter() - t0
            first_s, median, times, (state, _) = timed(algo.run_block, state, 1, repeats=args.repeats)
            row = {
                "layer": layer,
                "batch": batch,
                "devices": devices,
                "generation_s": median,
                "generation_s_all": times,
                "evaluations_per_s": batch / median,
                "steps_per_s": batch * steps_per_evaluation(config, layer) / median,
                "init_plus_compile_s": init_s,
                "first_generation_plus_compile_s": first_s,
            }
            if args.parts:
                row.update(part_seconds(algo, state, args.repeats))
            if args.trace is not None:
                folder = Path(args.trace) / f"{layer}_{batch}_{devices}dev"
                with jax.profiler.trace(str(folder), create_perfetto_trace=True):
                    waited(algo.run_block, state, 1)
                row["trace"] = {"folder": str(folder), "processes": trace_summary(folder)}
            rows.append(row)
            parts = "".join(f"  {name} {row[f'{name}_s']:.3f}" for name in ("ask", "evaluate", "tell") if f"{name}_s" in row)
            print(f"{layer:7} batch {batch:6d} on {devices} device(s): {row['evaluations_per_s']:10.1f} eval/s "
                  f"{row['steps_per_s'] / 1e3:9.1f} k steps/s  (generation {median:.3f} s{parts})", flush=True)

    print(f"\n{'layer':8}{'batch':>8}{'devices':>8}{'eval/s':>12}{'k steps/s':>12}{'gen s':>9}"
          + ("".join(f"{name:>12}" for name in ("ask s", "evaluate s", "tell s")) if args.parts else ""))
    for r in rows:
        print(f"{r['layer']:8}{r['batch']:8d}{r['devices']:8d}{r['evaluations_per_s']:12.1f}{r['steps_per_s'] / 1e3:12.1f}"
              f"{r['generation_s']:9.3f}" + ("".join(f"{r[k]:12.3f}" for k in ("ask_s", "evaluate_s", "tell_s")) if args.parts else ""))
    settings = {"preset": args.preset, "impl": base.robot.impl, "devices": devices, "parts": args.parts,
                "middle_samples": base.middle_samples, "repeats": args.repeats,
                "capacities": {"bottom": base.bottom.capacity, "middle": base.middle.capacity}}
    path = args.out or result_path("hbr_layers", env)
    with open(path, "w") as handle:
        json.dump({"environment": env, "settings": settings, "rows": rows}, handle, indent=2)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
