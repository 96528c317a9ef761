"""Repertoire files of any task spec: the elites (`io.elite_arrays`) in a compressed `.npz`, its header the spec's
`metadata()` (a file loads only for the same) and the caller's; `rebuild_elites` also checks HBR and flat files."""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from hte_jax.errors import ConfigError
from hte_jax.qd.archive import Archive
from hte_jax.qd.grid import Grid
from hte_jax.qd.io import CheckpointError, jsonable, elite_arrays, read_checkpoint, rebuild_repertoire, save_checkpoint
from hte_jax.qd.repertoire import Repertoire
from hte_jax.qd.task_spec import TaskSpec

KIND = "hte_jax.repertoire"
KIND_VERSION = 1
_RESERVED = ("kind", "kind_version", "task")


def check_repertoire(spec: TaskSpec, repertoire: Repertoire) -> None:
    """Raise ConfigError unless `repertoire` has the spec's capacity, genotype and descriptor sizes and extras."""
    want_leaves, want_tree = jax.tree_util.tree_flatten_with_path(jax.eval_shape(spec.empty))
    got_leaves, got_tree = jax.tree_util.tree_flatten_with_path(repertoire)
    if want_tree != got_tree:
        raise ConfigError(f"task {spec.name!r}: the repertoire's fields {got_tree} are not the spec's {want_tree}")
    for (path, expected), (_, leaf) in zip(want_leaves, got_leaves):
        if tuple(np.shape(leaf)) != expected.shape or np.asarray(leaf).dtype != expected.dtype:
            name = jax.tree_util.keystr(path)
            raise ConfigError(f"task {spec.name!r}: repertoire{name} is {np.shape(leaf)} {np.asarray(leaf).dtype}, "
                              f"the spec's is {expected.shape} {expected.dtype}")


def save_repertoire(path: str | Path, spec: TaskSpec, repertoire: Repertoire, metadata: dict | None = None) -> None:
    """Atomically write the elites of `repertoire` (compressed) with the spec and JSON-able `metadata`."""
    check_repertoire(spec, repertoire)
    clash = sorted(set(metadata or {}) & set(_RESERVED))
    if clash:
        raise ConfigError(f"metadata keys {clash} are reserved for the file's header")
    header = {"kind": KIND, "kind_version": KIND_VERSION, "task": spec.metadata(), **(metadata or {})}
    save_checkpoint(path, elite_arrays(repertoire), header, compress=True)


def load_repertoire(path: str | Path, spec: TaskSpec) -> tuple[Repertoire, dict]:
    """Read a file of `save_repertoire` written for this spec: (Repertoire on device, the header metadata)."""
    arrays, meta = read_kind(path, KIND, KIND_VERSION, "repertoire")
    stored, wanted = meta.get("task"), jsonable(spec.metadata())
    if not isinstance(stored, dict):
        raise CheckpointError(f"{path}: bad repertoire header: no task")
    for key, value in wanted.items():
        if stored.get(key) != value:
            raise CheckpointError(f"{path}: repertoire was written with task {key} = {stored.get(key)!r}, this spec has {value!r}")
    return rebuild_elites(path, arrays, spec), meta


def rebuild_elites(path, arrays: dict, spec: TaskSpec, prefix: str = "", label: str | None = None) -> Repertoire:
    """One repertoire of the spec from its `elite_arrays` (under `prefix`), every array checked
    (`io.rebuild_repertoire`), and each elite where its container keeps it: a grid's elite in the
    cell of its descriptor, an archive's elites a prefix of its slots. label: names the repertoire
    in errors (default: the prefix, or "repertoire")."""
    container = spec.container
    repertoire = rebuild_repertoire(path, arrays, prefix, spec.capacity, spec.genotype_dim, spec.descriptor_dim,
                                    spec.extras, low=container.low, high=container.high)
    label = label or prefix.rstrip("_") or "repertoire"
    slots = arrays[f"{prefix}slots"]
    if isinstance(container, Grid) and not container.cell_matches(arrays[f"{prefix}descriptors"], slots).all():
        raise CheckpointError(f"{path}: {label} has elites outside their descriptors' cells")
    if isinstance(container, Archive) and not np.array_equal(slots, np.arange(slots.shape[0])):
        raise CheckpointError(f"{path}: {label} elites are not a prefix of the archive")
    return repertoire


def read_kind(path, kind: str, version: int, what: str, article: str = "a") -> tuple[dict, dict]:
    """(arrays, header metadata) of a checkpoint file whose header has `kind` and `version`, else
    CheckpointError naming the file `what` ("not {article} {what} file")."""
    arrays, header = read_checkpoint(path)
    meta = header.get("metadata", {})
    if meta.get("kind") != kind:
        raise CheckpointError(f"{path}: not {article} {what} file (kind {meta.get('kind')!r})")
    if meta.get("kind_version") != version:
        raise CheckpointError(f"{path}: {what} file version {meta.get('kind_version')!r} is not supported")
    return arrays, meta
