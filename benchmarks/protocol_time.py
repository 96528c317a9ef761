"""Wall time of whole `maze_eval` runs, where it goes, and whether two settings give the same results.

Runs `python -m experiments.maze_eval ARGS --out WORK/LABEL --no-progress` for each `--run LABEL=ARGS`, one
after another, each on the devices this process sees, and times it from start to exit (compilation
included). `--read LABEL=DIR` reads a run made elsewhere (e.g. in parallel on another GPU, its wall time from
DIR/wall_s.txt if written, as `--run` does). From each run's batch files: per batch the actions, its setup
seconds (loading the repertoire, starting the episodes), the first action's seconds (compiling) and the
planning and acting medians per action after it, the batches it ran together with (`maze_eval --together`),
and the batches' seconds in all (each batch's own planning, each group's shared planning, acting and setup
once); from its episodes, per variant the successes and the median actions of the successful episodes.
`--compare A,B` (repeatable) tests whether runs A and B differ beyond run-to-run noise, per variant: Fisher's
exact test on the successes and Mann-Whitney on the successful episodes' actions (episodes as the sample;
Bonferroni over the variants).

    python benchmarks/protocol_time.py --run "base=--protocol hte-jax --preset gpu" \\
        --run "fast=--protocol hte-jax --preset gpu --iterations 250 --roots 16" --compare base,fast

Prints a table and writes JSON (--out, default benchmarks/results/protocol_time_<device>_<date>.json).
Bad input: one `error: ...` line on stderr, exit status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

WALL_FILE = "wall_s.txt"  # a run's wall seconds, beside its outputs


def _label_value(text: str, flag: str) -> tuple[str, str]:
    label, equals, value = text.partition("=")
    if not equals or not label.strip() or not value.strip():
        raise ValueError(f"{flag} {text!r}: expected LABEL=VALUE")
    return label.strip(), value.strip()


def run_command(args: list[str], out: Path) -> float:
    """maze_eval with `args` writing to `out`; its wall seconds (written to out/WALL_FILE). ValueError if it fails."""
    command = [sys.executable, "-m", "experiments.maze_eval", *args, "--out", str(out), "--no-progress"]
    start = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        tail = " | ".join(done.stderr.strip().splitlines()[-3:])
        raise ValueError(f"maze_eval {shlex.join(args)} exited {done.returncode}: {tail}")
    (out / WALL_FILE).write_text(f"{wall:.3f}\n")
    return wall


def read_run(folder: Path) -> tuple[dict, list[dict]]:
    """A finished run's wall seconds (None if not recorded), batches' timings and per-variant results, and its
    episode records."""
    from hte_jax.online.statistics import success_summary
    from hte_jax.qd.io import read_checkpoint

    try:
        records = json.loads((folder / "episodes.json").read_text())["episodes"]
        config = json.loads((folder / "config.json").read_text())
    except (OSError, ValueError, KeyError) as error:
        raise ValueError(f"{folder}: not a finished maze_eval run ({error})") from None
    wall = float((folder / WALL_FILE).read_text()) if (folder / WALL_FILE).is_file() else None
    batches, shared = [], {}  # shared: per group of batches run together, its acting, setup (and planning) seconds
    for k in range(len(list(folder.glob("episodes_*.npz")))):
        labels = read_checkpoint(folder / f"episodes_{k}.npz")[1]["metadata"]
        plan, act = labels["plan_seconds"], labels["act_seconds"]
        run_with = labels.get("run_with", [k])
        plan_shared = len(run_with) > 1  # batches run together plan in one search (`episode.plan_steps`)
        shared[tuple(run_with)] = sum(act) + (labels.get("setup_seconds") or 0.0) + sum(plan) * plan_shared
        batches.append({"variants": sorted(set(labels["variants"])), "episodes": len(labels["variants"]),
                        "run_with": run_with, "plan_shared": plan_shared, "plan_s": float(sum(plan)),
                        "actions": len(plan), "setup_s": labels.get("setup_seconds"), "first_action_s": plan[0] + act[0],
                        "plan_median_s": float(np.median(plan[1:])) if len(plan) > 1 else None,
                        "act_median_s": float(np.median(act[1:])) if len(act) > 1 else None,
                        "seconds": float(sum(plan) + sum(act) + (labels.get("setup_seconds") or 0.0))})
    variants = {}
    for variant in dict.fromkeys(r["variant"] for r in records):
        cell = success_summary([r for r in records if r["variant"] == variant])
        variants[variant] = {"episodes": cell["episodes"], "successes": cell["successes"],
                             "actions_median": cell["actions"]["median"]}
    # the batches' seconds: each one's own planning, each group's acting, setup and shared planning once
    in_batches = sum(b["plan_s"] for b in batches if not b["plan_shared"]) + sum(shared.values())
    result = {"folder": str(folder), "wall_s": wall, "batches_s": float(in_batches), "impl": config.get("impl"),
              "planner": {k: config.get(k) for k in ("iterations", "roots")}, "batches": batches, "variants": variants}
    return result, records


def compare_runs(a: dict, b: dict, records_a: list[dict], records_b: list[dict]) -> dict:
    """Per variant both runs hold: Fisher's exact test on successes, Mann-Whitney on successful actions."""
    from hte_jax.online.statistics import bonferroni_or_none, episode_action_tests, episode_success_tests

    shared = [v for v in a["variants"] if v in b["variants"]]
    if not shared:
        raise ValueError("the two runs share no variant")
    rows = {}
    for variant in shared:
        pair = ([{**r, "variant": "a"} for r in records_a if r["variant"] == variant]
                + [{**r, "variant": "b"} for r in records_b if r["variant"] == variant])
        success = episode_success_tests(pair)["pairs"][0]
        actions = episode_action_tests(pair)["pairs"][0]
        rows[variant] = {"successes": [success["successes_a"], success["successes_b"]],
                         "episodes": [success["episodes_a"], success["episodes_b"]], "success_p": success["p"],
                         "actions_median": [actions["median_a"], actions["median_b"]], "actions_p": actions["p"]}
    for key in ("success_p", "actions_p"):
        for variant, p in zip(shared, bonferroni_or_none([rows[v][key] for v in shared])):
            rows[variant][key + "_bonferroni"] = p
    return {"tests": "per variant: Fisher's exact (successes), Mann-Whitney (successful episodes' actions), "
                     "two-sided, episodes as the sample, Bonferroni over the variants", "variants": rows}


def _seconds(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", action="append", default=[], metavar="LABEL=ARGS", help="a maze_eval run to make")
    parser.add_argument("--read", action="append", default=[], metavar="LABEL=DIR", help="a finished run to read")
    parser.add_argument("--compare", action="append", default=[], metavar="A,B", help="two runs' results to test")
    parser.add_argument("--work", default="runs/protocol_time", help="where --run writes (WORK/LABEL)")
    parser.add_argument("--out", default=None, help="JSON path")
    args = parser.parse_args(argv)
    try:
        runs = [_label_value(text, "--run") for text in args.run]
        reads = [_label_value(text, "--read") for text in args.read]
        labels = [label for label, _ in runs + reads]
        if not labels or len(set(labels)) != len(labels):
            raise ValueError("give at least one --run or --read, each label once")
        pairs = [tuple(item.strip() for item in text.split(",")) for text in args.compare]
        for pair in pairs:
            if len(pair) != 2 or any(label not in labels for label in pair):
                raise ValueError(f"--compare {','.join(pair)}: name two of the runs ({', '.join(labels)})")
        folders = {label: Path(args.work) / label for label, _ in runs} | {label: Path(d) for label, d in reads}
        for label, text in runs:
            folders[label].mkdir(parents=True, exist_ok=True)
            wall = run_command(shlex.split(text), folders[label])
            print(f"{label}: {wall:.1f} s", flush=True)
        read = {label: read_run(folders[label]) for label in labels}
        results = {label: result for label, (result, _) in read.items()}
        for label, text in runs:
            results[label]["args"] = text
        comparisons = {f"{a},{b}": compare_runs(results[a], results[b], read[a][1], read[b][1]) for a, b in pairs}
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    from benchmarks.common import environment, result_path

    env = environment()
    print(f"\nwhole maze_eval runs on {env['device']} ({env['date']})")
    print(f"{'run':<14} {'wall s':>8} {'batches s':>9} {'impl':>5} {'planner':>9}  "
          "batch: episodes, actions, setup s, first action s, plan / act s")
    for label, result in results.items():
        planner = f"{result['planner']['iterations']}x{result['planner']['roots']}"
        cells = "; ".join(f"{b['episodes']}, {b['actions']}, {_seconds(b['setup_s'])}, {b['first_action_s']:.1f}, "
                          f"{_seconds(b['plan_median_s'])} / {_seconds(b['act_median_s'])}" for b in result["batches"])
        print(f"{label:<14} {_seconds(result['wall_s']):>8} {result['batches_s']:>9.1f} {result['impl'] or '-':>5} {planner:>9}  "
              f"{cells}")
    for name, comparison in comparisons.items():
        a, b = name.split(",")
        print(f"\n{a} vs {b}: {comparison['tests']}")
        print(f"{'variant':<14} {'successes':>13} {'p':>8} {'actions (median)':>17} {'p':>8}")
        for variant, row in comparison["variants"].items():
            medians = " / ".join("-" if m is None else f"{m:g}" for m in row["actions_median"])
            successes = f"{row['successes'][0]}/{row['episodes'][0]} {row['successes'][1]}/{row['episodes'][1]}"
            p = "-" if row["actions_p"] is None else f"{row['actions_p']:.3g}"
            print(f"{variant:<14} {successes:>13} {row['success_p']:>8.3g} {medians:>17} {p:>8}")
    out = Path(args.out) if args.out else result_path("protocol_time", env)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"environment": env, "runs": results, "comparisons": comparisons}, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
