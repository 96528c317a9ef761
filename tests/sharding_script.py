"""Multi-device checks of `hte_jax.sharding`, run in a subprocess with 4 forced CPU devices (the
rest of the suite keeps one device); `tests/test_sharding.py` starts it and reads its output.

python -m tests.sharding_script OUT.npz [--devices 1,2,4] [--parts hbr,flat,aprol,episodes,hlo]

Writes OUT.npz: for every part and device count N, the arrays of its result, named
"<part>/<N>/<array>"; "hlo/collectives" lists the collectives found inside while loops of one
compiled top-layer generation on 4 devices (none expected), "replica/error" the message of the
replica check on a deliberately inconsistent array.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile

os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"

import jax  # noqa: E402
import numpy as np  # noqa: E402

from hte_jax import sharding  # noqa: E402

PARTS = ("hbr", "flat", "aprol", "episodes", "hlo", "replica")


def tree_arrays(prefix: str, tree) -> dict[str, np.ndarray]:
    leaves = jax.tree_util.tree_leaves_with_path(jax.device_get(tree))
    return {f"{prefix}/{jax.tree_util.keystr(path)}": np.asarray(leaf) for path, leaf in leaves}


def hbr_config():
    from hte_jax.hbr.training import PRESETS

    return dataclasses.replace(PRESETS["tiny"], step_starts=0)


def run_hbr(devices: int) -> dict:
    from hte_jax.hbr.training import train_hbr

    with tempfile.TemporaryDirectory() as out:
        outcome = train_hbr(hbr_config(), out, progress=False, plots=False, mesh=sharding.batch_mesh(devices))
    hbr = outcome.hbr
    return tree_arrays(f"hbr/{devices}", {"bottom": hbr.bottom, "middle": hbr.middle, "top": hbr.top})


def run_flat(variant: str, devices: int) -> dict:
    from hte_jax.flat.training import preset, train_flat

    with tempfile.TemporaryDirectory() as out:
        outcome = train_flat(preset("tiny", variant), out, progress=False, plots=False, mesh=sharding.batch_mesh(devices))
    return tree_arrays(f"{'flat' if variant == '8d' else variant}/{devices}", outcome.repertoires.repertoire)


def run_episodes(devices: int) -> dict:
    from hte_jax.online.evaluation import EvalConfig, run_batch

    config = EvalConfig(variants="hte", damages="none,leg1,legs1+4", replicates=2, max_actions=3, iterations=20,
                        roots=2, candidates=20, depth=4)
    result = run_batch(config, None, ["hte"], progress=False, mesh=sharding.batch_mesh(devices))
    episodes = result.episodes
    return tree_arrays(f"episodes/{devices}", {"history": episodes.history, "trajectory": episodes.trajectory,
                                                "taken": episodes.taken, "reached": episodes.reached,
                                                "qpos": episodes.sim.qpos})


def top_generation_hlo() -> dict:
    """The compiled generation of a small top layer on 4 devices: collectives inside while loops."""
    from hte_jax.hbr.training import layer_algorithms, train_hbr
    from hte_jax.sim.robot import load_robot
    from hte_jax.sim.rollout import standing_state

    config = hbr_config()
    mesh = sharding.batch_mesh(4)
    with tempfile.TemporaryDirectory() as out:
        hbr = train_hbr(dataclasses.replace(config, top=dataclasses.replace(config.top, generations=0)), out,
                        progress=False, plots=False, mesh=mesh).hbr
    robot = load_robot(config.robot)
    start = standing_state(robot)
    algo = layer_algorithms(config, robot, start, {"bottom": hbr.bottom, "middle": hbr.middle}, mesh)["top"]()
    state = algo.place(algo.empty_state(jax.random.PRNGKey(0)))
    text = jax.jit(algo.generation_step).lower(state).compile().as_text()
    found = sharding.collectives_in_loops(text)
    return {"hlo/collectives": np.array(found, dtype=str), "hlo/all_collectives": np.array(
        sum(text.count(f" {name}(") for name in sharding.COLLECTIVES))}


def replica_error() -> dict:
    """The replica check on an array whose 4 device copies differ in one element."""
    mesh = sharding.batch_mesh(4)
    copies = [jax.device_put(np.full(8, 1.0 if i != 2 else 2.0, np.float32), d) for i, d in enumerate(mesh.devices)]
    broken = jax.make_array_from_single_device_arrays((8,), sharding.replicated(mesh), copies)
    healthy = sharding.put_replicated(np.ones(8, np.float32), mesh)
    sharding.check_replicas({"ok": healthy})
    try:
        sharding.check_replicas({"fitnesses": broken}, what="repertoire")
    except sharding.ReplicaMismatchError as error:
        return {"replica/error": np.array(str(error))}
    return {"replica/error": np.array("")}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("out")
    parser.add_argument("--devices", default="1,2,4")
    parser.add_argument("--parts", default=",".join(PARTS))
    args = parser.parse_args()
    counts = [int(n) for n in args.devices.split(",")]
    parts = args.parts.split(",")
    arrays: dict[str, np.ndarray] = {}
    for n in counts:
        if "hbr" in parts:
            arrays |= run_hbr(n)
        if "flat" in parts:
            arrays |= run_flat("8d", n)
        if "aprol" in parts:
            arrays |= run_flat("aprol", n)
        if "episodes" in parts:
            arrays |= run_episodes(n)
    if "hlo" in parts:
        arrays |= top_generation_hlo()
    if "replica" in parts:
        arrays |= replica_error()
    np.savez(args.out, **arrays)


if __name__ == "__main__":
    main()
