"""HBR files: the three layers' elites in one compressed `.npz` (archive slots a prefix, so middle indices
stay valid; top elites in their cells), with the tasks and capacities in the header; checked on load."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import jax
import numpy as np

from hte_jax.errors import ConfigError
from hte_jax.hbr.bottom import bottom_spec
from hte_jax.hbr.composition import StepModel
from hte_jax.hbr.hierarchy import HBR
from hte_jax.hbr.middle import MiddleTask, elite_controllers, middle_spec
from hte_jax.hbr.spare import with_spare
from hte_jax.hbr.top import TopTask, top_spec
from hte_jax.qd.io import CheckpointError, elite_arrays, read_checkpoint, save_checkpoint
from hte_jax.qd.repertoire import Repertoire
from hte_jax.qd.store import read_kind, rebuild_elites
from hte_jax.qd.task_spec import TaskSpec
from hte_jax.sim.robot import assets_dir

LAYERS = ("bottom", "middle", "top")
KIND = "hte_jax.hbr"
KIND_VERSION = 1
SHIPPED = "hbr_gpu/hbr.npz"  # trained with the gpu preset by experiments.train_hbr
SPARE_KIND = "hte_jax.hbr.spare"
SPARE_FILE = "spare.npz"  # beside an hbr.npz: its spare archive (`spare.with_spare`), used when present


def shipped_hbr_path() -> Path:
    """The HBR shipped in assets/ (trained by this code with `--preset gpu`)."""
    return assets_dir() / SHIPPED


def layer_specs(capacity: dict[str, int], top_task: TopTask) -> dict[str, TaskSpec]:
    """The layers' task specs at capacities {"bottom": Cb, "middle": Cm} (distance thresholds are not stored)."""
    return {"bottom": bottom_spec(capacity["bottom"]), "middle": middle_spec(capacity["middle"]),
            "top": top_spec(top_task)}


def save_hbr(path: str | Path, hbr: HBR, top_task: TopTask | None = None, metadata: dict | None = None) -> None:
    """Atomically write `hbr` (compressed) with its tasks and any extra JSON-able `metadata`.
    top_task: None writes `hbr.top_task`; a given one must equal it."""
    if top_task is not None and top_task != hbr.top_task:
        raise ConfigError(f"save_hbr: top_task {top_task} is not the HBR's {hbr.top_task}")
    arrays = {key: value for layer in LAYERS for key, value in elite_arrays(getattr(hbr, layer), f"{layer}_").items()}
    arrays.update(_step_arrays(hbr.middle, hbr.step_model, "middle_"))
    header = {"kind": KIND, "kind_version": KIND_VERSION,
              "capacity": {layer: getattr(hbr, layer).capacity for layer in LAYERS},
              "middle_task": dataclasses.asdict(hbr.middle_task), "top_task": dataclasses.asdict(hbr.top_task),
              **(metadata or {})}
    save_checkpoint(path, arrays, header, compress=True)


def load_hbr(path: str | Path | None = None) -> tuple[HBR, TopTask, dict]:
    """Read an HBR file (default: the shipped one): (HBR on device, its TopTask, the header metadata)."""
    path = shipped_hbr_path() if path is None else path
    arrays, meta = read_kind(path, KIND, KIND_VERSION, "HBR", article="an")
    try:
        middle_task = MiddleTask(**meta["middle_task"])
        top_task = TopTask(**meta["top_task"])
        capacity = {layer: int(meta["capacity"][layer]) for layer in LAYERS}
        specs = layer_specs(capacity, top_task)
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(f"{path}: bad HBR header: {error}") from None
    if capacity["top"] != specs["top"].capacity:
        raise CheckpointError(f"{path}: top capacity {capacity['top']} does not match a {top_task.bins}^2 grid")
    layers = {layer: rebuild_elites(path, arrays, specs[layer], f"{layer}_") for layer in LAYERS}
    middle_count = int(np.asarray(layers["middle"].filled).sum())
    used = np.asarray(arrays["top_extra_middle_indices"])
    if used.size and (used.min() < 0 or used.max() >= middle_count):
        raise CheckpointError(f"{path}: top elites refer to middle elites that are not in the file")
    hbr = HBR.build(layers["bottom"], layers["middle"], layers["top"], middle_task,
                    _step_model(path, arrays, middle_count, capacity["middle"]), top_task)
    return hbr, top_task, meta


def _step_arrays(middle: Repertoire, steps: StepModel | None, prefix: str) -> dict:
    """The stored arrays of a step model of the archive `middle` (its filled prefix); none without one."""
    if steps is None:
        return {}
    count = int(np.asarray(middle.filled).sum())
    return {f"{prefix}step_mean": np.asarray(steps.steps, np.float32)[:count],
            f"{prefix}step_spread": np.asarray(steps.spread, np.float32)[:count]}


def _step_model(path, arrays, count: int, capacity: int, prefix: str = "middle_") -> StepModel | None:
    """The measured step model (`composition.measure_steps`) if the file has one, padded to capacity."""
    mean_key, spread_key = f"{prefix}step_mean", f"{prefix}step_spread"
    if mean_key not in arrays and spread_key not in arrays:
        return None
    for key, shape in {mean_key: (count, 3), spread_key: (count,)}.items():
        value = arrays.get(key)
        if value is None or value.shape != shape or value.dtype != np.float32:
            got = "missing" if value is None else f"shape {value.shape} {value.dtype}"
            raise CheckpointError(f"{path}: {key} is {got}, expected {shape} float32")
    steps, spread = arrays[mean_key], arrays[spread_key]
    if not np.isfinite(steps).all() or np.isnan(spread).any() or (spread < 0).any():
        raise CheckpointError(f"{path}: the measured step model has non-finite steps or negative spreads")
    pad = capacity - count
    return StepModel(steps=jax.device_put(np.pad(steps, ((0, pad), (0, 0)))),
                     spread=jax.device_put(np.pad(spread, (0, pad), constant_values=np.inf)))


def bottom_fingerprint(hbr: HBR) -> str:
    """A short digest of the HBR's bottom layer: a spare archive's genotypes index it."""
    return hashlib.sha256(np.asarray(hbr.bottom.genotypes).tobytes()).hexdigest()[:16]


def save_spare(path: str | Path, hbr: HBR, spare: Repertoire, steps: StepModel | None, l: float,
               metadata: dict | None = None) -> None:
    """Atomically write a spare archive trained on `hbr`'s bottom layer (tied to it by its fingerprint)."""
    arrays = {**elite_arrays(spare, "spare_"), **_step_arrays(spare, steps, "spare_")}
    header = {"kind": SPARE_KIND, "kind_version": KIND_VERSION, "capacity": spare.capacity, "l": l,
              "bottom": bottom_fingerprint(hbr), **(metadata or {})}
    save_checkpoint(path, arrays, header, compress=True)


def load_spare(path: str | Path, hbr: HBR) -> HBR:
    """`hbr` with the spare archive of `path` appended (`spare.with_spare`): a `save_spare` file trained on
    this HBR's bottom layer, or another HBR file (its middle layer joins with its own controllers)."""
    arrays, header = read_checkpoint(path)
    meta = header.get("metadata", {})
    if meta.get("kind") == KIND:
        other, _, _ = load_hbr(path)
        return with_spare(hbr, other.middle, other.middle_params, other.step_model)
    if meta.get("kind") != SPARE_KIND:
        raise CheckpointError(f"{path}: neither a spare archive nor an HBR file (kind {meta.get('kind')!r})")
    if meta.get("bottom") != bottom_fingerprint(hbr):
        raise CheckpointError(f"{path}: the spare archive was trained on another HBR's bottom layer")
    try:
        capacity, l = int(meta["capacity"]), float(meta["l"])
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(f"{path}: bad spare header: {error}") from None
    spare = rebuild_elites(path, arrays, middle_spec(capacity, l), "spare_")
    steps = _step_model(path, arrays, int(np.asarray(spare.filled).sum()), capacity, "spare_")
    return with_spare(hbr, spare, elite_controllers(hbr.bottom, spare.genotypes, spare.filled), steps)


def spare_beside(hbr_path: str | Path | None) -> Path | None:
    """The spare archive file beside an HBR file (default: the shipped one), or None."""
    path = (shipped_hbr_path() if hbr_path is None else Path(hbr_path)).parent / SPARE_FILE
    return path if path.is_file() else None
