"""Spreading a batch axis over devices (docs/design.md, "Which arrays are replicated and which are split"): a 1-D
`Mesh` over the first N devices splits a population's or an episode batch's rows (`jax.shard_map`, no collective
inside), everything else replicated; only a function given devices places arrays. Rows are drawn before the split
and padded with copies of the last (`pad_rows`); N = 1 runs the plain jit program. XLA:CPU compiles a vmapped MJX
step per rows per device (3, 5, 6, 12 agree), so runs agree bit for bit across device counts only in one class."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from hte_jax import cpu_pool
from hte_jax.errors import ConfigError

BATCH_AXIS = "batch"


class ReplicaMismatchError(RuntimeError):
    """A replicated array differs between devices (a non-deterministic kernel, a broken device)."""


def check_device_count(count: int | None) -> int:
    """`count` devices, checked against the visible ones (None: all of them)."""
    visible = jax.device_count()  # over all processes of a multi-host run
    if count is None:
        return visible
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or not 1 <= count <= visible:
        raise ConfigError(f"devices must be an integer from 1 to {visible} (the visible devices), got {count!r}")
    return int(count)


def batch_mesh(devices: int | None = None) -> Mesh:
    """A 1-D mesh named "batch" over the first `devices` of `jax.devices()` (None: all)."""
    count = check_device_count(devices)
    chosen = jax.devices()[:count]
    _require_free_cpu_threads(sum(d.platform == "cpu" and d.process_index == jax.process_index() for d in chosen))
    return Mesh(np.array(chosen), (BATCH_AXIS,))


def _require_free_cpu_threads(cpu_devices: int) -> None:
    """ConfigError where XLA's CPU pool could deadlock under `cpu_devices` devices of this process
    (hte_jax/cpu_pool.py): jax started its CPU client before `hte_jax` sized the pool."""
    threads = cpu_pool.pool_threads()
    if cpu_devices > 1 and threads is not None and threads <= cpu_devices:
        needed = cpu_pool.pool_size(os.cpu_count() or 1, cpu_devices)
        raise ConfigError(f"XLA's CPU pool has {threads} threads for {cpu_devices} CPU devices and can deadlock: "
                          f"import hte_jax before jax touches a device, or set {cpu_pool.POOL_VARIABLE}={needed}")


def mesh_size(mesh: Mesh) -> int:
    return int(mesh.devices.size)


def padded_size(batch: int, mesh: Mesh) -> int:
    """The smallest multiple of the mesh's device count that holds `batch` rows."""
    return -(-batch // mesh_size(mesh)) * mesh_size(mesh)


def pad_rows(tree: Any, size: int) -> Any:
    """Every leaf's leading axis grown to `size` rows with copies of its last row."""

    def pad(x):
        extra = size - x.shape[0]
        return x if extra == 0 else jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)], axis=0)

    return jax.tree.map(pad, tree)


def join_rows(trees: list) -> Any:
    """Trees of one structure joined along every leaf's leading axis (rows), in order."""
    return jax.tree.map(lambda *xs: jnp.concatenate(xs), *trees)


def split_rows(tree: Any, sizes: list[int]) -> list:
    """`tree` cut into consecutive parts of `sizes` rows each (`join_rows` undone)."""
    bounds = np.cumsum([0, *sizes])
    return [jax.tree.map(lambda x, a=a, b=b: x[a:b], tree) for a, b in zip(bounds[:-1], bounds[1:])]


def where_rows(mask: jax.Array, new: Any, old: Any) -> Any:
    """Row i of every leaf from `new` where `mask[i]` (a (B,) bool), else from `old`."""
    return jax.tree.map(lambda n, o: jnp.where(mask.reshape(-1, *([1] * (n.ndim - 1))), n, o), new, old)


def batch_sharding(mesh: Mesh, ndim: int = 1) -> NamedSharding:
    """The leading axis split over the mesh, the other `ndim - 1` axes whole."""
    return NamedSharding(mesh, PartitionSpec(BATCH_AXIS, *([None] * (ndim - 1))))


def replicated(mesh: Mesh) -> NamedSharding:
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


def put_stacked(trees: list) -> Any:
    """Outside jit: pytrees of one structure stacked along a new leading axis on the host, then placed on the
    default device (one transfer per leaf, no XLA program)."""
    return jax.tree.map(lambda *xs: jax.device_put(np.stack([np.asarray(x) for x in xs])), *trees)


def local_device() -> jax.Device:
    """This process's first device, where MJX's loaders put their arrays (their default, `jax.devices()[0]`,
    belongs to process 0 in a multi-process run)."""
    return jax.local_devices()[0]


def addressable(tree: Any) -> Any:
    """`tree` with every array that spans devices of other processes gathered whole into a numpy array
    on this host (the others as they are): what a host read needs in a multi-process run."""
    def whole(x):
        spans_processes = isinstance(x, jax.Array) and not x.is_fully_addressable
        return multihost_utils.process_allgather(x, tiled=True) if spans_processes else x

    return jax.tree.map(whole, tree)


def uncommitted(tree: Any) -> Any:
    """Every array of `tree` as an uncommitted copy on the default device (through the host)."""
    return jax.device_put(jax.device_get(tree))


def spread_over(mesh: Mesh):
    """Context (while tracing): rollouts traced inside split their rows over `mesh`; part of jit's cache key."""
    return jax.sharding.use_abstract_mesh(mesh.abstract_mesh)


def current_mesh():
    """The mesh `spread_over` made current, or None (also inside a `shard_map` over it already)."""
    mesh = jax.sharding.get_abstract_mesh()
    unusable = mesh.empty or BATCH_AXIS not in mesh.axis_names or BATCH_AXIS in getattr(mesh, "manual_axes", ())
    return None if unusable else mesh


def map_rows(fn: Callable[..., Any], shared: Any, rows: Any) -> Any:
    """`fn(shared, rows)` on independent rows (every leaf's leading axis), split over the `spread_over` mesh if any."""
    mesh = current_mesh()
    if mesh is None or int(np.prod(mesh.axis_sizes)) == 1:
        return fn(shared, rows)  # one device: the very program a plain jit makes
    batch = jax.tree.leaves(rows)[0].shape[0]
    count = int(np.prod(mesh.axis_sizes))
    padded = pad_rows(rows, -(-batch // count) * count)
    (shared, rebuild_shared), (padded, rebuild_rows) = _without_empty(shared), _without_empty(padded, count)
    body = _empty_constants_made_inside(lambda s, r: fn(rebuild_shared(s), rebuild_rows(r)))
    split = jax.shard_map(body, mesh=mesh,
                          in_specs=(PartitionSpec(), PartitionSpec(BATCH_AXIS)),
                          out_specs=PartitionSpec(BATCH_AXIS), check_vma=False)
    result = jax.tree.map(lambda x: x[:batch], split(shared, padded))
    return jax.tree.map(lambda x: jax.lax.with_sharding_constraint(x, PartitionSpec()), result)


# XLA's Shardy partitioner (jax 0.11.2) crashes (SIGSEGV, in its ManualComputationUnusedInputsPattern) compiling a
# `shard_map` one of whose inputs is a zero-sized array that is used inside (`benchmarks/warp_devices.py`, variant
# "empty"). Such inputs are the zero-sized leaves of the arguments and the zero-sized constants captured while
# tracing the body (jax passes those in as inputs too): MJX's models hold many (absent sites, cameras, meshes:
# numpy arrays that MuJoCo Warp's calls take). Both are made inside the body instead (zeros: no data).


def _without_empty(tree: Any, split: int = 1) -> tuple[list, Callable[[list], Any]]:
    """`tree`'s leaves with the zero-sized ones set to None, and the function that puts them back inside the
    `shard_map` (zeros, the leading axis divided by `split`)."""
    leaves, treedef = jax.tree.flatten(tree)
    empty = {i: (np.shape(x), x.dtype) for i, x in enumerate(leaves) if np.size(x) == 0}

    def rebuild(kept: list) -> Any:
        local = {i: jnp.zeros((shape[0] // split, *shape[1:]), dtype) for i, (shape, dtype) in empty.items()}
        return jax.tree.unflatten(treedef, [local.get(i, x) for i, x in enumerate(kept)])

    return [None if i in empty else x for i, x in enumerate(leaves)], rebuild


def _empty_constants_made_inside(fn: Callable[..., Any]) -> Callable[..., Any]:
    """`fn` traced to a jaxpr and run with its zero-sized constants made by zeros inside it, not captured."""
    from jax.extend.core import ClosedJaxpr, jaxpr_as_fun

    def run(*args):
        closed, shapes = jax.make_jaxpr(fn, return_shape=True)(*args)
        consts = [jnp.zeros(np.shape(c), c.dtype) if np.size(c) == 0 else c for c in closed.consts]
        flat = jaxpr_as_fun(ClosedJaxpr(closed.jaxpr, consts))(*jax.tree.leaves(args))
        return jax.tree.unflatten(jax.tree.structure(shapes), flat)

    return run


def replica_digests(tree: Any) -> dict[str, list[str]]:
    """For every leaf of a replicated pytree: one digest of its bytes per local device copy."""
    digests = {}
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        if not isinstance(leaf, jax.Array):
            continue
        shards = sorted(leaf.addressable_shards, key=lambda s: s.device.id)
        data = [np.ascontiguousarray(np.asarray(s.data)).tobytes() for s in shards]
        digests[jax.tree_util.keystr(path)] = [hashlib.sha256(b).hexdigest() for b in data]
    return digests


def processes_differing(data: bytes) -> list[int]:
    """The processes whose `data` (the same length everywhere) differs from process 0's; [] in a one-process
    run. A collective: every process calls it, and none gets past it before all have."""
    if jax.process_count() == 1:
        return []
    everywhere = np.asarray(multihost_utils.process_allgather(np.frombuffer(data, np.uint8)))
    return [int(i) for i in np.flatnonzero((everywhere != everywhere[0]).any(axis=1))]


def check_replicas(tree: Any, what: str = "state") -> None:
    """Raise ReplicaMismatchError unless every device of every process holds the same bytes of `tree`."""
    digests = replica_digests(tree)
    for name, values in digests.items():
        if len(set(values)) > 1:
            raise ReplicaMismatchError(f"{what}{name} differs between devices ({len(set(values))} distinct copies on "
                                       f"{len(values)} devices): a non-deterministic kernel or a faulty device; "
                                       "stopping")
    if jax.process_count() > 1:
        local = np.array([int(v[0][:15], 16) for v in digests.values()], np.int64)
        everywhere = np.asarray(multihost_utils.process_allgather(local))
        if not (everywhere == everywhere[0]).all():
            raise ReplicaMismatchError(f"{what} differs between hosts: a non-deterministic kernel or a faulty device; stopping")
