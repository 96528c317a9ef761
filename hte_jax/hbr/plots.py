"""Figures of a trained HBR: one map per layer, the contact patterns, and training curves."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hte_jax.hbr.analysis import pattern_histogram  # noqa: E402
from hte_jax.hbr.hierarchy import HBR  # noqa: E402
from hte_jax.hbr.middle import pattern_bits  # noqa: E402
from hte_jax.hbr.top import TopTask  # noqa: E402
from hte_jax.qd.plots import grid_projection, plot_metrics, save_figure  # noqa: E402


def _elites(repertoire):
    filled = np.asarray(repertoire.filled)
    return np.asarray(repertoire.descriptors)[filled], np.asarray(repertoire.fitnesses)[filled]


def draw_xy_map(fig, ax, image: np.ndarray, extent: float, title: str, colorbar: bool = True):
    """A (bins, bins) x-y fitness image (NaN where empty) over [-extent, extent]^2 m on `ax`."""
    mesh = ax.imshow(image.T, origin="lower", extent=(-extent, extent, -extent, extent), cmap="viridis",
                     vmin=-np.pi / 2, vmax=0)
    if colorbar:
        fig.colorbar(mesh, ax=ax, label="fitness (minus angle error, rad)")
    ax.set(xlabel="final x (m)", ylabel="final y (m)", title=title)
    return mesh


def draw_pattern_counts(ax, counts: np.ndarray, prefix: str = ""):
    """(64,) elites per contact pattern as bars on `ax`, titled `prefix` and the number of patterns present."""
    ax.bar(np.arange(counts.size), counts, color="tab:blue")
    ax.set_yscale("log" if counts.max(initial=0) > 50 else "linear")
    ax.set(xlabel="contact pattern (leg 0 = most significant bit; 63 = all feet down)", ylabel="elites",
           title=f"{prefix}{int((counts > 0).sum())} distinct contact patterns")


def xy_title(name: str, image: np.ndarray) -> str:
    filled = int(np.isfinite(image).sum())
    mean = float(np.nanmean(image)) if filled else float("nan")
    return f"{name}: {filled} of {image.size} cells, mean fitness {mean:.3f}"


def plot_top(hbr: HBR, task: TopTask, path):
    """Top layer: final x-y position (metres) of every skill, coloured by fitness."""
    image = grid_projection(task.grid(), hbr.top)
    fig, ax = plt.subplots(figsize=(6, 5))
    draw_xy_map(fig, ax, image, task.extent, xy_title("top layer", image))
    save_figure(fig, path)


def plot_middle(hbr: HBR, path):
    """Middle layer: x-y displacement per second coloured by yaw, and elites per contact pattern."""
    desc, _ = _elites(hbr.middle)
    task = hbr.middle_task
    motion = np.asarray(task.denormalise(desc[:, :3])) if len(desc) else np.zeros((0, 3))
    fig, (ax_xy, ax_pat) = plt.subplots(1, 2, figsize=(14, 5), gridspec_kw={"width_ratios": [1, 1.6]},
                                        layout="constrained")
    points = ax_xy.scatter(motion[:, 0], motion[:, 1], c=motion[:, 2], s=2, cmap="twilight_shifted",
                           vmin=-task.max_turn, vmax=task.max_turn)
    fig.colorbar(points, ax=ax_xy, label="yaw (rad / s)")
    ax_xy.set(xlim=(-task.max_step, task.max_step), ylim=(-task.max_step, task.max_step), aspect="equal",
              xlabel="x (m / s)", ylabel="y (m / s)", title=f"middle layer: {len(desc)} body motions")
    draw_pattern_counts(ax_pat, pattern_histogram(hbr))
    save_figure(fig, path)


def plot_bottom(hbr: HBR, path):
    """Bottom layer: swing vs height for each duty level, coloured by fitness."""
    desc, fit = _elites(hbr.bottom)
    duty = np.round(desc[:, 2], 4)
    levels = np.unique(duty) if len(desc) else np.zeros(1)
    fig, axes = plt.subplots(1, len(levels), figsize=(4 * len(levels), 4), squeeze=False)
    for ax, level in zip(axes[0], levels):
        rows = duty == level
        points = ax.scatter(desc[rows, 0], desc[rows, 1], c=fit[rows], s=3, cmap="viridis")
        ylabel = "height (normalised)" if ax is axes[0][0] else ""
        ax.set(xlim=(0, 1), ylim=(0, 1), xlabel="swing (normalised)", ylabel=ylabel,
               title=f"duty level {level:.2f}: {int(rows.sum())}")
    if len(desc):
        fig.colorbar(points, ax=axes[0].tolist(), label="fitness (minus activation)")
    fig.suptitle(f"bottom layer: {len(desc)} leg primitives")
    save_figure(fig, path)


def plot_hbr(hbr: HBR, task: TopTask, run_dir, plot_dir):
    """All figures of a training run into plot_dir (metric curves read from run_dir/<layer>/metrics.csv)."""
    plot_dir = Path(plot_dir)
    plot_top(hbr, task, plot_dir / "top_xy_fitness.png")
    plot_middle(hbr, plot_dir / "middle_xy_yaw_patterns.png")
    plot_bottom(hbr, plot_dir / "bottom_projections.png")
    for layer in ("bottom", "middle", "top"):
        log = Path(run_dir) / layer / "metrics.csv"
        if log.exists():
            plot_metrics(log, plot_dir / f"{layer}_metrics.png", title=f"{layer} layer")


def plot_modulation_map(modulation, path, extent: float = 1.5, radius: float | None = None):
    """Paper Fig. 4: every skill at its final x-y, sized by its patterns that are shown and reach the cell
    (or within `radius` m), coloured by the median error of the executions showing the pattern."""
    counts = modulation.counts(radius)
    reach = "reach their cell" if radius is None else f"end within {radius:g} m"
    fig, ax = plt.subplots(figsize=(6.5, 5.5))
    size = 4 + 60 * counts["both"] / max(1, modulation.patterns.size)
    error = counts["median_error"]
    vmax = float(np.nanpercentile(error, 95)) if np.isfinite(error).any() else 1
    points = ax.scatter(*modulation.target_xy.T, s=size, c=error, marker="x", cmap="viridis_r", vmin=0, vmax=vmax)
    fig.colorbar(points, ax=ax, label="median error to the skill's final x-y (m)")
    ax.set(xlim=(-extent, extent), ylim=(-extent, extent), aspect="equal", xlabel="final x (m)", ylabel="final y (m)")
    ax.set_title(f"{modulation.slots.size} skills x {modulation.patterns.size} contact patterns: "
                 f"{counts['both'].mean():.2f} per skill show it and {reach}", fontsize=9)
    save_figure(fig, path)


def plot_modulation_grid(modulation, path, extent: float = 1.5):
    """Paper Fig. 5: per wanted pattern, the final x-y of the executions showing it (dots: legs, red = lifted)."""
    shows, error = modulation.shows_pattern, modulation.error
    count = modulation.patterns.size
    cols = int(np.ceil(np.sqrt(count)))
    rows = -(-count // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(1.9 * cols, 1.9 * rows), squeeze=False, sharex=True, sharey=True)
    vmax = float(np.nanpercentile(error[shows], 95)) if shows.any() else 1.0
    for ax in axes.flat[count:]:
        ax.axis("off")
    for index, pattern in enumerate(modulation.patterns):
        ax = axes.flat[index]
        rows_shown = shows[:, index]
        xy = modulation.final_xy[rows_shown, index]
        ax.scatter(xy[:, 0], xy[:, 1], s=1, c=error[rows_shown, index], cmap="viridis_r", vmin=0, vmax=vmax)
        bits = np.asarray(pattern_bits(pattern)).astype(bool)
        ax.scatter(0.08 + 0.09 * np.arange(bits.size), np.full(bits.size, 0.9), s=14, transform=ax.transAxes,
                   c=np.where(bits, "tab:green", "tab:red"), clip_on=False)
        ax.set_title(f"{int(pattern)}: {int(rows_shown.sum())}", fontsize=7, pad=2)
        ax.set(xlim=(-extent, extent), ylim=(-extent, extent))
        ax.tick_params(labelsize=5)
    fig.suptitle("final x-y per wanted contact pattern (dots: legs 0-5, red = not on the ground); "
                 "title: pattern, skills showing it", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
