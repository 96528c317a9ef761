"""Figures of trained flat repertoires: x-y maps (one per damage for APROL), contact patterns, curves."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hte_jax.flat.store import FlatRepertoires  # noqa: E402
from hte_jax.hbr.middle import NUM_PATTERNS, pattern_code  # noqa: E402
from hte_jax.hbr.plots import draw_pattern_counts, draw_xy_map, xy_title  # noqa: E402
from hte_jax.qd.plots import grid_projection, plot_metrics, save_figure  # noqa: E402


def xy_image(flat: FlatRepertoires, index: int) -> np.ndarray:
    """(bins, bins) best fitness per x-y cell of repertoire `index` (8-D projected), NaN where empty."""
    return grid_projection(flat.task.grid(), flat[index], (0, 1))


def contact_pattern_counts(flat: FlatRepertoires, index: int) -> np.ndarray:
    """(64,) elites per contact pattern of an 8-D repertoire (leg 0 = most significant bit)."""
    rep = flat[index]
    codes = pattern_code(np.asarray(rep.descriptors)[np.asarray(rep.filled), 2:])
    return np.bincount(np.asarray(codes), minlength=NUM_PATTERNS)


def plot_flat(flat: FlatRepertoires, metrics_csv, plot_dir):
    """All figures of a training run into plot_dir."""
    plot_dir = Path(plot_dir)
    extent = flat.task.extent
    if len(flat) == 1:
        image = xy_image(flat, 0)
        fig, ax = plt.subplots(figsize=(6, 5))
        draw_xy_map(fig, ax, image, extent, xy_title(f"flat {flat.task.descriptor}", image))
        save_figure(fig, plot_dir / "xy_fitness.png")
    else:
        cols = 7
        rows = -(-len(flat) // cols)
        fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols, 2.6 * rows), squeeze=False, layout="constrained")
        for ax in axes.flat[len(flat):]:
            ax.axis("off")
        for index, name in enumerate(flat.damages):
            image = xy_image(flat, index)
            mesh = draw_xy_map(fig, axes.flat[index], image, extent, f"{name}: {int(np.isfinite(image).sum())}",
                               colorbar=False)
            axes.flat[index].set(xlabel="", ylabel="")
        fig.colorbar(mesh, ax=axes, label="fitness (minus angle error, rad)", shrink=0.6)
        fig.suptitle("one 2-D repertoire per damage: cells filled")
        save_figure(fig, plot_dir / "xy_fitness_per_damage.png")
    if flat.task.descriptor == "8d":
        fig, ax = plt.subplots(figsize=(10, 4))
        draw_pattern_counts(ax, contact_pattern_counts(flat, 0), "flat 8d: ")
        save_figure(fig, plot_dir / "contact_patterns.png")
    if Path(metrics_csv).exists():
        plot_metrics(metrics_csv, plot_dir / "metrics.png", title=f"flat {flat.task.descriptor} ({len(flat)} repertoires)")
