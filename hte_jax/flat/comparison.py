"""Table 2 of the paper: per repertoire file its size, effective size (x-y cells filled) and the mean
fitness of its x-y projection; then mean and std over each method's seeds."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hte_jax.flat.store import load_flat
from hte_jax.hbr.store import load_hbr
from hte_jax.qd.io import CheckpointError, read_checkpoint
from hte_jax.qd.metrics import projected_statistics

# Table 2 of the paper (4e6 evaluations): mean, std.
PAPER_TABLE2 = {
    "HBR": {"size": (2980.8, 131.0), "effective_size": (2980.8, 131.0), "mean_fitness": (-0.01, 0.02)},
    "Flat-8D": {"size": (72528.0, 2809.4), "effective_size": (2531.5, 111.8), "mean_fitness": (-0.21, 0.02)},
}
COLUMNS = ("size", "effective_size", "mean_fitness", "mean_fitness_all")


def resolve(path: str | Path) -> Path:
    """A repertoire file, or the file a training run folder holds (hbr.npz or repertoires.npz)."""
    path = Path(path)
    if path.is_dir():
        for name in ("hbr.npz", "repertoires.npz"):
            if (path / name).is_file():
                return path / name
        raise CheckpointError(f"{path}: folder holds neither hbr.npz nor repertoires.npz")
    return path


def file_statistics(path: str | Path) -> dict:
    """Table 2 statistics of an HBR file (its top layer) or a one-repertoire flat file, with method and seed."""
    path = resolve(path)
    _, header = read_checkpoint(path)
    kind = header.get("metadata", {}).get("kind")
    if kind == "hte_jax.hbr":
        hbr, task, meta = load_hbr(path)
        rep, bins, label = hbr.top, task.bins, "HBR"
        evaluations = meta.get("training", {}).get("layers", {}).get("top", {}).get("evaluations")
    elif kind == "hte_jax.flat":
        flat, meta = load_flat(path)
        if len(flat) != 1:
            raise CheckpointError(f"{path}: holds {len(flat)} repertoires (APROL set?); "
                                  "Table 2 compares single repertoires")
        rep, bins, label = flat[0], flat.task.bins, f"Flat-{flat.task.descriptor.upper()}"
        evaluations = meta.get("training", {}).get("evaluations")
    else:
        raise CheckpointError(f"{path}: not an HBR or flat repertoire file (kind {kind!r})")
    stats = projected_statistics(rep.descriptors, rep.fitnesses, rep.filled, bins)
    seed = meta.get("training", {}).get("config", {}).get("seed")
    return {"method": label, "path": str(path), "evaluations": evaluations, "seed": seed, **stats}


def aggregate(rows: list[dict]) -> dict[str, dict]:
    """method -> {"n", "evaluations", column: (mean, std)} (std with ddof=1; 0 for one seed)."""
    table: dict[str, dict] = {}
    for method in dict.fromkeys(row["method"] for row in rows):
        group = [row for row in rows if row["method"] == method]
        entry: dict = {"n": len(group), "evaluations": sorted({row["evaluations"] for row in group}, key=str)}
        for column in COLUMNS:
            values = np.array([row[column] for row in group], np.float64)
            entry[column] = (float(values.mean()), float(values.std(ddof=1)) if values.size > 1 else 0.0)
        table[method] = entry
    return table


def markdown_table(table: dict[str, dict]) -> str:
    """Ours next to the paper's, one line per method."""

    def cell(pair, digits):
        return f"{pair[0]:.{digits}f} ± {pair[1]:.{digits}f}"

    lines = ["| method | seeds | evaluations | repertoire size | effective size | mean fitness (projected) "
             "| mean fitness (all elites) |", "|---|---|---|---|---|---|---|"]
    for method, entry in table.items():
        evals = ", ".join(f"{e:.3g}" if isinstance(e, (int, float)) else str(e) for e in entry["evaluations"])
        lines.append(f"| {method} (ours) | {entry['n']} | {evals} | {cell(entry['size'], 1)} "
                     f"| {cell(entry['effective_size'], 1)} | {cell(entry['mean_fitness'], 3)} "
                     f"| {cell(entry['mean_fitness_all'], 3)} |")
        if method in PAPER_TABLE2:
            paper = PAPER_TABLE2[method]
            lines.append(f"| {method} (paper) | – | 4e6 | {cell(paper['size'], 1)} "
                         f"| {cell(paper['effective_size'], 1)} | {cell(paper['mean_fitness'], 2)} | – |")
    return "\n".join(lines) + "\n"
