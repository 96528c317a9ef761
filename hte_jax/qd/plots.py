"""Matplotlib views of QD runs: grid projections and metric curves, and `save_figure` (PNG) for every figure."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display needed
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hte_jax.qd.grid import Grid  # noqa: E402
from hte_jax.qd.metrics import MetricsLog  # noqa: E402
from hte_jax.qd.repertoire import Repertoire  # noqa: E402


def save_figure(fig, path) -> None:
    """Write `fig` as a PNG at `path` (folders made) and close it."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def grid_projection(grid: Grid, repertoire: Repertoire, dims: tuple[int, int] = (0, 1)) -> np.ndarray:
    """(bins[dims[0]], bins[dims[1]]) best fitness over the other dimensions; NaN where empty."""
    fitness = np.where(np.asarray(repertoire.filled), np.asarray(repertoire.fitnesses, np.float64), -np.inf)
    cube = fitness.reshape(grid.bins)
    others = tuple(d for d in range(len(grid.bins)) if d not in dims)
    best = cube.max(axis=others) if others else cube
    if dims[0] > dims[1]:
        best = best.T
    return np.where(np.isfinite(best), best, np.nan)


def plot_metrics(log_path: str | Path, path: str | Path, *, title: str = "") -> None:
    """Coverage, QD score and max / mean fitness against evaluations, from a metrics CSV, saved at `path`."""
    rows = MetricsLog(log_path).read()

    def column(name):
        return np.array([float(r[name]) for r in rows])

    evals = column("evaluations")
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
    save_figure(fig, path)
