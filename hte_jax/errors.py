"""Exception types raised on bad user input, the checks that raise them, and the one rule for overriding settings."""

import dataclasses
import math


class ConfigError(ValueError):
    """A configuration value is out of range or inconsistent; the message names it."""


def require_int(name: str, value, minimum: int = 1) -> None:
    """`value` must be an integer >= minimum."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {value!r}")


def require_number(name: str, value, low: float = -math.inf, high: float = math.inf, *, open_low: bool = False) -> None:
    """`value` must be a finite real in [low, high] (or (low, high] with open_low)."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > low if open_low else value >= low) and value <= high
    if not ok:
        bounds = f"{'(' if open_low else '['}{low}, {high}]"
        raise ConfigError(f"{name} must be a finite number in {bounds}, got {value!r}")


def require_choice(name: str, value, choices) -> None:
    """`value` must be one of `choices`."""
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


def convert_setting(key: str, current, value):
    """`value` read as the type of the setting's `current` value (a CLI string, say)."""
    kind = type(current)
    if isinstance(value, kind):
        return value
    try:
        return kind(value)
    except (TypeError, ValueError):
        raise ConfigError(f"setting {key!r}: cannot read {value!r} as {kind.__name__}") from None


def with_overrides(config, overrides: dict):
    """A copy of the (possibly nested, frozen) dataclass `config` with settings replaced.

    A key names a leaf setting: "field", or "a.b.field" through nested dataclass fields. Each value
    is read as its setting's current type (`convert_setting`); the copy is rebuilt with
    `dataclasses.replace`, inner dataclasses first, so every `__post_init__` check runs, and an inner
    check's message is prefixed with its path ("middle.selection must be ...").
    """
    changes: dict = {}  # field name -> new leaf value, or the changes of a nested dataclass
    for key, value in overrides.items():
        *path, name = key.split(".")
        target, pending = config, changes
        for part in path:
            target = _setting(target, part, key)
            if not _is_config(target):
                raise ConfigError(f"unknown setting {key!r}")
            pending = pending.setdefault(part, {})
        current = _setting(target, name, key)
        if _is_config(current):
            raise ConfigError(f"unknown setting {key!r}")
        pending[name] = convert_setting(key, current, value)
    return _rebuilt(config, changes)


def _is_config(value) -> bool:
    return dataclasses.is_dataclass(value) and not isinstance(value, type)


def _setting(config, name: str, key: str):
    """The current value of `config`'s settable field `name`; `key` is the whole setting's name."""
    if name not in {field.name for field in dataclasses.fields(config) if field.init}:
        raise ConfigError(f"unknown setting {key!r}")
    return getattr(config, name)


def _rebuilt(config, changes: dict):
    values = {}
    for field in dataclasses.fields(config):  # in field order, as a constructor validates them
        if field.name not in changes:
            continue
        value, current = changes[field.name], getattr(config, field.name)
        if _is_config(current):
            try:
                value = _rebuilt(current, value)
            except ConfigError as error:
                raise ConfigError(f"{field.name}.{error}") from None
        values[field.name] = value
    return dataclasses.replace(config, **values)
