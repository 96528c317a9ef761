"""Figures of a trained HBR: one map per layer, the contact patterns, and training curves."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hte_jax.hbr.analysis import pattern_histogram  # noqa: E402
from hte_jax.hbr.execution import HBR  # noqa: E402
from hte_jax.hbr.top import TopTask  # noqa: E402
from hte_jax.qd.plots import grid_projection, plot_metrics  # noqa: E402


def _save(fig, path):
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def _elites(repertoire):
    filled = np.asarray(repertoire.filled)
    return np.asarray(repertoire.descriptors)[filled], np.asarray(repertoire.fitnesses)[filled]


def plot_top(hbr: HBR, task: TopTask, path):
    """Top layer: final x-y position (metres) of every skill, coloured by fitness."""
    image = grid_projection(task.grid(), hbr.top)
    fig, ax = plt.subplots(figsize=(6, 5))
    e = task.extent
    mesh = ax.imshow(image.T, origin="lower", extent=(-e, e, -e, e), cmap="viridis", vmin=-np.pi / 2, vmax=0)
    fig.colorbar(mesh, ax=ax, label="fitness (minus angle error, rad)")
    filled = int(np.isfinite(image).sum())
    mean = float(np.nanmean(image)) if filled else float("nan")
    ax.set(xlabel="final x (m)", ylabel="final y (m)",
           title=f"top layer: {filled} of {image.size} cells, mean fitness {mean:.3f}")
    _save(fig, path)


def plot_middle(hbr: HBR, path):
    """Middle layer: x-y displacement per second coloured by yaw, and elites per contact pattern."""
    desc, _ = _elites(hbr.middle)
    task = hbr.middle_task
    motion = np.asarray(task.denormalise(desc[:, :3])) if len(desc) else np.zeros((0, 3))
    histogram = pattern_histogram(hbr)
    fig, (ax_xy, ax_pat) = plt.subplots(1, 2, figsize=(14, 5), gridspec_kw={"width_ratios": [1, 1.6]}, layout="constrained")
    points = ax_xy.scatter(motion[:, 0], motion[:, 1], c=motion[:, 2], s=2, cmap="twilight_shifted",
                           vmin=-task.max_turn, vmax=task.max_turn)
    fig.colorbar(points, ax=ax_xy, label="yaw (rad / s)")
    ax_xy.set_xlim(-task.max_step, task.max_step)
    ax_xy.set_ylim(-task.max_step, task.max_step)
    ax_xy.set_aspect("equal")
    ax_xy.set_xlabel("x (m / s)")
    ax_xy.set_ylabel("y (m / s)")
    ax_xy.set_title(f"middle layer: {len(desc)} body motions")
    ax_pat.bar(np.arange(histogram.size), histogram, color="tab:blue")
    ax_pat.set_yscale("log" if histogram.max(initial=0) > 50 else "linear")
    ax_pat.set_xlabel("contact pattern (leg 0 = most significant bit; 63 = all feet down)")
    ax_pat.set_ylabel("elites")
    ax_pat.set_title(f"{int((histogram > 0).sum())} distinct contact patterns")
    _save(fig, path)


def plot_bottom(hbr: HBR, path):
    """Bottom layer: swing vs height for each duty level, coloured by fitness."""
    desc, fit = _elites(hbr.bottom)
    duty = np.round(desc[:, 2], 4)
    levels = np.unique(duty) if len(desc) else np.zeros(1)
    fig, axes = plt.subplots(1, len(levels), figsize=(4 * len(levels), 4), squeeze=False)
    for ax, level in zip(axes[0], levels):
        rows = duty == level
        points = ax.scatter(desc[rows, 0], desc[rows, 1], c=fit[rows], s=3, cmap="viridis")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_xlabel("swing (normalised)")
        ax.set_ylabel("height (normalised)" if ax is axes[0][0] else "")
        ax.set_title(f"duty level {level:.2f}: {int(rows.sum())}")
    if len(desc):
        fig.colorbar(points, ax=axes[0].tolist(), label="fitness (minus activation)")
    fig.suptitle(f"bottom layer: {len(desc)} leg primitives")
    _save(fig, path)


def plot_hbr(hbr: HBR, task: TopTask, run_dir, plot_dir):
    """All figures of a training run into plot_dir (metric curves read from run_dir/<layer>/metrics.csv)."""
    plot_dir = Path(plot_dir)
    plot_top(hbr, task, plot_dir / "top_xy_fitness.png")
    plot_middle(hbr, plot_dir / "middle_xy_yaw_patterns.png")
    plot_bottom(hbr, plot_dir / "bottom_projections.png")
    for layer in ("bottom", "middle", "top"):
        log = Path(run_dir) / layer / "metrics.csv"
        if log.exists():
            fig = plot_metrics(log, title=f"{layer} layer", path=plot_dir / f"{layer}_metrics.png")
            plt.close(fig)
