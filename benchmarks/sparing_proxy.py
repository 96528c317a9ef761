"""Proxy for issue 17: how far damaged robots end from a skill's stored end, per way of executing it.

Each robot chains `--actions` random top-layer skills of an HBR reset-free in open space (3 s
skill + 1 s neutral pose, as in the maze) under a damage; for each action after the first we
measure the distance (m) between where it ended and where the skill's stored end says it should
(in the action's start frame). Ways of executing a skill, all with the damage known (oracles):

- rte: the nearest middle elite of any pattern to each waypoint (RTE on the HBR);
- pattern: the damage's contact pattern at the HBR's threshold, planned to the skill's end
  (Perfect HTE with planned composition);
- sparing: the damage's sparing set (`hbr.sparing`: elites with under 5 % contact on every
  damaged leg), planned to the skill's end; with `--spare FILE` the middle elites of that HBR
  file (e.g. one trained at a 5 % contact threshold) are added to the sets.

Prints a table (median error, share within 0.1 m, invalid actions) and writes JSON to
benchmarks/results/. Usage: python benchmarks/sparing_proxy.py [--spare FILE] [--damages leg1,leg4,legs1+4]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import environment, result_path  # noqa: E402
from hte_jax.hbr.composition import planning_table, skill_ends  # noqa: E402
from hte_jax.hbr.hierarchy import STEPS_PER_SKILL, execute_skill, state_pose  # noqa: E402
from hte_jax.geometry import relative_pose  # noqa: E402
from hte_jax.hbr.sparing import sparing_table  # noqa: E402
from hte_jax.hbr.store import load_hbr, load_spare  # noqa: E402
from hte_jax.online.execute import neutral_second  # noqa: E402
from hte_jax.online.secondary import oracle_pattern  # noqa: E402
from hte_jax.sim.damage import damage_masks  # noqa: E402
from hte_jax.sim.robot import RobotConfig, load_robot  # noqa: E402
from hte_jax.sim.rollout import standing_state  # noqa: E402

WAYS = ("rte", "pattern", "sparing")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--hbr", default=None, help="HBR file (default: the shipped one)")
    parser.add_argument("--spare", default=None, help="a spare archive (experiments.train_spare) or an HBR file whose middle elites join the sparing sets")
    parser.add_argument("--damages", default="leg1,leg4,legs1+4")
    parser.add_argument("--damage-model", default="raised", choices=("raised", "locked"))
    parser.add_argument("--robots", type=int, default=64, help="robots per damage and way")
    parser.add_argument("--actions", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--label", default="")
    parser.add_argument("--measured-ends", action="store_true",
                        help="also the error to the end the intact robot reaches executing the skill the same way")
    args = parser.parse_args(argv)

    hbr, task, _ = load_hbr(args.hbr)
    if args.spare:
        hbr = load_spare(args.spare, hbr)
    tables = {"pattern": planning_table(hbr), "sparing": sparing_table(hbr)}
    robot = load_robot(RobotConfig(damage_model=args.damage_model))
    names = args.damages.split(",")
    masks = damage_masks(names)
    top = np.flatnonzero(np.asarray(hbr.top.filled))
    ends_all = np.asarray(skill_ends(hbr.top.descriptors, hbr.top.extras["arrival_yaw"], task.extent))
    rng = np.random.default_rng(args.seed)

    @jax.jit
    def act(hbr, table, state, damage, genes, ends, patterns):
        skill = execute_skill(robot, hbr, genes, state, damage=damage, patterns=patterns, table=table, ends=ends)
        rest = neutral_second(robot, skill.state, damage)
        return rest.final_state, skill.valid & rest.valid

    rows = []
    for name, mask in zip(names, masks):
        batch = args.robots
        damage = jnp.broadcast_to(jnp.asarray(mask), (batch, 6))
        start = standing_state(robot, damage)
        pattern = oracle_pattern(mask)
        chosen = rng.choice(top, size=(args.actions, batch))
        for way in WAYS:
            began = time.perf_counter()
            state, alive, errors, measured = start, np.ones(batch, bool), [], []
            wanted = -1 if way == "rte" else pattern
            table = tables.get(way)
            for a in range(args.actions):
                slots = chosen[a]
                origin = np.asarray(state_pose(state))
                patterns = jnp.full((batch, STEPS_PER_SKILL), wanted, jnp.int32)
                state, valid = act(hbr, table, state, damage, hbr.top.genotypes[slots], jnp.asarray(ends_all[slots]),
                                   patterns)
                moved = np.asarray(relative_pose(jnp.asarray(origin), state_pose(state)))
                alive &= np.asarray(valid)
                if a > 0:
                    errors.append(np.where(alive, np.linalg.norm(moved[:, :2] - ends_all[slots, :2], axis=-1), np.nan))
                    measured.append(moved[:, :2])
            errors = np.stack(errors)
            row = {"damage": name, "way": way, "median_error_m": float(np.nanmedian(errors)),
                   "within_0.1m": float(np.nanmean(errors <= 0.1)), "invalid_robots": float(1 - alive.mean())}
            if args.measured_ends:
                # the same skills, executed the same way by the intact robot from the standing state:
                # how far the damaged robot ends from the end a table of measured ends would predict
                slots = chosen[1:].reshape(-1)
                intact_start = jax.tree.map(lambda x: jnp.broadcast_to(x[:1], (slots.size, *x.shape[1:])), start)
                none = jnp.zeros((slots.size, 6), bool)
                patterns = jnp.full((slots.size, STEPS_PER_SKILL), wanted, jnp.int32)
                skill = execute_skill(robot, hbr, hbr.top.genotypes[slots], intact_start, damage=none, patterns=patterns,
                                      table=table, ends=jnp.asarray(ends_all[slots]))
                reference = np.asarray(skill.displacement[:, :2]).reshape(args.actions - 1, batch, 2)
                gaps = np.where(alive[None], np.linalg.norm(np.stack(measured) - reference, axis=-1), np.nan)
                intact_gap = np.linalg.norm(reference - ends_all[chosen[1:], :2], axis=-1)
                row.update(median_error_to_measured_end_m=float(np.nanmedian(gaps)),
                           within_0_1m_of_measured_end=float(np.nanmean(gaps <= 0.1)),
                           intact_measured_end_to_stored_end_m=float(np.median(intact_gap)))
            row["seconds"] = time.perf_counter() - began
            rows.append(row)
            extra = (f"  to measured end {row['median_error_to_measured_end_m']:.3f} m (within 0.1 m "
                     f"{row['within_0_1m_of_measured_end']:.2f}; intact vs stored {row['intact_measured_end_to_stored_end_m']:.3f})"
                     if args.measured_ends else "")
            print(f"{name:8s} {way:8s} median {row['median_error_m']:.3f} m  within 0.1 m "
                  f"{row['within_0.1m']:.2f}  invalid {row['invalid_robots']:.2f}{extra}", flush=True)
    env = environment()
    out = result_path(f"sparing_proxy{args.label}", env)
    out.write_text(json.dumps({"environment": env, "args": vars(args), "rows": rows}, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
