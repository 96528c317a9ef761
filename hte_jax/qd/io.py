"""Checkpoints: any pytree of arrays as `.npz`, with JSON metadata, written atomically.

Layout: one npz entry per leaf, named by its pytree path, plus `__metadata__` (a JSON string
with the format version, every leaf's shape and dtype, and the caller's metadata such as the
container and config). Writes go to a temporary file in the same folder, are fsync-ed, then
renamed over the target, so a kill mid-write leaves the previous checkpoint intact.
Loading checks everything against a template and raises `CheckpointError` naming the problem.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from pathlib import Path
from typing import Any

import jax
import numpy as np

FORMAT = "hte_jax.checkpoint"
FORMAT_VERSION = 1
_META = "__metadata__"


class CheckpointError(ValueError):
    """A checkpoint or repertoire file is missing, corrupt, or does not match what is expected."""


def _leaf_name(path) -> str:
    return "/".join(str(getattr(k, "name", getattr(k, "key", getattr(k, "idx", k)))) for k in path)


def _flatten(tree) -> dict[str, np.ndarray]:
    leaves, _ = jax.tree_util.tree_flatten_with_path(tree)
    return {_leaf_name(path): np.asarray(leaf) for path, leaf in leaves}


def save_checkpoint(path: str | Path, tree: Any, metadata: dict | None = None, *, compress: bool = False) -> None:
    """Atomically write `tree` (a pytree of arrays) and JSON-able `metadata` to `path` (zip-deflated if compress)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = _flatten(tree)
    header = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "leaves": {name: {"shape": list(a.shape), "dtype": str(a.dtype)} for name, a in arrays.items()},
        "metadata": metadata or {},
    }
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as handle:
            save = np.savez_compressed if compress else np.savez
            save(handle, **arrays, **{_META: np.array(json.dumps(header))})
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def read_checkpoint(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """All arrays and the header of a checkpoint file, fully read and CRC-checked."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError) as error:
        raise CheckpointError(f"{path}: not a readable checkpoint (truncated or corrupt): {error}") from None
    if _META not in arrays:
        raise CheckpointError(f"{path}: not an hte-jax checkpoint (no {_META} entry)")
    try:
        header = json.loads(str(arrays.pop(_META)))
    except json.JSONDecodeError as error:
        raise CheckpointError(f"{path}: corrupt metadata: {error}") from None
    if header.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an hte-jax checkpoint (format {header.get('format')!r})")
    if header.get("version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format version {header.get('version')!r} is not supported "
            f"(this hte-jax reads version {FORMAT_VERSION})"
        )
    return arrays, header


def load_checkpoint(path: str | Path, template: Any, expected_metadata: dict | None = None) -> Any:
    """Load a checkpoint into the structure of `template`, checking names, shapes and dtypes.

    expected_metadata: if given, every key in it must equal the stored metadata's value.
    """
    arrays, header = read_checkpoint(path)
    stored = header.get("metadata", {})
    for key, value in (expected_metadata or {}).items():
        if _jsonable(value) != stored.get(key):
            raise CheckpointError(
                f"{path}: checkpoint was written with {key} = {stored.get(key)!r}, "
                f"this run has {key} = {_jsonable(value)!r}"
            )
    leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
    restored = []
    for leaf_path, leaf in leaves:
        name = _leaf_name(leaf_path)
        if name not in arrays:
            raise CheckpointError(f"{path}: missing field {name!r}")
        value, want = arrays.pop(name), np.asarray(leaf)
        if value.shape != want.shape:
            raise CheckpointError(f"{path}: field {name!r} has shape {value.shape}, expected {want.shape}")
        if value.dtype != want.dtype:
            raise CheckpointError(f"{path}: field {name!r} has dtype {value.dtype}, expected {want.dtype}")
        restored.append(value)
    if arrays:
        raise CheckpointError(f"{path}: unexpected fields {sorted(arrays)}")
    return jax.tree_util.tree_unflatten(treedef, [jax.numpy.asarray(v) for v in restored])


def _jsonable(value):
    """The value as it reads back from JSON (tuples become lists)."""
    return json.loads(json.dumps(value))
