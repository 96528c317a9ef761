"""What each damage does to the shipped skills: validity, outcome shift, flips and lost foot contacts.

Conditions: intact (the reference), each --models damage model on each --legs leg ("shortened" and "weak"
at --fraction of the tibia's length / the servos' torque; a model that takes no fraction at none), and
"friction": the floor's friction at --friction of its value, no leg damaged. A --skills sample (seeded by
--seed; 0: every one) of the shipped HBR's top-layer skills and of the shipped Flat-2D elites runs under
every condition, each from the standing state settled under its own condition (x = y = 0):

  hbr      a top-layer skill as `hierarchy.execute_skill` runs it: three 1 s steps, each the middle elite
           (any contact pattern) nearest to the next waypoint seen from where the robot is;
  flat-2d  a Flat-2D elite's controller for the flat task's 3 s (`rollout`).

All conditions of one repertoire run in one compiled program: a batch of C x K rollouts (C conditions,
K skills) whose `Damage` rows mix damage models (blocks of --chunk rows, all of one size). --robot picks the
robot and its validity (`RolloutResult.valid`): "online" (default), an episode's (`arena.maze_config`
without walls: body and links collide with the floor; invalid past 90 degrees of tilt or in a non-finite or
exploding state, `action.ONLINE_LIMITS`), or "training", the repertoires' (only the feet touch the floor;
also invalid past 45 degrees, with the base below 4 cm or a body corner below the floor). Reported per
(repertoire, condition):

  valid          share of the skills valid to the end;
  flipped        share whose body tilted past the validity's max_tilt (`InvalidReason.FLIPPED`);
  distance       median and 90th percentile of the distance between the skill's final (x, y) in its start
                 frame and the same skill's intact one, over the skills valid both intact and damaged
                 ("compared"; intact: 0 by definition);
  contact        share of control steps the measured feet touched the floor (a foot sphere within the
                 rollout's contact tolerance, 1 mm, of it; a removed leg's foot never), averaged over the
                 compared skills and the measured feet: the damaged leg's foot, all six feet where no leg
                 is damaged (intact, friction); contact_intact: the same feet and skills intact;
  contact_lost   1 - contact / contact_intact: the share of the intact contact time those feet lost
                 (1: they never touch; negative: they touch more than intact).

    python benchmarks/damage_skills.py                                 # CPU: 8 skills each, a few minutes
    python benchmarks/damage_skills.py --models removed,weak --legs 1,4 --skills 4
    python benchmarks/damage_skills.py --skills 0                      # GPU: every skill of both repertoires

Prints a table per repertoire and writes JSON (environment, command, settings, rows) to
benchmarks/results/ (or --out). Bad input: one `error: ...` line on stderr, exit status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import shlex
import sys
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from common import environment, parse_setting, result_path, setting_label
from hte_jax import sharding
from hte_jax.errors import ConfigError
from hte_jax.flat.store import load_flat, shipped_flat_path
from hte_jax.geometry import planar_pose, relative_pose
from hte_jax.hbr.hierarchy import execute_skill
from hte_jax.hbr.store import load_hbr, shipped_hbr_path
from hte_jax.online.action import ONLINE_LIMITS
from hte_jax.qd.io import CheckpointError
from hte_jax.sim.damage import DAMAGE_PARTS, Damage, damage_model, make_damage, stack_damages
from hte_jax.sim.env import InvalidReason, ValidityLimits
from hte_jax.sim.robot import NUM_LEGS, RobotConfig, load_robot
from hte_jax.sim.rollout import rollout, standing_state
from hte_jax.warp_calls import waited

INTACT = "intact"  # the reference condition
FRICTION = "friction"  # the floor's friction scaled, no leg damaged
# --robot: (body and links collide with the floor, validity limits)
ROBOTS = {"online": (True, ONLINE_LIMITS), "training": (False, ValidityLimits())}
REPERTOIRES = ("hbr", "flat-2d")


class Condition(NamedTuple):
    """One condition: `model` (INTACT, a damage model or FRICTION) on `leg` (None: no leg) with its `damage`
    (a `Damage` of NumPy arrays, unbatched)."""

    model: str
    leg: int | None
    damage: Damage


def parse_models(text: str) -> tuple[str, ...]:
    """Comma-separated damage models (registered ones, or FRICTION), in order; ConfigError if unknown, repeated
    or none."""
    names = tuple(name.strip() for name in text.split(",") if name.strip())
    if not names:
        raise ConfigError(f"--models: give at least one of {', '.join([*DAMAGE_PARTS, FRICTION])}")
    for name in names:
        if name != FRICTION:
            damage_model(name)  # ConfigError naming the registered models
    if len(set(names)) != len(names):
        raise ConfigError(f"--models {text!r} names a model twice")
    return names


def parse_legs(text: str) -> tuple[int, ...]:
    """Comma-separated leg indices in 0..5, in order; ConfigError if malformed, repeated or none."""
    items = [item.strip() for item in text.split(",") if item.strip()]
    if not items or not all(item.isdigit() and int(item) < NUM_LEGS for item in items):
        raise ConfigError(f"--legs {text!r}: give comma-separated leg indices in 0..{NUM_LEGS - 1}")
    legs = tuple(int(item) for item in items)
    if len(set(legs)) != len(legs):
        raise ConfigError(f"--legs {text!r} names a leg twice")
    return legs


def conditions(models: tuple[str, ...], legs: tuple[int, ...], fraction: float, friction: float) -> list[Condition]:
    """INTACT, then each model on each leg (FRICTION: once, no leg), in order. `fraction` applies to the models
    that take one; ConfigError (`make_damage`) for a fraction or friction out of range."""
    none = np.zeros(NUM_LEGS, bool)
    out = [Condition(INTACT, None, make_damage(none, xp=np))]
    make_damage(none, friction=friction, xp=np)  # checks --friction whether or not FRICTION runs
    for model in models:
        if model == FRICTION:
            out.append(Condition(FRICTION, None, make_damage(none, friction=friction, xp=np)))
            continue
        share = fraction if damage_model(model).fraction else 1.0
        for leg in legs:
            out.append(Condition(model, leg, make_damage(none | (np.arange(NUM_LEGS) == leg), model, share, xp=np)))
    return out


def sample(rng: np.random.Generator, filled, count: int) -> np.ndarray:
    """`count` of the filled rows (all if 0 or fewer filled), drawn without replacement, in row order."""
    rows = np.flatnonzero(np.asarray(filled))
    if count == 0 or count >= len(rows):
        return rows
    return np.sort(rng.choice(rows, count, replace=False))


@functools.partial(jax.jit, static_argnames=("limits",))
def hbr_outcomes(robot, hbr, genotypes, damage, start, limits):
    """HBR top-layer skills genotypes (B, 9) under `damage` (B, ...) from `start` (B, ...): final pose (B, 3)
    in the start frame, valid (B,), invalid reason bits (B,) int32 of every step, contact share (B, 6)."""
    skill = execute_skill(robot, hbr, genotypes, start, damage, limits=limits)
    reason = jnp.bitwise_or.reduce(skill.steps.invalid_reason, axis=0)
    return skill.displacement, skill.valid, reason, skill.steps.contact_fraction.mean(axis=0)


@functools.partial(jax.jit, static_argnames=("spec",))
def flat_outcomes(robot, params, damage, start, spec):
    """Flat controllers params (B, 36) under `damage` (B, ...) from `start` (B, ...) for spec.num_steps: final
    pose (B, 3) in the start frame, valid (B,), invalid reason bits (B,) int32, contact share (B, 6)."""
    result = rollout(robot, params, damage, start, spec)
    poses = planar_pose(result.base_pos, result.base_quat)
    return (relative_pose(poses[:, 0], poses[:, -1]), result.valid, result.invalid_reason,
            result.foot_contacts.mean(axis=1))


def run_all(fn, genotypes: np.ndarray, damage: Damage, start, chunk: int) -> list[np.ndarray]:
    """`fn(genotypes, damage, start)` (row-batched) on every (condition, skill) pair, condition-major (row
    c * K + k: condition c of damage / start (C, ...), skill k of genotypes (K, G)), in equal blocks of at most
    `chunk` rows (the last padded with copies of its last row): one compiled program. NumPy outputs (C * K, ...)."""
    conditions_count, skills_count = damage.legs.shape[0], genotypes.shape[0]
    total = conditions_count * skills_count
    blocks = -(-total // chunk)
    size = -(-total // blocks)
    which = np.repeat(np.arange(conditions_count), skills_count)
    skill = np.tile(np.arange(skills_count), conditions_count)
    parts = []
    for begin in range(0, total, size):
        rows = np.arange(begin, begin + size).clip(max=total - 1)
        take = min(size, total - begin)
        picked = jax.tree.map(lambda x, rows=which[rows]: jnp.asarray(x[rows]), (damage, start))
        out = waited(fn, jnp.asarray(genotypes[skill[rows]]), *picked)
        parts.append([np.asarray(x)[:take] for x in out])
    return [np.concatenate(column) for column in zip(*parts)]


def summarise(items: list[Condition], pose, valid, reason, contact) -> list[dict]:
    """One row per condition from the outcomes (C * K, ...) of `run_all` (condition 0: intact)."""
    count = len(items)
    pose, valid = pose.reshape(count, -1, 3), valid.reshape(count, -1)
    reason, contact = reason.reshape(count, -1), contact.reshape(count, -1, NUM_LEGS)
    rows = []
    for c, item in enumerate(items):
        both = valid[0] & valid[c]
        distance = np.linalg.norm(pose[c, both, :2] - pose[0, both, :2], axis=-1)
        feet = np.arange(NUM_LEGS) if item.leg is None else np.array([item.leg])
        share = float(contact[c][both][:, feet].mean()) if both.any() else None
        intact = float(contact[0][both][:, feet].mean()) if both.any() else None
        rows.append({
            "model": item.model, "leg": item.leg, "fraction": float(item.damage.fraction),
            "friction": float(item.damage.friction), "skills": int(valid.shape[1]),
            "valid": float(valid[c].mean()), "flipped": float(((reason[c] & InvalidReason.FLIPPED) != 0).mean()),
            "invalid_reasons": {flag.name: float(((reason[c] & flag) != 0).mean()) for flag in InvalidReason},
            "compared": int(both.sum()),
            "distance_median_m": float(np.median(distance)) if both.any() else None,
            "distance_p90_m": float(np.percentile(distance, 90)) if both.any() else None,
            "contact_feet": feet.tolist(), "contact": share, "contact_intact": intact,
            "contact_lost": 1.0 - share / intact if intact else None,
            "feet_contact": contact[c][both].mean(axis=0).tolist() if both.any() else None})
    return rows


def _cell(value, scale: float = 100.0, digits: int = 1) -> str:
    return "-" if value is None else f"{value * scale:.{digits}f}"


def print_table(name: str, rows: list[dict]) -> None:
    print(f"\n{name}: {rows[0]['skills']} skills per condition (distance over those valid intact and damaged)")
    print(f"{'model':<10} {'leg':>3} {'valid %':>7} {'flip %':>6} {'dist med cm':>11} {'dist p90 cm':>11} "
          f"{'contact %':>9} {'intact %':>8} {'lost %':>6}")
    for row in rows:
        leg = "-" if row["leg"] is None else str(row["leg"])
        print(f"{row['model']:<10} {leg:>3} {_cell(row['valid']):>7} {_cell(row['flipped']):>6} "
              f"{_cell(row['distance_median_m']):>11} {_cell(row['distance_p90_m']):>11} {_cell(row['contact']):>9} "
              f"{_cell(row['contact_intact']):>8} {_cell(row['contact_lost']):>6}")


def _parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--skills", type=int, default=8,
                   help="skills sampled from each repertoire (default 8; 0: every one, for a GPU)")
    p.add_argument("--models", default=",".join([*DAMAGE_PARTS, FRICTION]),
                   help=f"comma-separated damage models and/or '{FRICTION}' (default: all of them)")
    p.add_argument("--legs", default=",".join(map(str, range(NUM_LEGS))), help="legs each model damages (default 0..5)")
    p.add_argument("--fraction", type=float, default=0.5,
                   help="fraction of the models that take one: the tibia's length (shortened), the torque (weak)")
    p.add_argument("--friction", type=float, default=0.5, help=f"the floor's friction scale of '{FRICTION}'")
    p.add_argument("--robot", default="online", choices=tuple(ROBOTS),
                   help="an episode's robot and validity (online, default) or the repertoires' training ones")
    p.add_argument("--repertoires", default=",".join(REPERTOIRES), help="comma-separated: hbr, flat-2d (default both)")
    p.add_argument("--hbr", type=Path, default=None, help="HBR file (default: the shipped one)")
    p.add_argument("--flat", type=Path, default=None, help="Flat-2D repertoire file (default: the shipped one)")
    p.add_argument("--seed", type=int, default=0, help="seed of the skill samples")
    p.add_argument("--setting", default=None, help="solver setting S/L[@tol=T][@dt=D] (default: RobotConfig's)")
    p.add_argument("--reflex-tilt", type=float, default=0.0, help="RobotConfig.reflex_tilt (rad; 0: no reflex)")
    p.add_argument("--reflex-release", type=float, default=0.0, help="RobotConfig.reflex_release (rad)")
    p.add_argument("--devices", type=int, default=None, help="spread each block over the first N devices (default: all)")
    p.add_argument("--chunk", type=int, default=32768, help="rollouts per compiled call (default 32768)")
    p.add_argument("--out", type=Path, default=None, help="JSON path (default: results/damage_skills_<device>_<date>.json)")
    return p.parse_args(argv)


def _checked(args) -> tuple:
    """(conditions, repertoire kinds, RobotConfig) of the arguments; ConfigError for bad ones."""
    if args.skills < 0:
        raise ConfigError(f"--skills must be >= 0 (0: every skill), got {args.skills}")
    if args.chunk < 1:
        raise ConfigError(f"--chunk must be >= 1, got {args.chunk}")
    kinds = tuple(kind.strip() for kind in args.repertoires.split(",") if kind.strip())
    if not kinds or any(kind not in REPERTOIRES for kind in kinds) or len(set(kinds)) != len(kinds):
        raise ConfigError(f"--repertoires {args.repertoires!r}: give one or both of {', '.join(REPERTOIRES)}")
    try:
        overrides = parse_setting(args.setting) if args.setting else {}
    except ValueError as error:
        raise ConfigError(f"--setting: {error}") from None
    config = RobotConfig(**overrides, reflex_tilt=args.reflex_tilt, reflex_release=args.reflex_release,
                         body_floor_contact=ROBOTS[args.robot][0])
    items = conditions(parse_models(args.models), parse_legs(args.legs), args.fraction, args.friction)
    return items, kinds, config


def main(argv=None) -> int:
    args = _parse(argv)
    try:
        items, kinds, config = _checked(args)
        mesh = sharding.batch_mesh(args.devices)
        robot = load_robot(config)
        hbr = load_hbr(args.hbr)[0] if "hbr" in kinds else None
        flat = load_flat(args.flat or shipped_flat_path("2d"))[0] if "flat-2d" in kinds else None
    except (ConfigError, CheckpointError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if flat is not None and flat.task.descriptor != "2d":
        print(f"error: --flat {args.flat}: a {flat.task.descriptor} repertoire, not a Flat-2D one", file=sys.stderr)
        return 2
    limits = ROBOTS[args.robot][1]
    damage = stack_damages([item.damage for item in items])
    rng = np.random.default_rng(args.seed)
    began = time.perf_counter()
    with sharding.spread_over(mesh):
        start = jax.tree.map(np.asarray, standing_state(robot, jax.tree.map(jnp.asarray, damage)))
    timings = {"standing_s": time.perf_counter() - began}
    results, sampled = {}, {}
    for kind in kinds:
        began = time.perf_counter()
        if kind == "hbr":
            rows = sample(rng, hbr.top.filled, args.skills)
            genotypes = np.asarray(hbr.top.genotypes)[rows]
            fn = functools.partial(hbr_outcomes, robot, hbr, limits=limits)
        else:
            rows = sample(rng, flat[0].filled, args.skills)
            genotypes = np.asarray(flat[0].genotypes)[rows]
            spec = dataclasses.replace(flat.task.spec(), limits=limits)
            fn = functools.partial(flat_outcomes, robot, spec=spec)
        with sharding.spread_over(mesh):
            outcomes = run_all(fn, genotypes, damage, start, args.chunk)
        timings[f"{kind}_s"] = time.perf_counter() - began
        results[kind] = summarise(items, *outcomes)
        sampled[kind] = "all" if args.skills == 0 else rows.tolist()  # --skills 0: every filled cell, in order
    env = environment()
    for kind in kinds:
        print_table(kind, results[kind])
    print("\n" + ", ".join(f"{name} {seconds:.1f}" for name, seconds in timings.items()) + " (compile included)")
    command = "python benchmarks/damage_skills.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    settings = {"skills": args.skills, "models": parse_models(args.models), "legs": parse_legs(args.legs),
                "fraction": args.fraction, "friction": args.friction, "robot_kind": args.robot,
                "limits": dataclasses.asdict(limits), "seed": args.seed, "chunk": args.chunk,
                "devices": sharding.mesh_size(mesh), "robot": dataclasses.asdict(config),
                "setting": setting_label(config),
                "hbr": str(args.hbr or shipped_hbr_path()) if "hbr" in kinds else None,
                "flat": str(args.flat or shipped_flat_path("2d")) if "flat-2d" in kinds else None}
    rows = [{"repertoire": kind, **row} for kind in kinds for row in results[kind]]
    out = args.out or result_path("damage_skills", env)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"environment": env, "command": command, "settings": settings, "timings": timings,
                               "sampled_rows": sampled, "rows": rows}, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
