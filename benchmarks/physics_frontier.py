"""Speed versus fidelity of MJX solver settings, against a converged reference.

A setting is "S/L" (Newton iterations / line-search iterations), optionally followed by
"@tol=T" (RobotConfig.solver_tolerance, MuJoCo's default 1e-8) and "@dt=D" (timestep; 0.005
gives two physics steps per 10 ms control step), e.g. "2/4", "4/8@dt=0.005", "20/8@tol=1e-4".
Each setting runs in its own subprocess (a crash or timeout is an error row) and measures:

  speed     compile, then the median of --repeats timed 3 s rollouts of --batch random
            36-parameter controllers, intact (the workload of benchmarks/batch_size.py);
  fidelity  one fixed workload, 3 s each from the standing state of that setting's robot:
            --fidelity-size random controllers intact ("random-intact") and the same ones with
            the paper's seven damages in turn ("random-damaged", damage model "raised");
            --skills shipped Flat-2D elites ("flat-2d") and shipped HBR top skills run by
            execute_skill, intact ("hbr-intact") and with --skill-damage ("hbr-<damage>").
            Final planar pose (x, y, yaw) in the start frame, validity, and on the rollout
            workloads the deepest foot penetration (foot radius minus the lowest foot-sphere
            centre over the 3 s).

Every setting is compared with --reference (run the same way): final-position error median /
p90 / max (cm) and yaw error over rollouts valid in both, valid fraction, "new invalid"
(valid in the reference, invalid here) and penetration p99 / max (mm) of those rollouts, per
workload and pooled. The reference is run twice more: with doubled iterations (is it
converged?) and from initial joint angles perturbed by 1e-6 rad (the noise floor: how far
float-level differences grow in 3 s). The summary names the fastest setting within --budget (pooled: median and p90
error in cm, new invalid rollouts in % of the reference's valid ones, max penetration in mm over
the reference's). --merge adds the rows of earlier runs of the same workload.

--repertoires re-simulates the shipped repertoires as they were trained (all HBR top skills by
evaluate_top, all Flat-2D elites by evaluate_flat, intact, from the standing state) under each
given setting and compares the final (x, y) with the stored descriptors: error median / p90 /
max and the fraction of elites still in their own grid cell.

Tolerance under vmap (MJX 3.17, mjx/_src/solver.py): the Newton loop is a lax.while_loop that
stops a rollout once its cost improvement or gradient (scaled by the mass-matrix trace) is
below opt.tolerance; batched by vmap, the loop runs until the slowest rollout of the batch has
stopped, so a tolerance saves time only when every rollout of the batch converges before the
iteration cap. The line search is a fixed-length scan whose per-rollout early exit (through
ls_tolerance) is a lax.cond, i.e. a select under vmap: it always costs ls_iterations
evaluations, and ls_tolerance can change results but never time.

    python benchmarks/physics_frontier.py                          # CPU: the default grid, about 1 h on 2 cores
    python benchmarks/physics_frontier.py --settings 4/8,2/4 --fidelity-size 64 --skills 64 --repertoires ''
    python benchmarks/physics_frontier.py --settings '' --repertoires 4/8,2/4   # repertoire check only
    python benchmarks/physics_frontier.py --batch 32768 --fidelity-size 4096   # GPU (its defaults)

Prints tables, writes JSON to benchmarks/results/ (or --out) and a speed-versus-error plot
(PNG) next to it.
"""

from __future__ import annotations

import argparse
import functools
import itertools
import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from common import earlier_result, environment, parse_setting, random_params, result_path, run_worker, setting_label
from hte_jax.flat.store import load_flat, shipped_flat_path
from hte_jax.flat.task import evaluate_flat
from hte_jax.hbr.hierarchy import execute_skill
from hte_jax.geometry import planar_pose, relative_pose
from hte_jax.hbr.store import load_hbr
from hte_jax.hbr.top import evaluate_top
from hte_jax.sim.damage import paper_damage_masks, parse_damage
from hte_jax.sim.robot import FOOT_RADIUS, NUM_LEGS, RobotConfig, load_robot, stored_solver
from hte_jax.sim.rollout import RolloutSpec, rollout, standing_state

GRID = "4/8,4/4,5/4,6/4,8/4,3/4,2/4,2/2,1/4,2/4@dt=0.005,6/4@tol=1e-4,20/4@tol=1e-4"
BUDGET = "median=1,p90=3,new_invalid=0.5,penetration=1"
BUDGET_KEYS = ("median", "p90", "new_invalid", "penetration")
BASELINE = "4/8"  # the solver setting before this benchmark (speed ratios are against it)
PERTURBATION = 1e-6  # rad added to every initial joint angle by the reference's noise-floor check


def _parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--settings", default=GRID, help="comma-separated settings ('' skips the frontier)")
    p.add_argument("--reference", default="20/20", help="the converged setting errors are measured against")
    p.add_argument("--budget", default=BUDGET,
                   help="pooled fidelity budget: median / p90 error (cm), new_invalid (%% of the reference's "
                        "valid rollouts), penetration (mm over the reference's max)")
    p.add_argument("--batch", type=int, default=None, help="speed batch (default: 256 on CPU, 32768 on GPU)")
    p.add_argument("--steps", type=int, default=300, help="control steps of the speed rollouts (300 = 3 s)")
    p.add_argument("--repeats", type=int, default=3, help="timed speed runs (median reported)")
    p.add_argument("--fidelity-size", type=int, default=None,
                   help="random controllers of the fidelity workload (default: 256 on CPU, 4096 on GPU)")
    p.add_argument("--skills", type=int, default=None,
                   help="shipped HBR skills and Flat-2D elites in it (default: 256 on CPU, 2048 on GPU; 0: none)")
    p.add_argument("--skill-damage", default="leg1", help="the damage the HBR skills also run with")
    p.add_argument("--repertoires", default=None,
                   help="settings for the shipped-repertoire check (default: 4/8 and today's default; '' skips)")
    p.add_argument("--elites", type=int, default=0, help="repertoire check: the first N elites of each (0: all)")
    p.add_argument("--hbr", type=Path, default=None, help="HBR file of the skill workload and the repertoire check (default: shipped)")
    p.add_argument("--flat", type=Path, default=None,
                   help="Flat-2D repertoire file of the skill workload and the repertoire check (default: shipped)")
    p.add_argument("--chunk", type=int, default=None, help="rollouts per call (default: 1024 on CPU, 16384 on GPU)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random controllers and skill samples")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds allowed per setting")
    p.add_argument("--reference-checks", default="doubled,perturbed",
                   help="runs checking the reference: 'doubled' (both iteration counts doubled: converged?) and "
                        f"'perturbed' (initial joint angles + {PERTURBATION:g} rad: the workload's noise floor); '' none")
    p.add_argument("--out", type=Path, default=None, help="JSON path (default: results/physics_frontier_<device>_<date>.json)")
    p.add_argument("--merge", type=Path, nargs="*", default=[],
                   help="JSON files of earlier runs on the same device, workload and reference: their rows join this run's")
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    p.add_argument("--repertoire-worker", default=None, help=argparse.SUPPRESS)
    p.add_argument("--npz", type=Path, default=None, help=argparse.SUPPRESS)
    p.add_argument("--no-speed", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--perturb", type=float, default=0.0, help=argparse.SUPPRESS)
    return p.parse_args(argv)


def _config(setting: str) -> RobotConfig:
    return RobotConfig(**parse_setting(setting))


def _doubled(setting: str) -> str:
    """The setting with both iteration counts doubled (the reference's convergence check)."""
    overrides = parse_setting(setting)
    overrides["solver_iterations"] *= 2
    overrides["ls_iterations"] *= 2
    return setting_label(RobotConfig(**overrides))


def _in_chunks(fn, arrays, chunk: int) -> list[np.ndarray]:
    """fn over row blocks of the numpy `arrays` (one program: the last block is padded with its last row)."""
    num = len(arrays[0])
    size = min(chunk, num)
    parts = []
    for start in range(0, num, size):
        block = [a[start:start + size] for a in arrays]
        pad = size - len(block[0])
        block = [np.concatenate([b, np.repeat(b[-1:], pad, axis=0)]) for b in block]
        out = [np.asarray(x) for x in fn(*block)]
        parts.append([x[:size - pad] for x in out])
    return [np.concatenate(column) for column in zip(*parts)]


@functools.partial(jax.jit, static_argnames=("spec",))
def _walk(robot, params, damage, init, spec):
    """(B, 3) final pose in the start frame, (B,) validity and (B,) deepest foot penetration."""
    result = rollout(robot, params, damage, init, spec)
    poses = planar_pose(result.base_pos, result.base_quat)
    depth = FOOT_RADIUS - result.foot_pos[..., 2].min(axis=(1, 2))
    return relative_pose(poses[:, 0], poses[:, 1]), result.valid, depth


@jax.jit
def _skill(robot, hbr, genotypes, damage, init):
    """(B, 3) final pose in the start frame and (B,) validity of HBR skills."""
    skill = execute_skill(robot, hbr, genotypes, init, damage)
    return skill.displacement, skill.valid


def _speed(config, args) -> dict:
    """Compile and time the batch_size.py rollout at --batch."""
    robot = load_robot(config)
    init = standing_state(robot)
    params = jnp.asarray(random_params(args.batch))
    damage = jnp.zeros(6, bool)
    spec = RolloutSpec(num_steps=args.steps, pose_steps=(0, args.steps), record_contacts=True)
    began = time.perf_counter()
    compiled = rollout.lower(robot, params, damage, init, spec=spec).compile()
    compile_s = time.perf_counter() - began
    jax.block_until_ready(compiled(robot, params, damage, init))  # warm-up
    times = []
    for _ in range(args.repeats):
        began = time.perf_counter()
        jax.block_until_ready(compiled(robot, params, damage, init))
        times.append(time.perf_counter() - began)
    run_s = statistics.median(times)
    return {"compile_s": compile_s, "run_s": run_s, "run_s_all": times,
            "steps_per_s": args.batch * args.steps * config.substeps / run_s}


def _fidelity(config, args) -> dict[str, np.ndarray]:
    """The fidelity workload under `config`: "<workload>/pose|valid|depth" arrays (depth NaN for skills)."""
    robot = load_robot(config)
    rng = np.random.default_rng(args.seed)
    paper = paper_damage_masks()
    conditions = np.concatenate([np.zeros((1, NUM_LEGS), bool), paper, parse_damage(args.skill_damage)[None]])
    standing = standing_state(robot, jnp.asarray(conditions))
    standing = standing.replace(qpos=standing.qpos.at[:, 7:].add(args.perturb))

    def start(rows):
        return jax.tree.map(lambda x: x[jnp.asarray(rows)], standing)

    n, k = args.fidelity_size, args.skills
    random = rng.uniform(size=(n, 36)).astype(np.float32)
    sizes = {"random-intact": n, "random-damaged": n}
    params, condition = [random, random], [np.zeros(n, int), 1 + np.arange(n) % len(paper)]
    if k:
        flat, _ = load_flat(args.flat or shipped_flat_path("2d"))
        rows = _sample(rng, flat[0].filled, k)
        sizes["flat-2d"] = len(rows)
        params.append(np.asarray(flat[0].genotypes)[rows])
        condition.append(np.zeros(len(rows), int))
    spec = RolloutSpec(num_steps=300, pose_steps=(0, 300), record_contacts=False, record_feet=True)
    out = _split(sizes, *_in_chunks(
        lambda p, c: _walk(robot, jnp.asarray(p), jnp.asarray(conditions[c]), start(c), spec),
        (np.concatenate(params), np.concatenate(condition)), args.chunk))
    if k:
        hbr, _, _ = load_hbr(args.hbr)
        genes = np.asarray(hbr.top.genotypes)[_sample(rng, hbr.top.filled, k)]
        cases = np.concatenate([np.zeros(len(genes), int), np.full(len(genes), len(conditions) - 1)])
        pose, valid = _in_chunks(
            lambda g, c: _skill(robot, hbr, jnp.asarray(g), jnp.asarray(conditions[c]), start(c)),
            (np.concatenate([genes, genes]), cases), args.chunk)
        sizes = {"hbr-intact": len(genes), f"hbr-{args.skill_damage}": len(genes)}
        out.update(_split(sizes, pose, valid, np.full(len(valid), np.nan, np.float32)))
    return out


def _sample(rng, filled, k: int) -> np.ndarray:
    """k of the filled rows (all if fewer), drawn without replacement, in row order."""
    rows = np.flatnonzero(np.asarray(filled))
    return np.sort(rng.choice(rows, min(k, len(rows)), replace=False))


def _split(sizes: dict, pose, valid, depth) -> dict[str, np.ndarray]:
    """Consecutive row blocks of the given sizes as "<workload>/pose|valid|depth" arrays."""
    out, begin = {}, 0
    for name, size in sizes.items():
        rows = slice(begin, begin + size)
        out.update({f"{name}/pose": pose[rows], f"{name}/valid": valid[rows], f"{name}/depth": depth[rows]})
        begin += size
    return out


def _worker(args) -> dict:
    config = _config(args.worker)
    row = {"setting": args.worker, "solver_iterations": config.solver_iterations, "ls_iterations": config.ls_iterations,
           "solver_tolerance": config.solver_tolerance, "timestep": config.timestep, "substeps": config.substeps,
           "impl": config.impl}
    if not args.no_speed:
        row.update(_speed(config, args))
    began = time.perf_counter()
    np.savez(args.npz, **_fidelity(config, args))
    row["fidelity_s"] = time.perf_counter() - began
    return row


def _repertoire_worker(args) -> dict:
    """Re-simulate the HBR top skills and Flat-2D elites as trained; compare with their stored descriptors."""
    config = _config(args.repertoire_worker)
    robot = load_robot(config)
    start = standing_state(robot)
    hbr, top_task, hbr_meta = load_hbr(args.hbr)
    flat, flat_meta = load_flat(args.flat or shipped_flat_path("2d"))
    trained = {"hbr-top": _trained_setting(hbr_meta), "flat-2d": _trained_setting(flat_meta)}

    @jax.jit
    def top(robot, hbr, start, genotypes):
        evaluation = evaluate_top(robot, start, top_task, hbr, None, genotypes)
        return evaluation.descriptors, evaluation.valid

    @jax.jit
    def walk(robot, start, genotypes):
        evaluation = evaluate_flat(robot, flat.task, start, jnp.zeros(NUM_LEGS, bool), None, genotypes)
        return evaluation.descriptors, evaluation.valid

    row = {"setting": args.repertoire_worker}
    for name, rep, task, evaluate in (
        ("hbr-top", hbr.top, top_task, lambda g: top(robot, hbr, start, jnp.asarray(g))),
        ("flat-2d", flat[0], flat.task.xy, lambda g: walk(robot, start, jnp.asarray(g))),
    ):
        began = time.perf_counter()
        rows = np.flatnonzero(np.asarray(rep.filled))[:args.elites or None]
        descriptors, valid = _in_chunks(evaluate, (np.asarray(rep.genotypes)[rows],), args.chunk)
        stored = np.asarray(rep.descriptors)[rows, :2]
        error = np.linalg.norm(np.asarray(task.denormalise(descriptors)) - np.asarray(task.denormalise(stored)), axis=1)
        own = task.grid().cell_matches(descriptors, rows) & valid
        row[name] = {"trained": trained[name], "elites": len(rows), "valid_fraction": float(valid.mean()), **_spread(error[valid] * 100, "cm"),
                     "in_own_cell": float(own.mean()), "wall_s": time.perf_counter() - began}
    return row


def _trained_setting(meta: dict) -> str:
    """The solver setting a stored repertoire was trained with (4/8 for files from before it was a setting)."""
    return setting_label(RobotConfig(**stored_solver(meta.get("training", {}).get("config", {}))))


def _spread(values: np.ndarray, unit: str) -> dict:
    """median / p90 / max of `values` (None when empty)."""
    if len(values) == 0:
        return {f"median_{unit}": None, f"p90_{unit}": None, f"max_{unit}": None}
    return {f"median_{unit}": float(np.median(values)), f"p90_{unit}": float(np.percentile(values, 90)),
            f"max_{unit}": float(values.max())}


def _compare(run: dict, ref: dict, prefix: str) -> dict:
    """Fidelity of one workload (`prefix` "<name>/", or "" for all pooled) against the reference."""
    def take(data, field):
        keys = [key for key in data if key.endswith("/" + field) and key.startswith(prefix)]
        return np.concatenate([data[key] for key in sorted(keys)])

    pose, valid, depth = take(run, "pose"), take(run, "valid"), take(run, "depth")
    ref_pose, ref_valid, ref_depth = take(ref, "pose"), take(ref, "valid"), take(ref, "depth")
    both = valid & ref_valid
    error = np.linalg.norm(pose[both, :2] - ref_pose[both, :2], axis=1) * 100
    yaw = np.degrees(np.abs(np.angle(np.exp(1j * (pose[both, 2] - ref_pose[both, 2])))))
    measured = both & np.isfinite(depth) & np.isfinite(ref_depth)
    penetration = depth[measured] * 1000
    row = {"rollouts": len(valid), "compared": int(both.sum()), **_spread(error, "cm"),
           "yaw_median_deg": float(np.median(yaw)) if both.any() else None,
           "yaw_p90_deg": float(np.percentile(yaw, 90)) if both.any() else None,
           "valid_fraction": float(valid.mean()), "reference_valid_fraction": float(ref_valid.mean()),
           "reference_valid": int(ref_valid.sum()), "new_invalid": int((ref_valid & ~valid).sum()),
           "new_valid": int((valid & ~ref_valid).sum())}
    if measured.any():
        row.update(penetration_p99_mm=float(np.percentile(penetration, 99)), penetration_max_mm=float(penetration.max()),
                   reference_penetration_max_mm=float(ref_depth[measured].max() * 1000))
    return row


def _fidelity_rows(run: dict, ref: dict) -> dict:
    names = dict.fromkeys(key.split("/")[0] for key in run)
    return {"pooled": _compare(run, ref, ""), **{name: _compare(run, ref, name + "/") for name in names}}


def _budget(text: str) -> dict:
    values = {}
    for item in text.split(","):
        key, _, value = item.partition("=")
        if key.strip() not in BUDGET_KEYS:
            raise SystemExit(f"--budget: unknown key {key!r}; use {', '.join(BUDGET_KEYS)}")
        values[key.strip()] = float(value)
    if set(values) != set(BUDGET_KEYS):
        raise SystemExit(f"--budget must give {', '.join(BUDGET_KEYS)}")
    return values


def _misses(pooled: dict, budget: dict) -> list[str]:
    """The budget items a pooled fidelity row misses (empty: within budget)."""
    misses = []
    if pooled["median_cm"] is None or pooled["median_cm"] > budget["median"]:
        misses.append("median")
    if pooled["p90_cm"] is None or pooled["p90_cm"] > budget["p90"]:
        misses.append("p90")
    if pooled["new_invalid"] > budget["new_invalid"] / 100 * pooled["reference_valid"]:
        misses.append("new_invalid")
    if pooled.get("penetration_max_mm", math.inf) > pooled.get("reference_penetration_max_mm", 0.0) + budget["penetration"]:
        misses.append("penetration")
    return misses


def _spawn(flag: str, setting: str, args, extra=()) -> dict:
    cmd = [sys.executable, __file__, flag, setting, "--batch", str(args.batch), "--steps", str(args.steps),
           "--repeats", str(args.repeats), "--fidelity-size", str(args.fidelity_size), "--skills", str(args.skills),
           "--skill-damage", args.skill_damage, "--chunk", str(args.chunk), "--seed", str(args.seed),
           "--elites", str(args.elites), *extra]
    for name in ("hbr", "flat"):
        if getattr(args, name) is not None:
            cmd += [f"--{name}", str(getattr(args, name))]
    return run_worker(cmd, args.timeout, {"setting": setting})


def _fmt(value, spec: str) -> str:
    text = format(math.nan if value is None else value, spec)
    return text.replace("nan", "-").rjust(len(text))


def _table(rows) -> str:
    head = (f"{'setting':18} {'steps/s':>10} {'x' + BASELINE:>6} {'med cm':>7} {'p90 cm':>7} {'max cm':>7} "
            f"{'yaw p90':>7} {'valid %':>7} {'new inv':>7} {'pen p99':>7} {'pen max':>7}  budget")
    lines = [head, "-" * len(head)]
    for r in rows:
        if "error" in r:
            lines.append(f"{r['setting']:18} {r['error']}")
            continue
        f = r["fidelity"]["pooled"]
        lines.append(
            f"{r['setting']:18} {_fmt(r.get('steps_per_s'), '10,.0f')} {_fmt(r.get('speedup'), '6.2f')} "
            f"{_fmt(f['median_cm'], '7.2f')} {_fmt(f['p90_cm'], '7.2f')} {_fmt(f['max_cm'], '7.2f')} "
            f"{_fmt(f['yaw_p90_deg'], '7.2f')} {100 * f['valid_fraction']:7.1f} {f['new_invalid']:7d} "
            f"{_fmt(f.get('penetration_p99_mm'), '7.1f')} {_fmt(f.get('penetration_max_mm'), '7.1f')}  "
            f"{'ok' if not r['budget_misses'] else 'misses ' + ','.join(r['budget_misses'])}"
        )
    return "\n".join(lines)


def _workload_table(rows) -> str:
    names = [name for name in rows[0]["fidelity"] if name != "pooled"]
    head = f"{'setting':18} " + " ".join(f"{name[:20]:>20}" for name in names)
    lines = ["final position error median / p90 / max (cm), per workload", head, "-" * len(head)]
    for r in rows:
        cells = [f"{_fmt(r['fidelity'][n]['median_cm'], '.2f')}/{_fmt(r['fidelity'][n]['p90_cm'], '.2f')}/"
                 f"{_fmt(r['fidelity'][n]['max_cm'], '.1f')}" for n in names]
        lines.append(f"{r['setting']:18} " + " ".join(f"{c:>20}" for c in cells))
    return "\n".join(lines)


def _repertoire_table(rows) -> str:
    head = f"{'setting':18} {'repertoire':10} {'trained':>9} {'elites':>6} {'valid %':>7} {'med cm':>7} {'p90 cm':>7} {'max cm':>7} {'own cell %':>10}"
    lines = ["repertoires re-simulated vs their stored descriptors", head, "-" * len(head)]
    for r in rows:
        if "error" in r:
            lines.append(f"{r['setting']:18} {r['error']}")
            continue
        for name in ("hbr-top", "flat-2d"):
            s = r[name]
            lines.append(f"{r['setting']:18} {name:10} {s.get('trained', '-'):>9} {s['elites']:6d} {100 * s['valid_fraction']:7.1f} "
                         f"{_fmt(s['median_cm'], '7.2f')} {_fmt(s['p90_cm'], '7.2f')} {_fmt(s['max_cm'], '7.2f')} "
                         f"{100 * s['in_own_cell']:10.1f}")
    return "\n".join(lines)


def _plot(rows, budget: dict, reference: dict, path: Path) -> None:
    """Speed (log x) against pooled final-position error: p90 (filled) and median (open) per setting."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    for r in rows:
        if "error" in r or r.get("steps_per_s") is None:
            continue
        f = r["fidelity"]["pooled"]
        colour = "tab:green" if not r["budget_misses"] else "tab:red"
        x = r["steps_per_s"]
        ax.plot([x, x], [f["median_cm"], f["p90_cm"]], color=colour, lw=1)
        ax.plot(x, f["p90_cm"], "o", color=colour)
        ax.plot(x, f["median_cm"], "o", mfc="white", color=colour)
        label = r["setting"] + (" (reference)" if r["setting"] == reference["setting"] else "")
        ax.annotate(label, (x, f["p90_cm"]), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.axhline(budget["p90"], color="k", ls="--", lw=1, label=f"budget p90 {budget['p90']:g} cm")
    ax.axhline(budget["median"], color="k", ls=":", lw=1, label=f"budget median {budget['median']:g} cm")
    floor = reference.get("perturbed", {}).get("fidelity")
    if floor:
        ax.axhline(floor["pooled"]["p90_cm"], color="tab:gray", ls="-.", lw=1,
                   label=f"noise floor p90 (reference, joints + {PERTURBATION:g} rad)")
    ax.set_xscale("log")
    ax.set_xlabel("physics steps / s")
    ax.set_ylabel(f"final position error vs {reference['setting']} (cm)")
    ax.set_title("solver settings: speed vs fidelity (filled p90, open median; green within budget)")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _frontier(args, settings: list[str], budget: dict, scratch: Path, save) -> dict:
    """Run the reference (and its checks), then every setting; compare. `save(partial)` is called
    after every setting with the rows so far, so a run cut short keeps what it measured."""
    count = itertools.count()

    def run(setting, extra=()):
        npz = scratch / f"{next(count)}.npz"
        row = _spawn("--worker", setting, args, ("--npz", str(npz), *extra))
        data = None if "error" in row else dict(np.load(npz))
        took = f" (compile {row['compile_s']:.0f} s, fidelity {row['fidelity_s']:.0f} s)" if "fidelity_s" in row and "compile_s" in row else ""
        print(f"{setting}: {row.get('error') or _fmt(row.get('steps_per_s'), ',.0f') + ' steps/s'}{took}", flush=True)
        return row, data

    ref_row, ref = run(args.reference)
    if ref is None:
        raise SystemExit(f"reference {args.reference} failed: {ref_row['error']}")
    reference = {"setting": args.reference}
    checks = [c.strip() for c in args.reference_checks.split(",") if c.strip()]
    if "doubled" in checks:
        doubled, data = run(_doubled(args.reference), ("--no-speed",))
        reference["doubled"] = doubled if data is None else {"setting": doubled["setting"], **_compare(data, ref, "")}
    if "perturbed" in checks:
        perturbed, data = run(args.reference, ("--no-speed", "--perturb", str(PERTURBATION)))
        reference["perturbed"] = perturbed if data is None else {
            "perturbation_rad": PERTURBATION, "fidelity": _fidelity_rows(data, ref)}
    rows = []
    for setting in settings:
        row, data = (ref_row, ref) if setting == args.reference else run(setting)
        if data is not None:
            row["fidelity"] = _fidelity_rows(data, ref)
            row["budget_misses"] = _misses(row["fidelity"]["pooled"], budget)
        rows.append(row)
        save({"reference": reference, "rows": rows})
    if args.reference not in settings:
        ref_row.update(fidelity=_fidelity_rows(ref, ref), budget_misses=[])
        rows.append(ref_row)
    return {"reference": reference, "rows": rows}


def _summary(rows, reference: dict, budget: dict) -> dict:
    """Budget misses, speed ratios against BASELINE and the fastest setting within the budget (rows updated)."""
    for r in rows:
        if "fidelity" in r:
            r["budget_misses"] = _misses(r["fidelity"]["pooled"], budget)
    baseline = next((r for r in rows if r["setting"] == BASELINE and r.get("steps_per_s")), None)
    for r in rows:
        if baseline is not None and r.get("steps_per_s"):
            r["speedup"] = r["steps_per_s"] / baseline["steps_per_s"]
    ok = [r for r in rows if "error" not in r and not r["budget_misses"] and r.get("steps_per_s")]
    fastest = max(ok, key=lambda r: r["steps_per_s"], default=None)
    summary = {"fastest_within_budget": fastest and fastest["setting"],
               "fastest_within_budget_steps_per_s": fastest and fastest["steps_per_s"],
               "within_budget": [r["setting"] for r in ok]}
    if "max_cm" in reference.get("doubled", {}):
        summary["reference_doubled_max_mm"] = reference["doubled"]["max_cm"] * 10
        summary["reference_converged"] = reference["doubled"]["max_cm"] < 0.1
    if "fidelity" in reference.get("perturbed", {}):
        floor = reference["perturbed"]["fidelity"]["pooled"]
        summary["noise_floor_median_cm"], summary["noise_floor_p90_cm"] = floor["median_cm"], floor["p90_cm"]
    return summary


# What must agree for rows of two runs to be compared (their settings otherwise may differ).
SAME_WORKLOAD = ("reference", "batch", "steps", "fidelity_size", "skills", "skill_damage", "seed", "elites")


def _merged(paths, env: dict, settings: dict) -> list[dict]:
    """Payloads of earlier runs with the same device and workload (SystemExit otherwise)."""
    payloads = []
    for path in paths:
        earlier = earlier_result(path, env)
        differ = [key for key in SAME_WORKLOAD if earlier["settings"].get(key) != settings[key]]
        if differ:
            raise SystemExit(f"{path} used another workload (differs in: {', '.join(differ)})")
        for row in earlier.get("rows", []) + earlier.get("repertoires", []):
            row.setdefault("measured_in", Path(path).name)
        payloads.append(earlier)
    return payloads


def _join(own: list[dict], earlier: list[dict]) -> list[dict]:
    """This run's rows, then earlier rows of settings this run did not measure."""
    rows, seen = list(own), {r["setting"] for r in own}
    for r in earlier:
        if r["setting"] not in seen:
            rows.append(r)
            seen.add(r["setting"])
    return rows


def main(argv=None):
    args = _parse(argv)
    if args.worker is not None or args.repertoire_worker is not None:
        print(json.dumps(_worker(args) if args.worker is not None else _repertoire_worker(args)))
        return

    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # the parent only reads the device's name
    env = environment()
    gpu = env["platform"] != "cpu"
    args.batch = args.batch or (32768 if gpu else 256)
    args.fidelity_size = args.fidelity_size or (4096 if gpu else 256)
    args.skills = (2048 if gpu else 256) if args.skills is None else args.skills
    args.chunk = args.chunk or (16384 if gpu else 1024)
    if args.repertoires is None:
        args.repertoires = ",".join(dict.fromkeys([BASELINE, setting_label(RobotConfig())]))
    settings = [s.strip() for s in args.settings.split(",") if s.strip()]
    checks = [s.strip() for s in args.repertoires.split(",") if s.strip()]
    budget = _budget(args.budget)
    for setting in [args.reference, *settings, *checks]:
        try:
            _config(setting)
        except Exception as error:  # noqa: BLE001 - a bad setting is a one-line error
            raise SystemExit(f"bad setting {setting!r}: {error}") from None

    payload = {"environment": env, "settings": {
        "settings": settings, "reference": args.reference, "budget": budget, "batch": args.batch, "steps": args.steps,
        "repeats": args.repeats, "fidelity_size": args.fidelity_size, "skills": args.skills,
        "skill_damage": args.skill_damage, "seed": args.seed, "repertoires": checks, "elites": args.elites,
        "hbr": str(args.hbr or "shipped"), "flat": str(args.flat or "shipped")}}
    out = args.out or result_path("physics_frontier", env)
    out.parent.mkdir(parents=True, exist_ok=True)
    header = (f"{env['device']} ({env['platform']}), jax {env['jax']}, mujoco {env['mujoco']}, speed batch {args.batch}, "
              f"fidelity {args.fidelity_size} random x 2 + {args.skills} flat + {args.skills} HBR x 2, reference {args.reference}")
    merged = _merged(args.merge, env, payload["settings"])
    if settings:
        with tempfile.TemporaryDirectory(prefix="physics-frontier-") as scratch:
            payload.update(_frontier(args, settings, budget, Path(scratch),
                                     lambda part: out.write_text(json.dumps({**payload, **part, "partial": True}, indent=2))))
    elif merged:
        payload["reference"] = merged[0]["reference"]
    if merged:
        payload["merged"] = [str(path) for path in args.merge]
        payload["rows"] = _join(payload.get("rows", []), [r for m in merged for r in m.get("rows", [])])
        payload["settings"]["settings"] = [r["setting"] for r in payload["rows"]]
        for check in ("doubled", "perturbed"):
            earlier = next((m["reference"][check] for m in merged if check in m["reference"]), None)
            if check not in payload["reference"] and earlier is not None:
                payload["reference"][check] = earlier
    if payload.get("rows"):
        payload["summary"] = _summary(payload["rows"], payload["reference"], budget)
        print()
        print(header)
        print(_table(payload["rows"]))
        print()
        floor = payload["reference"].get("perturbed", {}).get("fidelity")
        noise = [{"setting": "noise floor", "fidelity": floor}] if floor else []
        print(_workload_table([r for r in payload["rows"] if "error" not in r] + noise))
        for key, value in payload["summary"].items():
            print(f"{key}: {value}")
        plot = out.with_suffix(".png")
        _plot(payload["rows"], budget, payload["reference"], plot)
        payload["plot"] = plot.name
    repertoires = _join([_spawn("--repertoire-worker", s, args) for s in checks],
                        [r for m in merged for r in m.get("repertoires", [])])
    if repertoires:
        payload["repertoires"] = repertoires
        print()
        print(_repertoire_table(payload["repertoires"]))
    out.write_text(json.dumps(payload, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
