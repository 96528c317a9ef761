"""Figures of adaptation runs: mazes with trajectories, GP prediction error, actions per variant."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, Rectangle  # noqa: E402

from hte_jax.online.episode import SECONDS_PER_ACTION, Episodes  # noqa: E402
from hte_jax.online.maze import Maze  # noqa: E402
from hte_jax.qd.plots import save_figure  # noqa: E402


def draw_maze(ax, maze: Maze) -> None:
    """Obstacles, the planner's map bounds, the start (arrow) and the goal disc."""
    for x1, y1, x2, y2 in maze.obstacles:
        ax.add_patch(Rectangle((x1, y1), x2 - x1, y2 - y1, color="0.35"))
    x0, y0, x1, y1 = maze.bounds
    ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ls=":", ec="0.6"))
    ax.add_patch(Circle(maze.goal, maze.goal_radius, color="tab:green", alpha=0.35))
    sx, sy, syaw = maze.start
    ax.annotate("", xy=(sx + 0.3 * np.cos(syaw), sy + 0.3 * np.sin(syaw)), xytext=(sx, sy),
                arrowprops={"arrowstyle": "->", "color": "k"})
    boxes, pad = maze.obstacles + (maze.bounds,), 0.3
    ax.set_xlim(min(b[0] for b in boxes) - pad, max(b[2] for b in boxes) + pad)
    ax.set_ylim(min(b[1] for b in boxes) - pad, max(b[3] for b in boxes) + pad)
    ax.set(aspect="equal", xlabel="x (m)", ylabel="y (m)")


def episode_track(episodes: Episodes, index: int) -> np.ndarray:
    """(4 n + 1, 3) poses of episode `index`, one per second of its n actions."""
    taken = int(episodes.taken[index])
    return np.asarray(episodes.trajectory[index, : SECONDS_PER_ACTION * taken + 1])


def plot_episodes(path, maze: Maze, episodes: Episodes, indices, labels, title: str, plan_of: int | None = None) -> None:
    """Trajectories of the episodes `indices` (dots at action ends) and the first plan of episode `plan_of`."""
    fig, ax = plt.subplots(figsize=(6, 5.5))
    draw_maze(ax, maze)
    colours = plt.cm.viridis(np.linspace(0, 0.9, max(len(indices), 1)))
    for colour, index, label in zip(colours, indices, labels):
        track = episode_track(episodes, index)
        ax.plot(track[:, 0], track[:, 1], color=colour, lw=1.2, label=label)
        ax.plot(track[::SECONDS_PER_ACTION, 0], track[::SECONDS_PER_ACTION, 1], "o", color=colour, ms=2.5)
    if plan_of is not None:
        length = int(episodes.history.path_length[plan_of, 0])
        planned = np.asarray(episodes.history.path[plan_of, 0, :length])
        ax.plot(planned[:, 0], planned[:, 1], "--", color="tab:red", lw=1.5, marker="x", ms=4, label="first plan")
    ax.set_title(title)
    if len(indices) <= 12:
        ax.legend(fontsize=6, loc="lower left")
    save_figure(fig, path)


def plot_prediction_error(path, curves: dict[str, np.ndarray]) -> None:
    """Median and inter-quartile band of the RTE GP's prediction error (m) against the action index.
    curves: variant -> (E, L) errors, NaN after an episode's last action."""
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name, errors in curves.items():
        counts = np.isfinite(errors).sum(axis=0)
        upto = int(np.max(np.nonzero(counts)[0]) + 1) if counts.any() else 0
        if upto == 0:
            continue
        steps = np.arange(1, upto + 1)
        with np.errstate(all="ignore"):
            q25, q50, q75 = np.nanpercentile(errors[:, :upto], [25, 50, 75], axis=0)
        ax.plot(steps, q50, label=name)
        ax.fill_between(steps, q25, q75, alpha=0.2)
    ax.set(xlabel="action", ylabel="|predicted - measured| end position (m)",
           title="RTE GP prediction error (median, 25-75 %)")
    ax.legend(fontsize=7)
    save_figure(fig, path)


def plot_protocol_box(path, statistics: dict, max_actions: int, paper: dict | None = None) -> None:
    """The paper's Fig. 6 by the paper's method: per variant, a box of its replication medians with the
    nearest-data-point quartiles (whiskers: the extreme values), and the paper's quartiles as markers."""
    variants, medians = list(statistics["variants"]), statistics["medians"]
    boxes = [{"label": name, "q1": v["p25"], "med": v["p50"], "q3": v["p75"], "whislo": float(np.min(medians[name])),
              "whishi": float(np.max(medians[name])), "fliers": []} for name, v in statistics["variants"].items()]
    fig, ax = plt.subplots(figsize=(1.3 * len(variants) + 2, 4))
    ax.bxp(boxes, showfliers=False)
    for i, name in enumerate(variants, start=1):
        if paper and name in paper:
            ax.plot([i] * 3, paper[name], "_", color="tab:red", ms=18, mew=2, label="paper" if i == 1 else None)
    if paper and any(name in paper for name in variants):
        handles = [plt.Line2D([], [], color="tab:red", marker="_", ls="", ms=12, mew=2)]
        ax.legend(handles, ["paper's 25 / 50 / 75 %"], fontsize=7, loc="upper left")
    ax.axhline(max_actions, color="0.5", ls=":", lw=1)
    ax.set(ylabel="median actions per replication (paper's method)",
           title="actions to reach the goal (failures count as the cap)")
    save_figure(fig, path)


def plot_failures(path, statistics: dict) -> None:
    """The paper's Fig. 7: percentage of failed episodes per variant (hatched: the robot flipped), with the
    95 % Wilson interval of the failure rate (1 - the success rate's) where `statistics` has "success"
    (statistics.json files written before it have none)."""
    variants = list(statistics["variants"])
    v = statistics["variants"]
    failed = [v[n]["failure_percent"] for n in variants]
    flipped = [100.0 * v[n]["flipped"] / v[n]["episodes"] for n in variants]
    fig, ax = plt.subplots(figsize=(1.3 * len(variants) + 2, 3.5))
    x = np.arange(len(variants))
    error = None
    if "success" in statistics:
        bounds = np.array([[100.0 * (1.0 - hi), 100.0 * (1.0 - lo)] for lo, hi in
                           (statistics["success"][n]["pooled"]["ci95"] for n in variants)])
        error = np.abs(bounds - np.asarray(failed)[:, None]).T  # below, above the bar
    ax.bar(x, failed, color="tab:blue", label="failed (80 actions or flipped)", yerr=error, capsize=3)
    ax.bar(x, flipped, color="none", edgecolor="k", hatch="//", label="of which flipped")
    ax.set_xticks(x, variants)
    ax.set_ylabel("failed episodes (%)" if error is None else "failed episodes (%, 95 % Wilson interval)")
    ax.legend(fontsize=7)
    save_figure(fig, path)


def plot_variant_mazes(path, maze: Maze, tracks: dict[str, list[tuple[str, np.ndarray]]]) -> None:
    """One maze panel per variant with sample trajectories: tracks[variant] = [(label, (T, 3) poses)]."""
    names = list(tracks)
    columns = min(3, len(names))
    rows = -(-len(names) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 4 * rows), squeeze=False)
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    for ax, name in zip(axes.ravel(), names):
        draw_maze(ax, maze)
        colours = plt.cm.viridis(np.linspace(0, 0.9, max(len(tracks[name]), 1)))
        for colour, (label, track) in zip(colours, tracks[name]):
            ax.plot(track[:, 0], track[:, 1], color=colour, lw=1.0, label=label)
            ax.plot(track[-1, 0], track[-1, 1], "o", color=colour, ms=3)
        ax.set_title(name)
        ax.legend(fontsize=5, loc="lower left")
    save_figure(fig, path)
