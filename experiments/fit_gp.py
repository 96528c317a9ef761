"""Fit the RTE GP's kernel to the episodes of a maze_eval run (issue 22): a tool for researchers.

    python -m experiments.fit_gp --run runs/maze-eval
    python -m experiments.fit_gp --run runs/maze-eval --variant rte,hte --steps 400 --learning-rate 0.02

Rebuilds each HBR episode's RTE GP from its episodes_<k>.npz (the executed skills' GP inputs, the
prior outcomes of the HBR file the run used, the measured outcomes), then maximises the summed log
marginal likelihood of those GPs over the squared exponential kernel's length-scale, variance and
noise with Adam, from the online loop's kernel (`gp.RTE_KERNEL`). Prints the fitted kernel and the
log-likelihood before and after, and writes fit.json (also the likelihood trace) into the run folder;
the online loop keeps its kernel. Episodes on flat repertoires are left out. Bad input gives a
one-line error and exit status 2.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from experiments.cli import fail, input_errors, interruptible
from hte_jax.errors import ConfigError, require_int, require_number
from hte_jax.hbr.store import load_hbr
from hte_jax.online.gp import RTE_KERNEL, GPData
from hte_jax.online.gp_fit import fit_kernel
from hte_jax.online.skills import ActionSet, action_set, replayed_models
from hte_jax.online.variants import variant as variant_named
from hte_jax.qd.io import CheckpointError, read_checkpoint, write_json

BATCH_FILE = re.compile(r"episodes_(\d+)\.npz")


def batch_files(run: Path) -> list[Path]:
    """The run's episodes_<k>.npz in batch order; a ConfigError unless `run` is a maze_eval run folder."""
    if not run.is_dir():
        raise ConfigError(f"--run {run}: no such folder")
    files = sorted((p for p in run.iterdir() if BATCH_FILE.fullmatch(p.name)),
                   key=lambda p: int(BATCH_FILE.fullmatch(p.name).group(1)))
    if not (run / "config.json").is_file() or not files:
        raise ConfigError(f"--run {run}: not a maze_eval run folder (needs config.json and episodes_<k>.npz)")
    return files


def hbr_actions(repertoire: dict, cache: dict) -> ActionSet:
    """The actions (top-layer skills) of the HBR a batch ran on ("shipped" or its file)."""
    path = repertoire.get("path")
    if path not in cache:
        hbr, task, _ = load_hbr(None if path == "shipped" else path)
        cache[path] = action_set(hbr.top, task.extent)
    return cache[path]


def run_models(run: Path, variants: set[str] | None) -> tuple[GPData, dict]:
    """The rebuilt RTE GPs (E, L, ...) of the run's HBR episodes (of `variants`, None: all) with at
    least one action, and what was used and left out."""
    models, used, skipped, cache = [], {}, {"flat repertoire": 0, "not asked for": 0}, {}
    for path in batch_files(run):
        arrays, header = read_checkpoint(path)
        labels = header.get("metadata", {})
        try:
            names, repertoire = list(labels["variants"]), dict(labels["repertoire"])
            executed, observed, predicted = arrays["action"], arrays["observed"], arrays["predicted"]
        except (KeyError, TypeError, ValueError) as error:
            raise CheckpointError(f"{path}: not a maze_eval episodes file ({type(error).__name__}: {error})") from None
        if repertoire.get("kind") != "hbr":
            skipped["flat repertoire"] += len(names)
            continue
        rows = []
        for row, name in enumerate(names):
            if variants is not None and name not in variants:
                skipped["not asked for"] += 1
            elif executed[row, 0] >= 0:
                rows.append(row)
                used[name] = used.get(name, 0) + 1
        if not rows:
            continue
        actions = hbr_actions(repertoire, cache)
        if executed[rows].max() >= actions.size:
            raise CheckpointError(f"{path}: actions beyond the {actions.size} skills of {repertoire.get('path')}")
        # A fresh GP predicts the prior: the first action's recorded prediction must be its stored
        # end position (clipped as `actions.displacement_of` clips it).
        first = np.clip(np.asarray(actions.prior)[executed[rows, 0], :2], -1.5, 1.5)
        if not np.allclose(first, predicted[rows, 0, :2], atol=1e-4):
            raise CheckpointError(f"{path}: the skills of {repertoire.get('path')} are not the ones the run planned with")
        models.append(replayed_models(actions, executed[rows], observed[rows]))
    if not models:
        raise ConfigError(f"--run {run}: no HBR episode with an action to fit on")
    if len({m.mask.shape[1] for m in models}) > 1:
        raise ConfigError(f"--run {run}: batches with different max_actions")
    return jax.tree.map(lambda *parts: jnp.concatenate(parts), *models), {"episodes": used, "skipped": skipped}


@interruptible()  # Ctrl-C: `interrupted: nothing written` (fit.json is written at the end)
def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", required=True, help="a maze_eval run folder")
    p.add_argument("--variant", default="", help="comma-separated variants to fit on (default: every HBR variant)")
    p.add_argument("--steps", type=int, default=200, help="Adam steps (default 200)")
    p.add_argument("--learning-rate", type=float, default=0.05, help="Adam step size in log space (default 0.05)")
    args = p.parse_args(argv)
    run = Path(args.run)
    with input_errors() as errors:
        variants = {v.strip() for v in args.variant.split(",") if v.strip()} or None
        for name in variants or ():
            variant_named(name)  # validates the name
        require_int("--steps", args.steps)
        require_number("--learning-rate", args.learning_rate, 0.0, open_low=True)
        data, info = run_models(run, variants)
        fitted, trace = fit_kernel(data, RTE_KERNEL, steps=args.steps, learning_rate=args.learning_rate)
    if errors.failed:
        return 2
    if not np.isfinite(trace[-1]):
        return fail(f"the fit diverged (log-likelihood {trace[-1]}); try a smaller --learning-rate")
    fields = ("kind", "length_scale", "variance", "noise")
    observations = int(data.mask.sum())
    write_json(run / "fit.json", {
        "initial": {k: getattr(RTE_KERNEL, k) for k in fields}, "fitted": {k: getattr(fitted, k) for k in fields},
        "log_likelihood": {"initial": float(trace[0]), "fitted": float(trace[-1])},
        "observations": observations, **info, "steps": args.steps, "learning_rate": args.learning_rate,
        "trace": [float(t) for t in trace],
    })
    print(f"RTE kernel fitted on {data.mask.shape[0]} episodes ({observations} observations): "
          f"length {fitted.length_scale:.4g}, variance {fitted.variance:.4g}, noise {fitted.noise:.4g}; "
          f"log-likelihood {trace[0]:.2f} -> {trace[-1]:.2f}; wrote {run / 'fit.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
