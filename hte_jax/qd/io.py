"""Checkpoints: a pytree of arrays as `.npz` plus a JSON header, written atomically; loads raise `CheckpointError`."""

from __future__ import annotations

import hashlib
import json
import os
import time
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils

from hte_jax import sharding
from hte_jax.errors import ConfigError
from hte_jax.qd.repertoire import EMPTY_FITNESS, Repertoire

FORMAT = "hte_jax.checkpoint"
FORMAT_VERSION = 1
_META = "__metadata__"
_ZIP_MAGIC = b"PK\x03\x04"  # how every .npz (a zip archive) begins
PAUSE_BEFORE_RENAME = "HTE_JAX_CHECKPOINT_PAUSE"  # seconds; tests and benchmarks only (`save_checkpoint`)


class CheckpointError(ValueError):
    """A checkpoint or repertoire file is missing, corrupt, or does not match what is expected."""


def _leaf_name(path) -> str:
    return "/".join(str(getattr(k, "name", getattr(k, "key", getattr(k, "idx", k)))) for k in path)


def save_checkpoint(path: str | Path, tree: Any, metadata: dict | None = None, *, compress: bool = False) -> None:
    """Atomically write `tree` (a pytree of arrays) and JSON-able `metadata` to `path` (zip-deflated if compress).
    $HTE_JAX_CHECKPOINT_PAUSE (seconds; tests and `benchmarks/resume_kill.py`) sleeps before the rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {_leaf_name(leaf_path): np.asarray(leaf) for leaf_path, leaf in jax.tree_util.tree_leaves_with_path(tree)}
    leaves = {name: {"shape": list(a.shape), "dtype": str(a.dtype)} for name, a in arrays.items()}
    header = {"format": FORMAT, "version": FORMAT_VERSION, "leaves": leaves, "metadata": metadata or {}}
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as handle:
            save = np.savez_compressed if compress else np.savez
            save(handle, **arrays, **{_META: np.array(json.dumps(header))})
            handle.flush()
            os.fsync(handle.fileno())
        if os.environ.get(PAUSE_BEFORE_RENAME):
            time.sleep(float(os.environ[PAUSE_BEFORE_RENAME]))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    _remove_leftovers(path)
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def _remove_leftovers(path: Path) -> None:
    """Remove the temporary files of `path` left by writers killed mid-write (processes no longer running)."""
    for leftover in path.parent.glob(f".{path.name}.tmp-*"):
        pid = leftover.name.rpartition("-")[2]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            leftover.unlink(missing_ok=True)
        except OSError:  # running, under another user
            pass


def read_checkpoint(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """All arrays and the header of a checkpoint file, fully read and CRC-checked."""
    arrays = _read(Path(path))
    return arrays, _header(Path(path), arrays.pop(_META, None))


def read_header(path: str | Path) -> dict:
    """The header of a checkpoint file without reading its arrays (a damaged array goes unnoticed)."""
    return _header(Path(path), _read(Path(path), only=_META).get(_META))


def _read(path: Path, only: str | None = None) -> dict[str, np.ndarray]:
    """The arrays of an .npz file (only `only`, if given); CheckpointError unless a sound .npz of plain arrays."""
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        with open(path, "rb") as handle:
            magic = handle.read(len(_ZIP_MAGIC))
    except OSError as error:
        raise CheckpointError(f"{path}: cannot be read ({error.strerror})") from None
    if magic != _ZIP_MAGIC:  # np.load would try it as a .npy, then as a pickle
        what = "an empty file" if not magic else "not an .npz archive"
        raise CheckpointError(f"{path}: not an hte-jax checkpoint ({what})")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in data.files if only is None or name == only}
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError) as error:
        raise CheckpointError(f"{path}: not an hte-jax checkpoint, or a truncated or corrupt one ({error})") from None
    except (ValueError, KeyError):  # entries that are not plain arrays (object arrays, foreign files)
        raise CheckpointError(f"{path}: not an hte-jax checkpoint (its entries are not plain arrays)") from None


def _header(path: Path, stored: np.ndarray | None) -> dict:
    """The checked header of a checkpoint from its `__metadata__` entry (None: it has none)."""
    if stored is None:
        raise CheckpointError(f"{path}: not an hte-jax checkpoint (no {_META} entry)")
    try:
        header = json.loads(str(stored))
    except json.JSONDecodeError as error:
        raise CheckpointError(f"{path}: corrupt metadata: {error}") from None
    if not isinstance(header, dict):
        raise CheckpointError(f"{path}: not an hte-jax checkpoint (its metadata is not a JSON object)")
    if header.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an hte-jax checkpoint (format {header.get('format')!r})")
    if header.get("version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {header.get('version')!r} is not supported "
                              f"(this hte-jax reads version {FORMAT_VERSION})")
    return header


def load_checkpoint(path: str | Path, template: Any, expected_metadata: dict | None = None) -> Any:
    """Load a checkpoint into `template`'s structure, checking leaves and every key of `expected_metadata`."""
    arrays, header = read_checkpoint(path)
    stored = header.get("metadata", {})
    for key, value in (expected_metadata or {}).items():
        if jsonable(value) != stored.get(key):
            raise CheckpointError(f"{path}: checkpoint was written with {key} = {stored.get(key)!r}, "
                                  f"this run has {key} = {jsonable(value)!r}")
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
    return jax.tree_util.tree_unflatten(treedef, [jnp.asarray(v) for v in restored])


def jsonable(value):
    """The value as it reads back from JSON (tuples become lists)."""
    return json.loads(json.dumps(value))


def write_json(path: str | Path, data: dict) -> None:
    """Atomically write `data` as indented JSON."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, path)


def stored_config(out: str | Path) -> dict | None:
    """The configuration a run folder was started with (its `config.json`), or None when it holds no run."""
    path = Path(out) / "config.json"
    return _read_config(path) if path.exists() else None


def _read_config(path: Path) -> dict:
    try:
        config = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ConfigError(f"{path} is not a run's configuration (not JSON: {error})") from None
    if not isinstance(config, dict):
        raise ConfigError(f"{path} is not a run's configuration (not a JSON object)")
    return config


def run_files_digest(out: str | Path) -> bytes:
    """sha256 of the names and bytes of the JSON and NPZ files under `out` (what a resumed run reads)."""
    digest = hashlib.sha256()
    for path in sorted(p for p in Path(out).rglob("*") if p.suffix in (".json", ".npz") and p.is_file()):
        digest.update(f"{path.relative_to(out)}\0".encode())
        digest.update(hashlib.sha256(path.read_bytes()).digest())
    return digest.digest()


def require_same_run_folder(out: str | Path) -> None:
    """In a multi-process run (a collective: every process calls it), ConfigError on every process unless each
    sees the same JSON and NPZ files under `out` as process 0: the others read it too, on --resume."""
    if jax.process_count() == 1:
        return
    differing = sharding.processes_differing(run_files_digest(out))
    if differing:
        raise ConfigError(f"process {differing[0]} of {jax.process_count()} sees other files in {out} than "
                          "process 0: every process reads the run folder, so it must be on a filesystem they share "
                          "(or copied to each host)")


def prepare_run_dir(out: str | Path, config: dict, resume_run: bool, normalise: Callable[[dict], dict] | None = None) -> Path:
    """Start a run folder holding `config.json`, or check that its run has `config` (the stored one `normalise`d);
    ConfigError naming the differing top-level keys, or for any run without `resume_run`. In a multi-process
    run every process calls it: all check the same folder (`require_same_run_folder`), then process 0 writes."""
    out = Path(out)
    require_same_run_folder(out)
    config_path = out / "config.json"
    wanted = jsonable(config)
    if config_path.exists():
        if not resume_run:
            raise ConfigError(f"{out} already holds a run; pass --resume to continue it or choose another --out")
        stored = _read_config(config_path)
        if normalise is not None:
            stored = jsonable(normalise(stored))
        changed = sorted(key for key in set(stored) | set(wanted) if stored.get(key) != wanted.get(key))
        if changed:
            raise ConfigError(f"{out} was started with a different configuration (differs in: {', '.join(changed)})")
    else:
        if jax.process_count() > 1:
            multihost_utils.sync_global_devices("run folder checked")  # by every process, before process 0 writes
        if jax.process_index() == 0:
            out.mkdir(parents=True, exist_ok=True)
            write_json(config_path, wanted)
    return out


def elite_arrays(repertoire: Repertoire, prefix: str = "") -> dict[str, np.ndarray]:
    """The filled rows of a Repertoire as flat arrays `<prefix>slots/genotypes/descriptors/fitnesses/extra_*`."""
    rows = np.flatnonzero(np.asarray(repertoire.filled))
    out = {"slots": rows.astype(np.int32), "genotypes": np.asarray(repertoire.genotypes)[rows],
           "descriptors": np.asarray(repertoire.descriptors)[rows], "fitnesses": np.asarray(repertoire.fitnesses)[rows],
           **{f"extra_{name}": np.asarray(value)[rows] for name, value in repertoire.extras.items()}}
    return {f"{prefix}{name}": value for name, value in out.items()}


def rebuild_repertoire(path, arrays: dict, prefix: str, capacity: int, genes: int, dims: int, extras: dict,
                       low: tuple[float, ...] | None = None, high: tuple[float, ...] | None = None) -> Repertoire:
    """Inverse of `elite_arrays`: a fixed-size Repertoire. extras: {name: (shape without rows, numpy dtype)};
    low / high: descriptor bounds (None: [0, 1]). CheckpointError for a missing or wrong-shaped array,
    non-finite values, genotypes or descriptors out of bounds, or slots not unique indices below `capacity`."""
    want = {"slots": ((), np.int32), "genotypes": ((genes,), np.float32), "descriptors": ((dims,), np.float32),
            "fitnesses": ((), np.float32), **{f"extra_{name}": spec for name, spec in extras.items()}}
    columns, rows = {}, None
    for name, (shape, dtype) in want.items():
        key = f"{prefix}{name}"
        if key not in arrays:
            raise CheckpointError(f"{path}: not a complete repertoire file: missing {key!r}")
        value = arrays[key]
        if rows is None:
            rows = value.shape[0] if value.ndim else -1
        if value.dtype != dtype or value.shape != (rows, *shape):
            raise CheckpointError(f"{path}: {key} has shape {value.shape} and dtype {value.dtype}, "
                                  f"expected {(rows, *shape)} {np.dtype(dtype)}")
        if value.dtype.kind == "f" and not np.isfinite(value).all():
            raise CheckpointError(f"{path}: {key} holds NaN or inf values")
        columns[name] = value
    label = prefix.rstrip("_") or "repertoire"
    slots = columns["slots"]
    if rows > capacity or (rows and (slots.min() < 0 or slots.max() >= capacity or len(np.unique(slots)) != rows)):
        raise CheckpointError(f"{path}: {label} slots are not unique indices below the capacity {capacity}")
    if ((columns["genotypes"] < 0) | (columns["genotypes"] > 1)).any():
        raise CheckpointError(f"{path}: {label} genotypes outside [0, 1]")
    low = np.zeros(dims, np.float32) if low is None else np.asarray(low, np.float32)
    high = np.ones(dims, np.float32) if high is None else np.asarray(high, np.float32)
    if ((columns["descriptors"] < low) | (columns["descriptors"] > high)).any():
        bounds = "[0, 1]" if (low == 0).all() and (high == 1).all() else f"[{low.tolist()}, {high.tolist()}]"
        raise CheckpointError(f"{path}: {label} descriptors outside {bounds}")

    def scatter(values, fill):
        store = np.full((capacity, *values.shape[1:]), fill, values.dtype)
        store[slots] = values
        return jax.device_put(store)  # jnp.asarray would compile a program per shape

    return Repertoire(genotypes=scatter(columns["genotypes"], 0), descriptors=scatter(columns["descriptors"], 0),
                      fitnesses=scatter(columns["fitnesses"], EMPTY_FITNESS), filled=scatter(np.ones(rows, bool), 0),
                      extras={name: scatter(columns[f"extra_{name}"], 0) for name in extras})
