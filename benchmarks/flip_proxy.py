"""Proxy for issue 17: how often each way of executing skills flips a robot with a damaged leg.

In the maze, a raised corner leg (0, 2, 3, 5) flips the robot in most episodes of every variant.
Here `--robots` robots per damage chain `--actions` random top-layer skills of an HBR reset-free
in open space (3 s skill + 1 s neutral pose, body colliding with the floor, the online phase's
validity limits: tilted past 90 degrees or a non-finite / exploding state). Ways of executing a
skill (`sparing_proxy.py`): rte (nearest elite of any pattern), pattern (the damage's contact
pattern, planned), sparing (the damage's sparing set, planned). Robots, which separate why a
robot flips:

- raised / locked: the damage under the "raised" and the "locked" damage model;
- light: the raised damage with the damaged legs' links made 1000x lighter (a leg removed: the
  raised pose without its mass up high);
- touchless: the intact robot, every leg run by its controller, but the damaged legs' links and
  feet pass through the floor (support lost, mass where the controller holds it);
- intact: the intact robot running the damage's gaits.

Prints, per damage, way, robot and tilt reflex (`--reflex-tilt`), the share of robots
flipped after the first action and after all of them, in which phase the flips began (step 1, 2,
3 of the skill or the neutral second), and the median distance between a whole skill's end and
its stored end point (what a reflex that fires in a stable gait costs); writes JSON to
benchmarks/results/.
Usage: python benchmarks/flip_proxy.py [--damages leg0,leg2,leg3,leg5] [--robots 64] [--actions 3]
       [--ways rte,pattern,sparing] [--models raised,light,touchless,locked,intact] [--reflex-tilt 0,0.5,0.3/0.15,0.3/0/1]
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import environment, result_path  # noqa: E402
from hte_jax.errors import ConfigError  # noqa: E402
from hte_jax.hbr.composition import planning_table, skill_ends  # noqa: E402
from hte_jax.hbr.hierarchy import STEPS_PER_SKILL, execute_skill  # noqa: E402
from hte_jax.hbr.sparing import sparing_table  # noqa: E402
from hte_jax.hbr.store import load_hbr, load_spare, spare_beside  # noqa: E402
from hte_jax.online.execute import ONLINE_LIMITS, neutral_second  # noqa: E402
from hte_jax.online.secondary import oracle_pattern  # noqa: E402
from hte_jax.sim.damage import NUM_LEGS, damage_masks  # noqa: E402
from hte_jax.sim.robot import FLOOR_BIT, Robot, RobotConfig, compile_model, load_robot, robot_info  # noqa: E402
from hte_jax.sim.mjx_import import mjx  # noqa: E402
from hte_jax.sim.rollout import standing_state  # noqa: E402

WAYS = ("rte", "pattern", "sparing")
ROBOTS = ("raised", "light", "touchless", "locked", "intact")
LIGHTER = 1e-3
PHASES = ("step 1", "step 2", "step 3", "neutral")


def first_invalid_phase(step_reasons: np.ndarray, rest_valid: np.ndarray) -> np.ndarray:
    """(3, B) per-step invalid bits and (B,) neutral validity -> (B,) index into PHASES of the
    first invalid phase, -1 where the whole action stayed valid."""
    bad = np.concatenate([step_reasons != 0, ~rest_valid[None]], axis=0)  # (4, B)
    return np.where(bad.any(axis=0), bad.argmax(axis=0), -1)


def skill_miss_median(misses: list[np.ndarray]) -> float:
    """Median over every whole skill run of how far (m, x-y) it ended from its stored end point; the
    robots' per-action arrays `misses`; NaN when no skill ran whole. The reflex's cost: a skill cut
    short by it ends short."""
    runs = np.concatenate([np.asarray(m, np.float64).ravel() for m in misses]) if misses else np.zeros(0)
    return float(np.median(runs)) if runs.size else float("nan")


def parse_reflex(item: str) -> tuple[float, float, float]:
    """'TILT[/RELEASE[/RATE]]' -> (reflex_tilt, reflex_release, reflex_rate), the missing ones 0."""
    values = [float(v) for v in item.split("/")]
    if not 1 <= len(values) <= 3:
        raise ValueError(f"{item!r} is not TILT[/RELEASE[/RATE]]")
    return tuple(values + [0.0] * (3 - len(values)))


def reflex_options(reflex: tuple[float, float, float]) -> dict:
    """RobotConfig's reflex fields of a `parse_reflex` triple."""
    return dict(zip(("reflex_tilt", "reflex_release", "reflex_rate"), reflex))


def altered_robot(config: RobotConfig, legs, lighter: float = 1.0, touchless: bool = False) -> Robot:
    """The hexapod of `config` with the links of `legs` made `lighter` times as heavy (mass and
    inertia) and, if `touchless`, their links and feet unable to touch the floor."""
    model = compile_model(config)
    for leg in legs:
        for part in (1, 2, 3):
            body = model.body(f"leg_{leg}_{part}").id
            model.body_mass[body] *= lighter
            model.body_inertia[body] *= lighter
        if touchless:
            for name in (f"leg_{leg}_1", f"leg_{leg}_2", f"leg_{leg}_3", f"foot_{leg}"):
                model.geom_contype[model.geom(name).id] &= ~FLOOR_BIT
    return Robot(model=mjx.put_model(model), info=robot_info(model, config))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--hbr", default=None, help="HBR file (default: the shipped one)")
    parser.add_argument("--spare", default=None, help="spare archive (default: the one beside the HBR, if any)")
    parser.add_argument("--damages", default="leg0,leg2,leg3,leg5")
    parser.add_argument("--robots", type=int, default=64, help="robots per damage, way and robot model")
    parser.add_argument("--actions", type=int, default=3)
    parser.add_argument("--ways", default=",".join(WAYS), help=f"ways of executing a skill, of {', '.join(WAYS)}")
    parser.add_argument("--models", default=",".join(ROBOTS), help=f"robot models to run, of {', '.join(ROBOTS)}")
    parser.add_argument("--reflex-tilt", default="0",
                        help="comma-separated tilt reflexes, each run: TILT[/RELEASE[/RATE]] (RobotConfig.reflex_tilt, "
                             "reflex_release rad, reflex_rate rad/s; 0 = off)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--label", default="")
    args = parser.parse_args(argv)
    chosen_ways, chosen_models = args.ways.split(","), args.models.split(",")
    for option, chosen, known in (("--ways", chosen_ways, WAYS), ("--models", chosen_models, ROBOTS)):
        unknown = sorted(set(chosen) - set(known))
        if unknown:
            parser.error(f"{option}: unknown {', '.join(unknown)}; choose from {', '.join(known)}")

    try:
        reflexes = [parse_reflex(item) for item in args.reflex_tilt.split(",")]
        configs = {(name, reflex): RobotConfig(damage_model=name, body_floor_contact=True, **reflex_options(reflex))
                   for reflex in reflexes for name in ("raised", "locked")}
    except (ValueError, TypeError, ConfigError) as error:
        parser.error(f"--reflex-tilt: {error}")
    hbr, task, _ = load_hbr(args.hbr)
    spare = args.spare or spare_beside(args.hbr)
    if spare:
        hbr = load_spare(spare, hbr)
    tables = {"pattern": planning_table(hbr), "sparing": sparing_table(hbr)}
    models = {key: load_robot(config) for key, config in configs.items()}
    top = np.flatnonzero(np.asarray(hbr.top.filled))
    ends_all = np.asarray(skill_ends(hbr.top.descriptors, hbr.top.extras["arrival_yaw"], task.extent))
    rng = np.random.default_rng(args.seed)

    @jax.jit
    def act(robot, hbr, table, state, damage, genes, ends, patterns):
        skill = execute_skill(robot, hbr, genes, state, damage=damage, patterns=patterns, table=table, ends=ends,
                              limits=ONLINE_LIMITS)
        rest = neutral_second(robot, skill.state, damage)
        miss = jnp.linalg.norm(skill.displacement[:, :2] - ends[:, :2], axis=-1)
        return rest.final_state, skill.steps.invalid_reason, rest.valid, miss

    rows = []
    names = args.damages.split(",")
    print(f"{'damage':8s} {'way':8s} {'robot':9s} {'reflex':>11s} flipped after 1 / {args.actions} actions   flips began in "
          + " / ".join(PHASES) + "   end miss (m)", flush=True)
    for (name, mask), reflex in itertools.product(zip(names, damage_masks(names)), reflexes):
        batch = args.robots
        pattern = oracle_pattern(mask)
        chosen = rng.choice(top, size=(args.actions, batch))
        legs = np.flatnonzero(mask).tolist()
        raised, locked = (configs[model, reflex] for model in ("raised", "locked"))
        robots = {"raised": (models["raised", reflex], mask), "locked": (models["locked", reflex], mask),
                  "light": (altered_robot(raised, legs, lighter=LIGHTER), mask),
                  "touchless": (altered_robot(raised, legs, touchless=True), np.zeros(NUM_LEGS, bool)),
                  "intact": (models["raised", reflex], np.zeros(NUM_LEGS, bool))}
        for way in chosen_ways:
            table = tables.get(way)
            wanted = -1 if way == "rte" else pattern
            patterns = jnp.full((batch, STEPS_PER_SKILL), wanted, jnp.int32)
            for robot_name in chosen_models:
                began = time.perf_counter()
                robot, robot_mask = robots[robot_name]
                damage = jnp.broadcast_to(jnp.asarray(robot_mask), (batch, NUM_LEGS))
                state = standing_state(robot, damage)
                alive = np.ones(batch, bool)
                flipped_after, began_in, misses = [], np.zeros(len(PHASES), int), []
                for a in range(args.actions):
                    slots = chosen[a]
                    state, reasons, rest_valid, miss = act(robot, hbr, table, state, damage, hbr.top.genotypes[slots],
                                                           jnp.asarray(ends_all[slots]), patterns)
                    phase = first_invalid_phase(np.asarray(reasons), np.asarray(rest_valid))
                    misses.append(np.asarray(miss)[alive & (phase < 0)])  # skills that ran whole
                    newly = alive & (phase >= 0)
                    began_in += np.bincount(phase[newly], minlength=len(PHASES))
                    alive &= ~newly
                    flipped_after.append(float(1 - alive.mean()))
                row = {"damage": name, "way": way, "robot": robot_name, **reflex_options(reflex),
                       "flipped_after_action": flipped_after,
                       "flips_began_in": dict(zip(PHASES, began_in.tolist())),
                       "end_miss_median_m": skill_miss_median(misses),
                       "seconds": time.perf_counter() - began}
                rows.append(row)
                print(f"{name:8s} {way:8s} {robot_name:9s} {'/'.join(f'{v:g}' for v in reflex):>11s} "
                      f"{flipped_after[0]:.2f} / {flipped_after[-1]:.2f}                     " + " / ".join(str(n) for n in began_in.tolist())
                      + f"   {row['end_miss_median_m']:.3f}", flush=True)
    env = environment()
    out = result_path(f"flip_proxy{args.label}", env)
    out.write_text(json.dumps({"environment": env, "args": vars(args), "rows": rows}, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
