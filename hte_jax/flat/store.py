"""Flat repertoire files: R repertoires (one per damage) in one compressed `.npz`, checked on load.

Only elites are stored, each under its grid cell; the header holds the task and the damage
names. Each repertoire is read by the task's spec (`task.flat_spec`, `qd.store.rebuild_elites`). `load_flat` rebuilds fixed-size device repertoires with a leading (R,) axis and raises
`CheckpointError` naming any problem (wrong kind, missing or wrong-shaped arrays, non-finite
values, elites outside the cells of their descriptors, unknown damages).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from hte_jax.errors import ConfigError
from hte_jax.flat.task import FlatTask, flat_spec
from hte_jax.qd.io import CheckpointError, elite_arrays, read_checkpoint, save_checkpoint
from hte_jax.qd.repertoire import Repertoire
from hte_jax.qd.store import rebuild_elites
from hte_jax.sim.damage import damage_masks
from hte_jax.sim.robot import assets_dir

KIND = "hte_jax.flat"
KIND_VERSION = 1
# trained with the gpu preset by experiments.train_flat
SHIPPED = {"2d": "flat_gpu/flat2d.npz", "8d": "flat_gpu/flat8d.npz", "aprol": "flat_gpu/aprol.npz"}


def shipped_flat_path(variant: str) -> Path:
    if variant not in SHIPPED:
        raise ConfigError(f"unknown flat variant {variant!r}; choose one of {sorted(SHIPPED)}")
    return assets_dir() / SHIPPED[variant]


@dataclasses.dataclass(frozen=True)
class FlatRepertoires:
    """R flat repertoires of one task, repertoire r trained on damage `damages[r]`.

    repertoire: Repertoire with a leading (R,) axis: genotypes (R, C, 36), descriptors (R, C, D),
    fitnesses (R, C), filled (R, C), extras arrival_yaw (R, C), contact_fraction (R, C, 6).
    """

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
    arrays = {}
    for index in range(len(flat)):
        arrays.update(elite_arrays(flat[index], _prefix(index)))
    header = {
        "kind": KIND,
        "kind_version": KIND_VERSION,
        "task": dataclasses.asdict(flat.task),
        "damages": list(flat.damages),
        **(metadata or {}),
    }
    save_checkpoint(path, arrays, header, compress=True)


def load_flat(path: str | Path) -> tuple[FlatRepertoires, dict]:
    """Read a flat repertoire file: (FlatRepertoires on device, the header metadata)."""
    arrays, header = read_checkpoint(path)
    meta = header.get("metadata", {})
    if meta.get("kind") != KIND:
        raise CheckpointError(f"{path}: not a flat repertoire file (kind {meta.get('kind')!r})")
    if meta.get("kind_version") != KIND_VERSION:
        raise CheckpointError(f"{path}: flat repertoire file version {meta.get('kind_version')!r} is not supported")
    try:
        task = FlatTask(**meta["task"])
        damages = tuple(str(name) for name in meta["damages"])
        damage_masks(damages)
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(f"{path}: bad flat repertoire header: {error}") from None
    if not damages:
        raise CheckpointError(f"{path}: holds no repertoire")
    spec = flat_spec(task)
    repertoires = [
        rebuild_elites(path, arrays, spec, _prefix(index), label=f"repertoire {index} ({damages[index]})")
        for index in range(len(damages))
    ]
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *repertoires)
    return FlatRepertoires(task=task, damages=damages, repertoire=stacked), meta
