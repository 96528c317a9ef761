"""Wall time of one `maze_eval` action: planning and acting of one batch, per action, on this machine.

Runs the HBR batch of a maze_eval configuration (a --protocol's variants on its damages, --preset
planner) for --actions actions, --repeats times, and reports the median planning and acting
seconds per action after the first (compiling) action of each repeat. It calls only
`evaluation.run_batch`, so the same file times two versions of the library in one run
(`--tree DIR`, repeatable: each run imports `hte_jax` from that checkout, in alternation), e.g.
before and after a refactor, and several settings of one configuration (`--config`, repeatable:
maze_eval's overrides, e.g. the planner's or the physics'):

    python benchmarks/action_time.py --protocol hte-jax
    python benchmarks/action_time.py --protocol hte-jax --tree /path/to/old/checkout --tree .
    python benchmarks/action_time.py --preset gpu --config impl=warp --config impl=warp,iterations=250,roots=16
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def parse_config(text: str) -> dict[str, str]:
    """"KEY=VALUE,KEY=VALUE" -> overrides ("" -> none); ValueError naming the malformed text."""
    pairs = [item.split("=", 1) for item in text.split(",") if item.strip()]
    if any(len(pair) != 2 for pair in pairs):
        raise ValueError(f"--config {text!r}: give KEY=VALUE items separated by commas")
    return {key.strip(): value.strip() for key, value in pairs}


def measure(protocol: str, preset: str, actions: int, seed: int, config: str = "") -> dict:
    """One run in this process: the timings of one batch (first action excluded), under the overrides `config`."""
    from hte_jax.online.evaluation import batches, preset as preset_named, protocol_overrides, run_batch, with_overrides

    overrides = protocol_overrides(protocol)
    overrides.update(parse_config(config))
    overrides.update(max_actions=str(actions), seed=str(seed))
    config = with_overrides(preset_named(preset), overrides)
    _, path, variants = next(b for b in batches(config) if b[1] is None or b[1].endswith("hbr.npz"))
    result = run_batch(config, path, variants, progress=False)
    plan, act = result.timings.plan, result.timings.act
    return {"episodes": len(result.variants), "variants": variants, "plan_s": plan, "act_s": act,
            "plan_median_s": float(np.median(plan[1:])), "act_median_s": float(np.median(act[1:])),
            "first_action_s": plan[0] + act[0]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--protocol", default="hte-jax", help="maze_eval protocol whose HBR batch is timed")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--actions", type=int, default=4, help="actions per run (the first compiles)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per tree, in alternation")
    parser.add_argument("--tree", action="append", default=None, help="a checkout to time (repeatable; default: this one)")
    parser.add_argument("--config", action="append", default=None,
                        help="overrides KEY=VALUE[,KEY=VALUE...] to time (repeatable; default: none)")
    parser.add_argument("--out", default=None, help="JSON path (default benchmarks/results/...)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    configs = args.config or [""]
    try:
        for config in configs:
            parse_config(config)
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if args.child:  # one measurement, printed as JSON for the parent
        print(json.dumps(measure(args.protocol, args.preset, args.actions, seed=0, config=configs[0])))
        return 0
    trees = [Path(t).resolve() for t in (args.tree or [HERE.parent])]
    cases = [(tree, config) for tree in trees for config in configs]
    label = {case: str(case[0]) + (f" [{case[1] or 'no overrides'}]" if len(configs) > 1 else "") for case in cases}
    runs = {label[case]: [] for case in cases}
    for _ in range(args.repeats):
        for tree, config in cases:
            env = {**os.environ, "PYTHONPATH": str(tree)}
            command = [sys.executable, str(HERE / "action_time.py"), "--child", "--protocol", args.protocol,
                       "--preset", args.preset, "--actions", str(args.actions), "--config", config]
            done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True)
            if done.returncode != 0:
                sys.exit(f"error: the run in {tree} ({config or 'no overrides'}) failed: "
                         f"{done.stderr.strip().splitlines()[-1:]}")
            runs[label[tree, config]].append(json.loads(done.stdout.strip().splitlines()[-1]))
    sys.path.insert(0, str(HERE))
    from common import environment, result_path

    env = environment()
    print(f"\none {args.protocol} action ({args.preset} preset), median over {args.repeats} runs x "
          f"{args.actions - 1} actions, on {env['device']}")
    print(f"{'run':<40} {'episodes':>8} {'plan s':>8} {'act s':>8} {'action s':>9} {'first s':>8}")
    rows = {}
    for tree, measured in runs.items():
        plan = float(np.median([m["plan_median_s"] for m in measured]))
        act = float(np.median([m["act_median_s"] for m in measured]))
        rows[tree] = {"episodes": measured[0]["episodes"], "variants": measured[0]["variants"], "plan_median_s": plan,
                      "act_median_s": act, "action_median_s": plan + act, "runs": measured}
        first = float(np.median([m["first_action_s"] for m in measured]))
        print(f"{tree[-40:]:<40} {measured[0]['episodes']:>8} {plan:>8.2f} {act:>8.2f} {plan + act:>9.2f} {first:>8.1f}")
    out = args.out or result_path(f"action_time_{args.protocol}_{args.preset}", env)
    Path(out).write_text(json.dumps({"environment": env, "protocol": args.protocol, "preset": args.preset,
                                     "actions": args.actions, "repeats": args.repeats, "configs": configs,
                                     "trees": rows}, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
