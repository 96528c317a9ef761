"""The exception raised on bad user input and the checks that raise it (one-line messages naming the setting);
`integer`, `number` and `choice` declare a configuration dataclass's checked fields, `check_fields` runs them."""

import dataclasses
import math

CHECK = "check"  # dataclasses.field metadata key: (check, its bounds) of a checked field


class ConfigError(ValueError):
    """A configuration value is out of range or inconsistent; the message names it."""


def require_int(name: str, value, minimum: int = 1) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {value!r}")


def require_number(name: str, value, low: float = -math.inf, high: float = math.inf, *, open_low: bool = False) -> None:
    """`value` must be a finite real in [low, high] (or (low, high] with open_low)."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > low if open_low else value >= low) and value <= high
    if not ok:
        bounds = f"{'(' if open_low else '['}{low}, {high}]"
        raise ConfigError(f"{name} must be a finite number in {bounds}, got {value!r}")


def lookup(what: str, name, table: dict):
    """`table[name]`; a ConfigError "unknown <what>" naming the choices otherwise."""
    if name not in table:
        raise ConfigError(f"unknown {what} {name!r}; choose one of {sorted(table)}")
    return table[name]


def require_choice(name: str, value, choices) -> None:
    if value not in choices:
        raise ConfigError(f"{name} must be one of {tuple(choices)}, got {value!r}")


def require_bounds(name: str, low, high, dims: int | None = None) -> None:
    """Per-dimension bounds: same length (== dims if given), finite, low < high."""
    if len(low) != len(high) or not low or (dims is not None and len(low) != dims):
        raise ConfigError(f"{name}: low and high must be non-empty, of equal length{'' if dims is None else f' {dims}'}; "
                          f"got {len(low)} and {len(high)}")
    for i, (lo, hi) in enumerate(zip(low, high)):
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ConfigError(f"{name} dimension {i}: need finite low < high, got [{lo}, {hi}]")


def integer(default=dataclasses.MISSING, minimum: int = 1):
    """A field holding an integer >= minimum (`require_int`)."""
    return dataclasses.field(default=default, metadata={CHECK: (require_int, (minimum,), {})})


def number(default=dataclasses.MISSING, low: float = -math.inf, high: float = math.inf, *, open_low: bool = False):
    """A field holding a finite number in [low, high], or (low, high] with open_low (`require_number`)."""
    return dataclasses.field(default=default, metadata={CHECK: (require_number, (low, high), {"open_low": open_low})})


def choice(default, choices):
    """A field holding one of `choices` (`require_choice`)."""
    return dataclasses.field(default=default, metadata={CHECK: (require_choice, (choices,), {})})


def check_fields(config, prefix: str = "") -> None:
    """ConfigError unless every `integer`, `number` and `choice` field of dataclass `config` holds a valid value
    (checked in field order; messages name the field, after `prefix`: "middle samples must be ...")."""
    for field in dataclasses.fields(config):
        if CHECK in field.metadata:
            check, bounds, options = field.metadata[CHECK]
            check(prefix + field.name, getattr(config, field.name), *bounds, **options)
