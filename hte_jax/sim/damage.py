"""Damages as parts. A `DamageModel` says what a damaged leg suffers: the pose its servos hold (`pose`), and
what it changes in the robot's model (`edit`): "raised" (the paper's "blocked in the air": femur and tibia
straight up, the foot 0.19 m above the hip), "locked" (standing, joints at 0: likely what the original simulated,
`docs/original_code.md` §10), "removed" (no mass, no inertia, no contact, no torque: RTE's damage and the
original's comment), "shortened" (the tibia at a fraction of its length, RTE's other damage), "weak" (the leg's
servos at a fraction of their torque). A `Damage` holds, per robot, the damaged legs, their model, its fraction
and the floor's friction scale (APROL's conditions), as arrays: one compiled program serves a batch that mixes
damages. A plain (6,) bool mask is the legs alone, under `RobotConfig.damage_model`. The paper's seven
conditions: each single leg and the middle legs 1+4.

A damage as the command lines spell it (`parse_damages`): comma-separated items, each
`<legs>[:<model>[=<fraction>]][:friction=<scale>]`. <legs>: none, leg<i>, legs<i>+<j> (i < j), an index of the
original's -l (-1: none, 0..5: leg<i>, 6: legs1+4), or all (the paper's seven, each with the rest of the item).
The item "suite" stands for `DAMAGE_SUITE`, the held-out conditions beside the paper's seven.
<model>: a registered damage model (default: the run's damage model); =<fraction> in (0, 1] for a model that takes
one (shortened: of the tibia's length, weak: of the torque), and only for it. friction=<scale> > 0: the floor's
friction scale. `leg0:removed`, `leg2:shortened=0.5:friction=0.6`, `none:friction=0.5` (the intact robot on a
slippery floor), `all:locked`."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hte_jax.errors import ConfigError
from hte_jax.sim.robot import DAMAGE_MODELS, JOINTS_PER_LEG, NUM_LEGS, RobotInfo

# (hip yaw, femur, tibia) in radians. The femur joint (+y axis) at -pi/2 turns the femur
# straight up; the tibia joint (-y axis) at +pi/2 turns the tibia up in line with it.
DAMAGED_POSE = (0.0, -np.pi / 2, np.pi / 2)

PAPER_DAMAGES: dict[str, tuple[int, ...]] = {**{f"leg{i}": (i,) for i in range(NUM_LEGS)}, "legs1+4": (1, 4)}
DAMAGE_NAMES = ("none", *PAPER_DAMAGES)
# The damage suite beside the paper's seven (`--damage suite`), never tuned on: leg pairs under the run's damage
# model (the two diagonal corner pairs, both front legs, a middle leg with the rear leg beside it), a corner and a
# middle leg's tibia at half its length, the same legs' servos at half their torque, and the intact robot on a
# floor of half the friction.
DAMAGE_SUITE = ("legs0+3", "legs2+5", "legs0+5", "legs1+2", "leg0:shortened=0.5", "leg1:shortened=0.5",
                "leg0:weak=0.5", "leg1:weak=0.5", "none:friction=0.5")
# APROL's prior conditions (paper section 5): the 6 single-leg and the 15 two-leg damages.
APROL_DAMAGES: dict[str, tuple[int, ...]] = {f"leg{i}": (i,) for i in range(NUM_LEGS)} | {
    f"legs{i}+{j}": (i, j) for i in range(NUM_LEGS) for j in range(i + 1, NUM_LEGS)}


def damage_mask(legs: Iterable[int]) -> np.ndarray:
    """(6,) bool mask with the given legs damaged."""
    mask = np.zeros(NUM_LEGS, bool)
    for leg in legs:
        if not (isinstance(leg, (int, np.integer)) and 0 <= leg < NUM_LEGS):
            raise ConfigError(f"leg index must be an integer in 0..{NUM_LEGS - 1}, got {leg!r}")
        mask[leg] = True
    return mask


def parse_damage(name: str | int) -> np.ndarray:
    """Mask for a damage name ('none', 'leg<i>', 'legs<i>+<j>', 'legs<i>+<j>+<k>'..., increasing) or the original's -l
    index (6: legs 1+4, -1: none)."""
    if isinstance(name, (int, np.integer)):
        names = list(PAPER_DAMAGES)
        if name == -1:
            return damage_mask(())
        if 0 <= name < len(names):
            return damage_mask(PAPER_DAMAGES[names[name]])
        raise ConfigError(f"unknown damage index {name}; expected -1 (none) or 0..{len(names) - 1}")
    if name == "none":
        return damage_mask(())
    if name in APROL_DAMAGES:  # the paper's too
        return damage_mask(APROL_DAMAGES[name])
    legs = name.removeprefix("legs").split("+") if name.startswith("legs") else []
    if len(legs) > 2 and all(leg.isdigit() for leg in legs):
        legs = [int(leg) for leg in legs]
        if legs == sorted(set(legs)) and legs[-1] < NUM_LEGS:
            return damage_mask(legs)
    raise ConfigError(f"unknown damage {name!r}; expected 'none', 'leg<i>' or 'legs<i>+<j>(+<k>...)' with "
                      f"0 <= i < j < k ... <= 5 (the paper's: {', '.join(DAMAGE_NAMES)})")


def paper_damage_masks() -> np.ndarray:
    """(7, 6) bool masks of the paper's conditions, in `PAPER_DAMAGES` order."""
    return np.stack([damage_mask(legs) for legs in PAPER_DAMAGES.values()])


def damage_masks(names: Iterable[str]) -> np.ndarray:
    """(N, 6) bool masks of damage names (see `parse_damage`)."""
    return np.stack([parse_damage(name) for name in names])


def damaged_joint_mask(damage: jax.Array, xp=jnp) -> jax.Array:
    """(6,) leg mask -> (18,) joint mask, leg-major joint order (jax or NumPy)."""
    return xp.repeat(damage, JOINTS_PER_LEG, axis=-1)


def damaged_pose(model: str) -> tuple[float, float, float] | None:
    """(hip yaw, femur, tibia) a damaged leg holds under damage model `model`, None: the gait's targets."""
    return damage_model(model).pose


# Model values a damage can change, per robot (MJX reads each of them in every step).
EDITED_FIELDS = ("body_mass", "body_inertia", "body_ipos", "geom_margin", "geom_pos", "geom_size", "geom_friction",
                 "actuator_forcerange")
NO_CONTACT_MARGIN = -1.0  # m: a geom this far inside another before their contact acts (never, for the hexapod)
TIBIA, FOOT = 2, 3  # a leg's tibia among its bodies, the tibia link and the foot among its geoms (RobotInfo)


def leg_rows(count: int, ids: np.ndarray, legs: jax.Array) -> jax.Array:
    """(count,) bool: the ids (6, k) of the legs `legs` (6,) bool."""
    return jnp.zeros(count, bool).at[ids.reshape(-1)].set(jnp.repeat(legs, ids.shape[1]))


@dataclasses.dataclass(frozen=True)
class DamageModel:
    """What a damaged leg suffers: `pose` (hip yaw, femur, tibia) its servos hold (None: the gait's targets),
    `fraction` whether it takes a fraction in (0, 1] (of a length, a torque), `touches` whether its foot can
    touch the floor, and `edit`, its change to the
    model values `EDITED_FIELDS` of one robot (none here). A new damage is a subclass given to
    `register_damage` (docs/extending.md)."""

    name: str
    pose: tuple[float, float, float] | None = None
    fraction: bool = False
    touches: bool = True  # whether the leg's foot can touch the floor (its contact is recorded)

    def edit(self, fields: dict[str, jax.Array], legs: jax.Array, fraction: jax.Array,
             info: RobotInfo) -> dict[str, jax.Array]:
        """`fields` of one robot with the legs `legs` (6,) bool damaged at `fraction` (a float32 scalar)."""
        return fields


class Removed(DamageModel):
    """The leg is gone: its bodies weigh nothing, its links and foot touch nothing, its servos give no torque."""

    def edit(self, fields, legs, fraction, info):
        bodies = leg_rows(fields["body_mass"].shape[0], np.asarray(info.leg_bodies), legs)
        geoms = leg_rows(fields["geom_margin"].shape[0], np.asarray(info.leg_geoms), legs)
        servos = leg_rows(fields["actuator_forcerange"].shape[0], np.asarray(info.leg_actuators), legs)
        return {**fields, "body_mass": jnp.where(bodies, 0.0, fields["body_mass"]),
                "body_inertia": jnp.where(bodies[:, None], 0.0, fields["body_inertia"]),
                "geom_margin": jnp.where(geoms, NO_CONTACT_MARGIN, fields["geom_margin"]),
                "actuator_forcerange": jnp.where(servos[:, None], 0.0, fields["actuator_forcerange"])}


class Shortened(DamageModel):
    """The tibia at `fraction` of its length below the knee: its link, its foot and its centre of mass that much
    closer to the knee along the tibia (its z axis), its mass and inertia scaled by `fraction`."""

    def edit(self, fields, legs, fraction, info):
        tibia = leg_rows(fields["body_mass"].shape[0], np.asarray(info.leg_bodies)[:, TIBIA:TIBIA + 1], legs)
        link = leg_rows(fields["geom_pos"].shape[0], np.asarray(info.leg_geoms)[:, TIBIA:TIBIA + 1], legs)
        lower = leg_rows(fields["geom_pos"].shape[0], np.asarray(info.leg_geoms)[:, TIBIA:FOOT + 1], legs)
        along = jnp.stack([jnp.float32(1.0), jnp.float32(1.0), fraction])  # x, y stay; z (down the tibia) scales
        return {**fields, "body_mass": jnp.where(tibia, fields["body_mass"] * fraction, fields["body_mass"]),
                "body_inertia": jnp.where(tibia[:, None], fields["body_inertia"] * fraction, fields["body_inertia"]),
                "body_ipos": jnp.where(tibia[:, None], fields["body_ipos"] * along, fields["body_ipos"]),
                "geom_pos": jnp.where(lower[:, None], fields["geom_pos"] * along, fields["geom_pos"]),
                "geom_size": jnp.where(link[:, None], fields["geom_size"] * along, fields["geom_size"])}


class Weak(DamageModel):
    """The leg's servos at `fraction` of their torque."""

    def edit(self, fields, legs, fraction, info):
        servos = leg_rows(fields["actuator_forcerange"].shape[0], np.asarray(info.leg_actuators), legs)
        forces = fields["actuator_forcerange"]
        return {**fields, "actuator_forcerange": jnp.where(servos[:, None], forces * fraction, forces)}


DAMAGE_PARTS: dict[str, DamageModel] = {model.name: model for model in (
    DamageModel("raised", pose=DAMAGED_POSE), DamageModel("locked", pose=(0.0, 0.0, 0.0)),
    Removed("removed", touches=False), Shortened("shortened", fraction=True), Weak("weak", fraction=True))}
assert tuple(DAMAGE_PARTS)[:len(DAMAGE_MODELS)] == DAMAGE_MODELS


def register_damage(model: DamageModel) -> None:
    """Add a damage model (before anything simulates with it: compiled programs hold the models they saw)."""
    if model.name in DAMAGE_PARTS:
        raise ConfigError(f"a damage model named {model.name!r} exists")
    DAMAGE_PARTS[model.name] = model


def _table(value) -> np.ndarray:
    """(K, ...) `value(model)` of every registered damage model, in `Damage.model` order."""
    return np.asarray([value(model) for model in DAMAGE_PARTS.values()])


def damage_model(name: str) -> DamageModel:
    """The registered damage model `name` (ConfigError if none)."""
    if name not in DAMAGE_PARTS:
        raise ConfigError(f"unknown damage model {name!r}; expected one of {', '.join(DAMAGE_PARTS)}")
    return DAMAGE_PARTS[name]


@struct.dataclass
class Damage:
    """What is wrong with robots (any leading batch shape ...): legs (..., 6) bool the damaged legs; model (...,)
    int32 their damage model (index in `DAMAGE_PARTS`); fraction (...,) float32 its fraction (1: none); friction
    (...,) float32 the floor's friction scale (1: intact)."""

    legs: jax.Array
    model: jax.Array
    fraction: jax.Array
    friction: jax.Array


def make_damage(legs, model: str = "raised", fraction: float = 1.0, friction: float = 1.0, xp=jnp) -> Damage:
    """A `Damage` of legs (..., 6) bool under one model; ConfigError for a fraction or friction out of range."""
    part = damage_model(model)
    if not (0.0 < fraction <= 1.0):
        raise ConfigError(f"damage fraction must be in (0, 1], got {fraction!r}")
    if fraction != 1.0 and not part.fraction:
        raise ConfigError(f"damage model {model!r} takes no fraction")
    if not friction > 0.0:
        raise ConfigError(f"floor friction scale must be > 0, got {friction!r}")
    legs = xp.asarray(legs, bool)
    batch = legs.shape[:-1]
    return Damage(legs=legs, model=xp.full(batch, list(DAMAGE_PARTS).index(model), xp.int32),
                  fraction=xp.full(batch, fraction, xp.float32), friction=xp.full(batch, friction, xp.float32))


def as_damage(damage, model: str, xp=jnp) -> Damage:
    """`damage` itself, or a plain (..., 6) bool leg mask as a `Damage` under `model` (`RobotConfig.damage_model`)."""
    return damage if isinstance(damage, Damage) else make_damage(damage, model, xp=xp)


def stack_damages(damages: Iterable[Damage], xp=np) -> Damage:
    """Unbatched damages stacked into one `Damage` (N, ...)."""
    return jax.tree.map(lambda *fields: xp.stack(fields), *damages)


def batch_damage(damage, batch: int):
    """`damage` (a (6,) or (batch, 6) bool leg mask, or a `Damage` unbatched or batched) with a leading batch axis."""
    if isinstance(damage, Damage):
        return jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *jnp.shape(x)[jnp.ndim(damage.legs) - 1:])), damage)
    return jnp.broadcast_to(damage, (batch, NUM_LEGS))


def mask_if_plain(damage: Damage, model: str):
    """`damage`'s legs (..., 6) bool (NumPy) when that plain leg mask under damage model `model` says the same:
    every robot's model is `model` and its floor intact (its fraction is then 1); else `damage` itself. A rollout
    of the mask keeps the program of a mask (`edits_model`)."""
    index = list(DAMAGE_PARTS).index(damage_model(model).name)
    plain = (np.all(np.asarray(damage.model) == index) and np.all(np.asarray(damage.fraction) == 1.0)
             and np.all(np.asarray(damage.friction) == 1.0))
    return np.asarray(damage.legs, bool) if plain else damage


def damage_legs(damage) -> jax.Array:
    """The damaged legs (..., 6) bool of `damage` (a `Damage` or a plain leg mask), whatever their model."""
    return damage.legs if isinstance(damage, Damage) else damage


def edits_model(damage, model: str) -> bool:
    """Whether `damage` (a `Damage`, or a leg mask under damage model `model`) may change model values, not only
    the servos' targets: any `Damage` (its models and friction are data), or a mask whose model has its own `edit`.
    Known before tracing: it decides which program runs."""
    return isinstance(damage, Damage) or type(damage_model(model)).edit is not DamageModel.edit


def held_targets(targets, damage: Damage, xp=jnp):
    """targets (18,) rad with each damaged leg that holds a pose (`DamageModel.pose`) set to it (jax or NumPy)."""
    holds = damage.legs & xp.asarray(_table(lambda model: model.pose is not None))[damage.model]
    pose = xp.tile(xp.asarray(_table(lambda model: model.pose or (0.0, 0.0, 0.0)), targets.dtype)[damage.model],
                   NUM_LEGS)
    return xp.where(damaged_joint_mask(holds, xp), pose, targets)


def touching_feet(damage: Damage) -> jax.Array:
    """(6,) bool: the feet that can touch the floor (not those of a leg whose damage model removes it)."""
    return ~(damage.legs & ~jnp.asarray(_table(lambda model: model.touches))[damage.model])


def edited_fields(fields: dict, damage: Damage, info: RobotInfo) -> dict[str, jax.Array]:
    """One robot's model values `EDITED_FIELDS` with `damage` (unbatched) applied: every damage model's `edit` for
    its legs, then the floor's and the feet's friction scaled (a contact's is the larger of its two geoms')."""
    fields = {name: jnp.asarray(fields[name]) for name in EDITED_FIELDS}
    for index, part in enumerate(DAMAGE_PARTS.values()):
        fields = part.edit(fields, damage.legs & (damage.model == index), damage.fraction, info)
    surfaces = np.zeros(fields["geom_friction"].shape[0], bool)
    surfaces[[info.floor_geom, *info.foot_geoms]] = True
    fields["geom_friction"] = jnp.where(surfaces[:, None], fields["geom_friction"] * damage.friction,
                                        fields["geom_friction"])
    return fields


def edited_model(model, damage: Damage, info: RobotInfo):
    """One robot's MJX `model` with `damage` (unbatched) applied (`edited_fields`)."""
    return model.replace(**edited_fields({name: getattr(model, name) for name in EDITED_FIELDS}, damage, info))


def edited_native_model(model, damage: Damage, info: RobotInfo):
    """A copy of the native MuJoCo `model` with `damage` (unbatched) applied (`edited_fields`)."""
    edited = edited_fields({name: getattr(model, name) for name in EDITED_FIELDS}, damage, info)
    copy = model.__copy__()
    for name, values in edited.items():
        getattr(copy, name)[:] = np.asarray(values, np.float64)
    return copy


def legs_label(legs) -> str:
    """The name of a leg mask (6,): none, leg<i> or legs<i>+<j>(+...)."""
    damaged = [int(leg) for leg in np.flatnonzero(np.asarray(legs, bool))]
    if not damaged:
        return "none"
    return f"leg{damaged[0]}" if len(damaged) == 1 else "legs" + "+".join(map(str, damaged))


def _number(text: str) -> str:
    """The shortest decimal that reads back as the float32 of `text` (a label's spelling of a value)."""
    return np.format_float_positional(np.float32(float(text)), trim="-")


def damage_label(damage: Damage, model: str) -> str:
    """The canonical spelling of an unbatched `damage` in a run whose damage model is `model` (what `parse_damages`
    reads back to it): its legs' name, ":<model>" unless it is `model` (with "=<fraction>" for a model that takes
    one), ":friction=<scale>" unless the floor is intact."""
    label = legs_label(damage.legs)
    part = list(DAMAGE_PARTS.values())[int(damage.model)]
    if part.name != model or part.fraction:
        label += f":{part.name}" + (f"={_number(damage.fraction)}" if part.fraction else "")
    if float(damage.friction) != 1.0:
        label += f":friction={_number(damage.friction)}"
    return label


def _value(item: str, name: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not np.isfinite(value):
        raise ConfigError(f"damage {item!r}: {name} must be a number, got {text!r}")
    return value


def _parse_item(item: str, model: str) -> list[tuple[str, Damage]]:
    """(label, unbatched NumPy `Damage`) of one item of `parse_damages` (the paper's seven for `all`)."""
    legs, *parts = item.split(":")
    legs = legs.strip()
    chosen, fraction, friction = None, None, None
    for part in (p.strip() for p in parts):
        key, equals, value = part.partition("=")
        key = key.strip()
        if not key:
            raise ConfigError(f"damage {item!r}: empty part; expected <legs>[:<model>[=<fraction>]][:friction=<scale>]")
        if key == "friction":
            if friction is not None or not equals:
                raise ConfigError(f"damage {item!r}: give friction once, as friction=<scale>")
            friction = _value(item, "friction", value.strip())
            continue
        if chosen is not None:
            raise ConfigError(f"damage {item!r}: names two damage models ({chosen!r}, {key!r})")
        if key not in DAMAGE_PARTS:
            raise ConfigError(f"damage {item!r}: unknown damage model {key!r}; expected one of {', '.join(DAMAGE_PARTS)}"
                              " or friction=<scale>")
        chosen = key
        if equals:
            fraction = _value(item, "fraction", value.strip())
            if not damage_model(chosen).fraction:
                raise ConfigError(f"damage {item!r}: damage model {chosen!r} takes no fraction")
        elif damage_model(chosen).fraction:
            raise ConfigError(f"damage {item!r}: damage model {chosen!r} needs a fraction in (0, 1]: {chosen}=<fraction>")
    if legs == "all":
        names = list(PAPER_DAMAGES)
    else:
        names = [legs_label(parse_damage(int(legs) if legs.lstrip("-").isdigit() else legs))]
    if names == ["none"] and chosen is not None:
        raise ConfigError(f"damage {item!r}: none damages no leg, so it takes no damage model (only friction=<scale>)")
    part = damage_model(model) if chosen is None else damage_model(chosen)
    out = []
    for name in names:
        try:  # make_damage checks the fraction's and the friction's ranges
            damage = make_damage(parse_damage(name), part.name, 1.0 if fraction is None else fraction,
                                 1.0 if friction is None else friction, xp=np)
        except ConfigError as error:
            raise ConfigError(f"damage {item!r}: {error}") from None
        out.append((damage_label(damage, model), damage))
    return out


def parse_damages(text: str, model: str = "raised") -> dict[str, Damage]:
    """label -> unbatched NumPy `Damage` of each damage that `text` spells (the module's docstring: comma-separated
    items, "all" the paper's seven, "suite" `DAMAGE_SUITE`), in order, under the run's damage model `model` where
    an item names none; labels are canonical (`damage_label`). ConfigError, one line, for a bad item or a damage named twice."""
    damage_model(model)
    damages: dict[str, Damage] = {}
    items = [i.strip() for i in text.split(",")]
    for item in [part for i in items for part in (DAMAGE_SUITE if i == "suite" else (i,))]:
        if not item:
            continue
        for label, damage in _parse_item(item, model):
            if label in damages:
                raise ConfigError(f"damages: {text!r} names the damage {label!r} twice")
            damages[label] = damage
    if not damages:
        raise ConfigError("damages: give 'all' or at least one damage")
    return damages
