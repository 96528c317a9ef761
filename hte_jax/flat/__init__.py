"""Flat baselines: repertoires of the 36-parameter controller run for 3 s (2-D, 8-D, APROL's 21)."""

from hte_jax.flat.comparison import PAPER_TABLE2, aggregate, file_statistics, markdown_table
from hte_jax.flat.store import FlatRepertoires, load_flat, save_flat, shipped_flat_path
from hte_jax.flat.task import FlatTask, evaluate_flat, flat_spec
from hte_jax.flat.training import (PRESETS, VARIANTS, FlatConfig, flat_algorithm, flat_statistics, preset, train_flat,
                                   with_overrides)

__all__ = ["PAPER_TABLE2", "PRESETS", "VARIANTS", "FlatConfig", "FlatRepertoires", "FlatTask", "aggregate",
           "evaluate_flat", "file_statistics", "flat_algorithm", "flat_spec", "flat_statistics", "load_flat",
           "markdown_table", "preset", "save_flat", "shipped_flat_path", "train_flat", "with_overrides"]
