"""Flat repertoire files: R repertoires (one per damage) in one compressed `.npz`, only elites, each under
its grid cell, with the task and damage names in the header; `load_flat` checks everything."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import numpy as np

from hte_jax import sharding
from hte_jax.errors import lookup
from hte_jax.flat.task import FlatTask, flat_spec
from hte_jax.qd.io import CheckpointError, elite_arrays, save_checkpoint
from hte_jax.qd.repertoire import Repertoire
from hte_jax.qd.store import read_kind, rebuild_elites
from hte_jax.sim.damage import damage_masks
from hte_jax.sim.robot import assets_dir

KIND = "hte_jax.flat"
KIND_VERSION = 1
# trained with the gpu preset by experiments.train_flat
SHIPPED = {"2d": "flat_gpu/flat2d.npz", "8d": "flat_gpu/flat8d.npz", "aprol": "flat_gpu/aprol.npz"}


def shipped_flat_path(variant: str) -> Path:
    return assets_dir() / lookup("flat variant", variant, SHIPPED)


@dataclasses.dataclass(frozen=True)
class FlatRepertoires:
    """R flat repertoires of one task, repertoire r trained on damage `damages[r]`; repertoire: genotypes
    (R, C, 36), descriptors (R, C, D), fitnesses, filled, extras arrival_yaw (R, C), contact_fraction (R, C, 6)."""

    task: FlatTask
    damages: tuple[str, ...]
    repertoire: Repertoire

    def __len__(self) -> int:
        return len(self.damages)

    def __getitem__(self, which: int | str) -> Repertoire:
        """One repertoire, by index or damage name."""
        index = self.damages.index(which) if isinstance(which, str) else which
        return jax.tree.map(lambda x: x[index], self.repertoire)

    @property
    def damage_masks(self) -> np.ndarray:
        """(R, 6) bool masks of the damages."""
        return damage_masks(self.damages)


def _prefix(index: int) -> str:
    return f"r{index:02d}_"


def save_flat(path: str | Path, flat: FlatRepertoires, metadata: dict | None = None) -> None:
    """Atomically write the repertoires (compressed) with their task, damages and JSON-able `metadata`."""
    arrays = {key: value for r in range(len(flat)) for key, value in elite_arrays(flat[r], _prefix(r)).items()}
    header = {"kind": KIND, "kind_version": KIND_VERSION, "task": dataclasses.asdict(flat.task),
              "damages": list(flat.damages), **(metadata or {})}
    save_checkpoint(path, arrays, header, compress=True)


def load_flat(path: str | Path) -> tuple[FlatRepertoires, dict]:
    """Read a flat repertoire file: (FlatRepertoires on device, the header metadata)."""
    arrays, meta = read_kind(path, KIND, KIND_VERSION, "flat repertoire")
    try:
        task = FlatTask(**meta["task"])
        damages = tuple(str(name) for name in meta["damages"])
        damage_masks(damages)
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(f"{path}: bad flat repertoire header: {error}") from None
    if not damages:
        raise CheckpointError(f"{path}: holds no repertoire")
    repertoires = [rebuild_elites(path, arrays, flat_spec(task), _prefix(index), label=f"repertoire {index} ({name})")
                   for index, name in enumerate(damages)]
    return FlatRepertoires(task=task, damages=damages, repertoire=sharding.put_stacked(repertoires)), meta
