"""Multi-device checks of `hte_jax.sharding`, run in a subprocess with as many forced CPU devices as
its largest device count (the rest of the suite keeps one device); `tests/test_sharding.py` starts
it and reads its output.

python -m tests.sharding_script OUT.npz [--devices 1,2,4] [--parts hbr,flat,batched,episodes,hlo,replica,empty,archive]

Writes OUT.npz: for every part and device count N, the arrays of its result, named
"<part>/<N>/<array>"; "hlo/collectives" lists the collectives found inside while loops of the
compiled generation of the batched run on the most devices (none expected), "hlo/outside" counts the
collectives of that program outside loops (the gather of the results: some expected),
"replica/error" the message of the replica check on a deliberately inconsistent array (replicated
over every visible device),
"seconds/<part>" the wall time of each part. Every setting is the smallest that still runs
the code path: the whole script must stay within a few minutes on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import tempfile
import time

import jax
import numpy as np

from hte_jax import sharding

PARTS = ("hbr", "flat", "batched", "episodes", "hlo", "replica", "empty", "archive")
BATCHED_DAMAGES = ("leg1", "legs1+4")  # an APROL-style BatchedMapElites of two damages
# Training batches: 12 rows, so 12, 6 or 3 rows per device. XLA's CPU code for a vmapped MJX step
# rounds differently with the rows it is compiled for (measured on one device: 3, 5, 6 and 12 rows
# agree bit for bit, 1, 2, 4, 8 and 24 each differ), so a batch of 6 on 4 devices (2 rows each)
# could not be compared bit for bit; the episode batch (6 on 4 devices) is compared with a tolerance.
BATCH = 12


# HLO inspection (these checks only)
COLLECTIVES = ("all-gather", "all-reduce", "collective-permute", "all-to-all", "reduce-scatter", "collective-broadcast")
_COMPUTATION = re.compile(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$")
_CALLED = re.compile(r"(?:body|condition|calls|to_apply|branch_computations)=\{?([%\w.\-, ]+)\}?")
_OPCODE = re.compile(r"=\s*[^=]*?\s([a-z][\w\-]*)\(")


def collectives_in_loops(hlo_text: str) -> list[str]:
    """The collective instructions (`COLLECTIVES`) of a compiled HLO module (`compiled.as_text()`)
    that run inside a while loop's body or condition, or anything they call; [] when none does."""
    computations: dict[str, list[str]] = {}
    current = None
    for line in hlo_text.splitlines():
        match = _COMPUTATION.match(line)
        if match and "=" not in line.split("{")[0].split("(")[0]:
            current = match.group(1)
            computations[current] = []
        elif line.strip() == "}":
            current = None
        elif current is not None:
            computations[current].append(line)

    def callees(lines, keys=("body", "condition", "calls", "to_apply", "branch_computations")):
        for line in lines:
            for found in _CALLED.finditer(line):
                for name in found.group(1).split(","):
                    yield name.strip().lstrip("%")

    loop_roots = {name for lines in computations.values() for line in lines if " while(" in line
                  for name in callees([line])}
    inside, todo = set(), list(loop_roots)
    while todo:
        name = todo.pop()
        if name in inside or name not in computations:
            continue
        inside.add(name)
        todo.extend(callees(computations[name]))
    found = []
    for name in sorted(inside):
        for line in computations[name]:
            opcode = _OPCODE.search(line)
            if opcode and opcode.group(1).removesuffix("-start").removesuffix("-done") in COLLECTIVES:
                found.append(f"{name}: {line.strip()[:160]}")
    return found



def tree_arrays(prefix: str, tree) -> dict[str, np.ndarray]:
    leaves = jax.tree_util.tree_leaves_with_path(jax.device_get(tree))
    return {f"{prefix}/{jax.tree_util.keystr(path)}": np.asarray(leaf) for path, leaf in leaves}


def hbr_config():
    """Every layer: a batch of 12 (12, 6 or 3 rows per device), one generation after the first batch."""
    from hte_jax.hbr.training import PRESETS

    tiny = PRESETS["tiny"]
    small = {layer: dataclasses.replace(getattr(tiny, layer), batch_size=BATCH, init_size=BATCH, generations=1, block_size=1)
             for layer in ("bottom", "middle", "top")}
    return dataclasses.replace(tiny, step_starts=0, **small)


def flat_config(variant: str):
    from hte_jax.flat.training import preset

    return dataclasses.replace(preset("tiny", variant), batch_size=BATCH, init_size=BATCH, generations=1, block_size=1)


def run_hbr(devices: int) -> dict:
    from hte_jax.hbr.training import train_hbr

    with tempfile.TemporaryDirectory() as out:
        outcome = train_hbr(hbr_config(), out, progress=False, plots=False, mesh=sharding.batch_mesh(devices))
    hbr = outcome.hbr
    return tree_arrays(f"hbr/{devices}", {"bottom": hbr.bottom, "middle": hbr.middle, "top": hbr.top})


def run_flat(devices: int) -> dict:
    from hte_jax.flat.training import train_flat

    with tempfile.TemporaryDirectory() as out:
        outcome = train_flat(flat_config("8d"), out, progress=False, plots=False, mesh=sharding.batch_mesh(devices))
    return tree_arrays(f"flat/{devices}", outcome.repertoires.repertoire)


def run_batched(devices: int) -> dict:
    """The APROL variant's BatchedMapElites (flat 2-D task, a run per damage) on two damages."""
    import jax.numpy as jnp

    from hte_jax.flat.task import evaluate_flat, flat_spec
    from hte_jax.qd.batched import BatchedMapElites
    from hte_jax.qd.loop import run
    from hte_jax.sim.damage import damage_masks
    from hte_jax.sim.robot import load_robot
    from hte_jax.sim.rollout import standing_state

    config = flat_config("aprol")
    robot = load_robot(config.robot)
    task = config.task
    masks = jnp.asarray(damage_masks(BATCHED_DAMAGES))
    conditions = {"damage": masks, "start": standing_state(robot, masks)}
    spec = flat_spec(task, evaluate=lambda key, genes, c: evaluate_flat(robot, task, c["start"], c["damage"], key, genes))
    algo = BatchedMapElites.from_spec(spec, conditions, BATCHED_DAMAGES, config.map_elites_config(),
                                      mesh=sharding.batch_mesh(devices))
    state = run(algo, algo.init(jax.random.PRNGKey(config.seed)), config.generations, block_size=1, progress=False)
    return tree_arrays(f"batched/{devices}", state.repertoire), (algo, state)


def episode_config():
    """HTE on the shipped HBR, 3 damages x 2 replicates, 2 actions, a tiny planner."""
    from hte_jax.online.evaluation import EvalConfig
    from hte_jax.online.mcts import PlannerConfig

    return EvalConfig(variants="hte", damages="none,leg1,legs1+4", replicates=2, max_actions=2,
                      planner=PlannerConfig(iterations=8, roots=2, candidates=8, depth=2))


def run_episodes(devices: int) -> dict:
    """6 episodes (3 damages x 2 replicates of HTE on the shipped HBR): 4 devices pad them to 8."""
    from hte_jax.online.evaluation import run_batch

    result = run_batch(episode_config(), None, ["hte"], progress=False, mesh=sharding.batch_mesh(devices))
    episodes = result.episodes
    return tree_arrays(f"episodes/{devices}", {"history": episodes.history, "trajectory": episodes.trajectory,
                                                "taken": episodes.taken, "reached": episodes.reached,
                                                "qpos": episodes.sim.qpos})


def generation_hlo(algo, state) -> dict:
    """The compiled block of one generation of `algo` (the batched run on the most devices, already
    compiled by its run: the compilation cache answers): the collectives inside while loops (the
    rollout's scan, the MJX solver's loops) and outside them."""
    text = type(algo).run_block.lower(algo, state, 1).compile().as_text()
    inside = collectives_in_loops(text)
    total = sum(text.count(f" {name}(") + text.count(f" {name}-start(") for name in COLLECTIVES)
    return {"hlo/collectives": np.array(inside, dtype=str), "hlo/outside": np.array(total - len(inside)),
            "hlo/loops": np.array(text.count(" while("))}


def run_empty(devices: int) -> dict:
    """`sharding.map_rows` of a function using zero-sized arrays: a shared leaf, a row leaf and a numpy constant
    (MJX's Warp models hold many; inputs of a shard_map that crashed jax 0.11.2's partitioner)."""
    import jax.numpy as jnp

    def fn(shared, rows):
        return rows[0] * shared[0] + shared[1].sum() + rows[1].sum(axis=1) + jnp.asarray(np.zeros((0, 2))).sum()

    mesh = sharding.batch_mesh(devices)
    shared = (np.float32(2.0), np.zeros((0, 3), np.float32))
    rows = (np.arange(BATCH, dtype=np.float32), np.zeros((BATCH, 0), np.float32))
    with sharding.spread_over(mesh):
        out = jax.jit(lambda s, r: sharding.map_rows(fn, s, r))(*sharding.put_replicated((shared, rows), mesh))
    return {f"empty/{devices}/out": np.asarray(out)}


def run_archive(devices: int) -> dict:
    """Where a generation runs them: `Archive.add` of BATCH candidates into 20 elites (additions, replacements
    and rejections) on inputs replicated on the mesh, as `tell` does, its new repertoire and insertion; and, under
    `spread_over` as in a layer's evaluation, the nearest of 20 points (arrays of the mesh, closed over) to each
    of BATCH queries in blocks of 5 rows (`middle.nearest_index`)."""
    import jax.numpy as jnp

    from hte_jax.hbr.middle import nearest_index
    from hte_jax.qd.archive import Archive
    from hte_jax.qd.repertoire import Evaluation

    rng = np.random.default_rng(0)
    archive = Archive(64, (0.0, 0.0), (1.0, 1.0), l=0.1, k=3)
    filled = np.arange(64) < 20
    repertoire = archive.empty(3).replace(
        genotypes=jnp.asarray(rng.random((64, 3)), jnp.float32) * filled[:, None],
        descriptors=jnp.asarray(rng.random((64, 2)), jnp.float32) * filled[:, None],
        fitnesses=jnp.where(filled, jnp.asarray(rng.random(64), jnp.float32), -jnp.inf), filled=jnp.asarray(filled))
    genotypes = jnp.asarray(rng.random((BATCH, 3)), jnp.float32)
    evaluation = Evaluation(fitnesses=jnp.asarray(rng.random(BATCH), jnp.float32),
                            descriptors=jnp.asarray(rng.random((BATCH, 2)), jnp.float32),
                            valid=jnp.asarray(np.arange(BATCH) != 5))
    mesh = sharding.batch_mesh(devices)

    args = sharding.put_replicated((repertoire, genotypes, evaluation), mesh)
    new, insertion = jax.jit(archive.add)(*args)

    points, mask, queries = sharding.put_replicated((repertoire.descriptors, repertoire.filled,
                                                     evaluation.descriptors), mesh)

    def nearest(queries):  # closing over arrays of the mesh, as a layer's evaluation does over the layer below
        with sharding.spread_over(mesh):
            return nearest_index(points, mask, queries, chunk=5)

    found = jax.jit(nearest)(queries)
    return tree_arrays(f"archive/{devices}", {"repertoire": new, "insertion": insertion, "nearest": found})


def replica_error() -> dict:
    """The replica check on an array whose device copies (one per visible device) differ in one element."""
    mesh = sharding.batch_mesh(jax.device_count())
    last = len(mesh.devices) - 1
    copies = [jax.device_put(np.full(8, 1.0 if i != last else 2.0, np.float32), d) for i, d in enumerate(mesh.devices)]
    broken = jax.make_array_from_single_device_arrays((8,), sharding.replicated(mesh), copies)
    healthy = sharding.put_replicated(np.ones(8, np.float32), mesh)
    sharding.check_replicas({"ok": healthy})
    try:
        sharding.check_replicas({"fitnesses": broken}, what="repertoire")
    except sharding.ReplicaMismatchError as error:
        return {"replica/error": np.array(str(error))}
    return {"replica/error": np.array("")}


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    parser.add_argument("out")
    parser.add_argument("--devices", default="1,2,4")
    parser.add_argument("--parts", default=",".join(PARTS))
    args = parser.parse_args(argv)
    args.counts = [int(n) for n in args.devices.split(",")]
    return args


def main(args: argparse.Namespace):
    counts = args.counts
    parts = args.parts.split(",")
    arrays: dict[str, np.ndarray] = {}
    seconds: dict[str, float] = {}

    def timed(name, fn, *a):
        tick = time.perf_counter()
        result = fn(*a)
        seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - tick
        print(f"{name}: {time.perf_counter() - tick:.1f} s", flush=True)
        return result

    batched = None
    for n in counts:
        if "hbr" in parts:
            arrays |= timed("hbr", run_hbr, n)
        if "flat" in parts:
            arrays |= timed("flat", run_flat, n)
        if "empty" in parts:
            arrays |= timed("empty", run_empty, n)
        if "archive" in parts:
            arrays |= timed("archive", run_archive, n)
        if "batched" in parts or "hlo" in parts:
            found, batched = timed("batched", run_batched, n)
            arrays |= found
    if "episodes" in parts:
        for n in sorted({1, max(counts)}):
            arrays |= timed("episodes", run_episodes, n)
    if "hlo" in parts:
        arrays |= timed("hlo", generation_hlo, *batched)
    if "replica" in parts:
        arrays |= timed("replica", replica_error)
    arrays |= {f"seconds/{name}": np.array(s) for name, s in seconds.items()}
    np.savez(args.out, **arrays)


if __name__ == "__main__":
    arguments = parse_args()
    # before jax starts its backend: as many forced CPU devices as the largest count asked for (set
    # here, so importing this module for its configurations changes nothing)
    others = [f for f in os.environ.get("XLA_FLAGS", "").split() if not f.startswith("--xla_force_host_platform")]
    os.environ["XLA_FLAGS"] = " ".join([*others, f"--xla_force_host_platform_device_count={max(arguments.counts)}"])
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    main(arguments)
