"""Spreading a batch axis over devices: one `Mesh` over the first N devices, the batch axis of a
population or an episode batch split over it, everything else (repertoires, GP data, planner
inputs, the robot) replicated.

Two places do the splitting, both with `jax.shard_map`, so that each device runs the per-row
program on its own rows with no collective inside (a `vmap`-ped while loop, such as the MJX
Newton solver's or the planner's, would otherwise wait on every device at each iteration):
- every MJX rollout (`sim.rollout.rollout`) splits its rows over the mesh that `spread_over`
  makes current while a program is traced (`MapElites` sets it around its evaluations, the step
  model around its blocks), and its results come back replicated;
- an episode batch (`online.episode.run_episodes`) runs its plan and act steps per device.

Who places arrays (docs/design.md, "Which arrays are replicated and which are split"): only a
function given devices, and it places every array it computes with, at its entry:
- the MAP-Elites loops (`place`: the state replicated; each generation's rows split inside the
  rollouts), the step model (`hbr.composition.measure_steps`: robot, controllers and start
  replicated, each block's rows split), episode batches (`online.episode.run_episodes`: skills,
  robot, distance field replicated, episodes split); their results come back replicated (or on
  the host);
- everything else (loaders, analyses, plots) places nothing: it makes uncommitted arrays, which
  jax runs on the default device and moves to wherever they are needed, and runs where its inputs
  are. jax refuses to mix an array committed to ONE device with a mesh's; `mjx.put_model` makes
  such arrays, which `uncommitted` undoes (`sim.robot.load_robot`).

Rows are independent, so a row's result does not depend on the device count N: draws are made
per individual before the split (the population's genotypes and draws, the episodes' own keys)
and a batch that does not divide by N is padded with copies of its last row (`pad_rows`), whose
results are dropped (episodes: marked ended, `online.episode.pad_episodes`). With N = 1 the same
functions run unwrapped: the program is the one a plain `jit` makes, bit for bit.

On a CPU, XLA compiles a vmapped MJX step differently with the number of rows it is compiled for,
so a row's last bits, and through the chaotic dynamics later results, depend on the rows per
device even on ONE device (measured: 3, 5, 6 and 12 rows agree bit for bit; 1, 2, 4, 8 and 24 each
differ, by up to 1.5e-3 after a 3 s rollout). Runs whose rows per device fall in one such class
(a batch of 12 on 1, 2 or 4 devices) are bit-identical across device counts; others agree to that
rounding (`tests/test_sharding.py`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from hte_jax.errors import ConfigError

BATCH_AXIS = "batch"


class ReplicaMismatchError(RuntimeError):
    """A replicated array differs between devices (a non-deterministic kernel, a broken device)."""


def visible_devices() -> int:
    """Number of devices jax sees (over all processes of a multi-host run)."""
    return jax.device_count()


def check_device_count(count: int | None) -> int:
    """`count` devices, checked against the visible ones (None: all of them)."""
    visible = visible_devices()
    if count is None:
        return visible
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or not 1 <= count <= visible:
        raise ConfigError(f"devices must be an integer from 1 to {visible} (the visible devices), got {count!r}")
    return int(count)


def batch_mesh(devices: int | None = None) -> Mesh:
    """A 1-D mesh named "batch" over the first `devices` of `jax.devices()` (None: all)."""
    count = check_device_count(devices)
    return Mesh(np.array(jax.devices()[:count]), (BATCH_AXIS,))


def mesh_size(mesh: Mesh) -> int:
    return int(mesh.devices.size)


def padded_size(batch: int, mesh: Mesh) -> int:
    """The smallest multiple of the mesh's device count that holds `batch` rows."""
    count = mesh_size(mesh)
    return -(-batch // count) * count


def pad_rows(tree: Any, size: int) -> Any:
    """Every leaf's leading axis grown to `size` rows with copies of its last row."""

    def pad(x):
        extra = size - x.shape[0]
        if extra == 0:
            return x
        return jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)], axis=0)

    return jax.tree.map(pad, tree)


def batch_sharding(mesh: Mesh, ndim: int = 1) -> NamedSharding:
    """The leading axis split over the mesh, the other `ndim - 1` axes whole."""
    return NamedSharding(mesh, PartitionSpec(BATCH_AXIS, *([None] * (ndim - 1))))


def replicated(mesh: Mesh) -> NamedSharding:
    """Every device holds the whole array."""
    return NamedSharding(mesh, PartitionSpec())


def replicate(tree: Any, mesh: Mesh) -> Any:
    """Inside jit: every leaf whole on every device of the mesh."""
    return jax.tree.map(lambda x: jax.lax.with_sharding_constraint(x, replicated(mesh)), tree)


def put_replicated(tree: Any, mesh: Mesh) -> Any:
    """Outside jit: the arrays of `tree` copied whole to every device of the mesh."""
    return jax.device_put(tree, replicated(mesh))


def put_batch(tree: Any, mesh: Mesh) -> Any:
    """Outside jit: the leading axis of every leaf (a multiple of the device count) split over the mesh."""
    return jax.tree.map(lambda x: jax.device_put(x, batch_sharding(mesh, np.ndim(x))), tree)


def uncommitted(tree: Any) -> Any:
    """Every array of `tree` as an uncommitted copy on the default device (through the host): for
    arrays that a library committed to one device (`mjx.put_model`), which no mesh could take."""
    return jax.device_put(jax.device_get(tree))


def spread_over(mesh: Mesh):
    """Context (while tracing a jitted program): rollouts traced inside split their rows over `mesh`
    (`map_rows`). It is part of jit's cache key, so a function traced with and without it compiles twice."""
    return jax.sharding.use_abstract_mesh(mesh.abstract_mesh)


def current_mesh():
    """The mesh `spread_over` made current, or None (also inside a `shard_map` over it already)."""
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty or BATCH_AXIS not in mesh.axis_names or BATCH_AXIS in getattr(mesh, "manual_axes", ()):
        return None
    return mesh


def map_rows(fn: Callable[..., Any], shared: Any, rows: Any) -> Any:
    """`fn(shared, rows)` where every leaf of `rows` has the batch as leading axis and `fn` treats
    rows independently; under `spread_over(mesh)` each device runs `fn` on its share of the rows
    (padded to a multiple of the device count, the padding dropped) and the result comes back
    whole on every device. Without a current mesh: `fn(shared, rows)`."""
    mesh = current_mesh()
    if mesh is None or int(np.prod(mesh.axis_sizes)) == 1:
        return fn(shared, rows)  # one device: the very program a plain jit makes
    batch = jax.tree.leaves(rows)[0].shape[0]
    count = int(np.prod(mesh.axis_sizes))
    padded = pad_rows(rows, -(-batch // count) * count)
    split = jax.shard_map(fn, mesh=mesh, in_specs=(PartitionSpec(), PartitionSpec(BATCH_AXIS)),
                          out_specs=PartitionSpec(BATCH_AXIS), check_vma=False)
    result = jax.tree.map(lambda x: x[:batch], split(shared, padded))
    return jax.tree.map(lambda x: jax.lax.with_sharding_constraint(x, PartitionSpec()), result)


def replica_digests(tree: Any) -> dict[str, list[str]]:
    """For every leaf of a replicated pytree: one digest of its bytes per local device copy."""
    digests = {}
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        if not isinstance(leaf, jax.Array):
            continue
        shards = sorted(leaf.addressable_shards, key=lambda s: s.device.id)
        digests[jax.tree_util.keystr(path)] = [
            hashlib.sha256(np.ascontiguousarray(np.asarray(s.data)).tobytes()).hexdigest() for s in shards
        ]
    return digests


def check_replicas(tree: Any, what: str = "state") -> None:
    """Raise ReplicaMismatchError unless every device holds the same bytes of every replicated
    array of `tree` (across processes: each process checks its own devices, and process 0's
    digests are compared with every other process's)."""
    digests = replica_digests(tree)
    for name, values in digests.items():
        if len(set(values)) > 1:
            raise ReplicaMismatchError(
                f"{what}{name} differs between devices ({len(set(values))} distinct copies on "
                f"{len(values)} devices): a non-deterministic kernel or a faulty device; stopping"
            )
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        local = np.array([int(v[0][:15], 16) for v in digests.values()], np.int64)
        everywhere = np.asarray(multihost_utils.process_allgather(local))
        if not (everywhere == everywhere[0]).all():
            raise ReplicaMismatchError(f"{what} differs between hosts: a non-deterministic kernel or a faulty device; stopping")
