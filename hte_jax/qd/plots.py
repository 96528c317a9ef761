"""Matplotlib figures a QD researcher looks at: repertoire maps and metric curves.

All functions return the matplotlib Figure and, given `path`, save a PNG there.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display needed
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hte_jax.qd.grid import Grid  # noqa: E402
from hte_jax.qd.metrics import MetricsLog  # noqa: E402
from hte_jax.qd.repertoire import Repertoire  # noqa: E402


def grid_projection(grid: Grid, repertoire: Repertoire, dims: tuple[int, int] = (0, 1)) -> np.ndarray:
    """(bins[dims[0]], bins[dims[1]]) best fitness over the other dimensions; NaN where empty."""
    fitness = np.where(np.asarray(repertoire.filled), np.asarray(repertoire.fitnesses, np.float64), -np.inf)
    cube = fitness.reshape(grid.bins)
    others = tuple(d for d in range(len(grid.bins)) if d not in dims)
    best = cube.max(axis=others) if others else cube
    if dims[0] > dims[1]:
        best = best.T
    return np.where(np.isfinite(best), best, np.nan)


def _save(fig, path):
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=120, bbox_inches="tight")
    return fig


def plot_grid(
    grid: Grid,
    repertoire: Repertoire,
    dims: tuple[int, int] = (0, 1),
    *,
    labels: tuple[str, str] = ("x", "y"),
    title: str = "",
    vmin: float | None = None,
    vmax: float | None = None,
    path: str | Path | None = None,
):
    """Heatmap of a grid repertoire coloured by fitness (the paper's Fig. 7 style).

    Grids of more than two dimensions are projected onto `dims`, keeping the best elite.
    """
    image = grid_projection(grid, repertoire, dims)
    extent = (grid.low[dims[0]], grid.high[dims[0]], grid.low[dims[1]], grid.high[dims[1]])
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    mesh = ax.imshow(image.T, origin="lower", extent=extent, aspect="auto", cmap="viridis", vmin=vmin, vmax=vmax)
    fig.colorbar(mesh, ax=ax, label="fitness")
    filled = int(np.isfinite(image).sum())
    ax.set(xlabel=labels[0], ylabel=labels[1], title=title or f"{filled} cells filled")
    return _save(fig, path)


def plot_metrics(log_path: str | Path, *, title: str = "", path: str | Path | None = None):
    """Coverage, QD score and max / mean fitness against evaluations, from a metrics CSV."""
    rows = MetricsLog(log_path).read()
    evals = np.array([float(r["evaluations"]) for r in rows])

    def column(name):
        return np.array([float(r[name]) for r in rows])

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    axes[0].plot(evals, column("coverage"))
    axes[0].set(ylabel="coverage")
    axes[1].plot(evals, column("qd_score"))
    axes[1].set(ylabel="QD score")
    axes[2].plot(evals, column("max_fitness"), label="max")
    axes[2].plot(evals, column("mean_fitness"), label="mean")
    axes[2].set(ylabel="fitness")
    axes[2].legend()
    for ax in axes:
        ax.set_xlabel("evaluations")
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)
