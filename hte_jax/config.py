"""Overriding, storing and reading nested configuration dataclasses: a nested configuration's settings are
"bottom.<name>", or, for a field declared with `inline(...)`, the parent's own ("iterations", stored flat)."""

import copy
import dataclasses
import functools
import typing

from hte_jax.errors import ConfigError

INLINE = "inline"  # dataclasses.field metadata key of an inlined nested configuration (`inline`)


def convert_setting(key: str, current, value):
    """`value` read as the type of the setting's `current` value (a CLI string, say)."""
    kind = type(current)
    if isinstance(value, kind):
        return value
    try:
        return kind(value)
    except (TypeError, ValueError):
        raise ConfigError(f"setting {key!r}: cannot read {value!r} as {kind.__name__}") from None


def inline(default):
    """A nested configuration field whose settings read as the parent's own (their names must differ from its)."""
    return dataclasses.field(default=default, metadata={INLINE: True})


def with_overrides(config, overrides: dict):
    """A copy of the (nested, frozen) dataclass `config` with settings ("field", "a.b.field", an inlined one's alone)
    replaced, values read as their settings' types, rebuilt inner first so every check runs (messages with path)."""
    changes: dict = {}  # field name -> new leaf value, or the changes of a nested dataclass
    for key, value in overrides.items():
        *path, name = key.split(".")
        target, fields = config, []
        for part in path:
            route = _route(target, part, key)
            target = functools.reduce(getattr, route, target)
            if not _is_config(target):
                raise ConfigError(f"unknown setting {key!r}")
            fields += route
        route = _route(target, name, key)
        current = functools.reduce(getattr, route, target)
        if _is_config(current):
            raise ConfigError(f"unknown setting {key!r}")
        *outer, leaf = fields + route
        pending = changes
        for part in outer:
            pending = pending.setdefault(part, {})
        pending[leaf] = convert_setting(key, current, value)
    return _rebuilt(config, changes)


def config_dict(config) -> dict:
    """`config` as stored: `dataclasses.asdict`'s layout, an inlined configuration's settings among its parent's."""
    out = {}
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if _is_config(value) and _is_inline(field):
            out.update(config_dict(value))
        else:
            out[field.name] = config_dict(value) if _is_config(value) else copy.deepcopy(value)
    return out


def config_from_dict(cls, data: dict, base=None):
    """The configuration of dataclass `cls` that `data` describes (`config_dict`'s or `dataclasses.asdict`'s
    layout, or a mix), missing settings from `base` (default: the defaults); an unknown key is a TypeError."""
    data, values = dict(data), {}
    types = typing.get_type_hints(cls)
    for field in dataclasses.fields(cls):
        kind = types[field.name]
        if not _is_config_class(kind):
            if field.name in data:
                values[field.name] = data.pop(field.name)
            continue
        inner = data.pop(field.name, {})
        if _is_inline(field):
            inner = {**inner, **{key: data.pop(key) for key in _stored_keys(kind) if key in data}}
        inner_base = getattr(base, field.name) if base is not None else (
            None if field.default is dataclasses.MISSING else field.default)
        if not inner and inner_base is not None:
            continue  # kept as it is
        try:
            values[field.name] = config_from_dict(kind, inner, inner_base)
        except ConfigError as error:  # an inlined setting's error names it alone
            raise (error if _is_inline(field) else ConfigError(f"{field.name}.{error}")) from None
    values.update(data)
    return cls(**values) if base is None else dataclasses.replace(base, **values)


def settings(cls) -> dict[str, dataclasses.Field]:
    """Every leaf setting of configuration dataclass `cls` by its `with_overrides` key, in field order."""
    out = {}
    types = typing.get_type_hints(cls)
    for field in dataclasses.fields(cls):
        if not field.init:
            continue
        kind = types[field.name]
        if _is_config_class(kind):
            prefix = "" if _is_inline(field) else f"{field.name}."
            out.update({prefix + key: leaf for key, leaf in settings(kind).items()})
        else:
            out[field.name] = field
    return out


def _is_config(value) -> bool:
    return dataclasses.is_dataclass(value) and not isinstance(value, type)


def _is_config_class(kind) -> bool:
    return isinstance(kind, type) and dataclasses.is_dataclass(kind)


def _is_inline(field: dataclasses.Field) -> bool:
    return bool(field.metadata.get(INLINE))


def _stored_keys(cls) -> list[str]:
    """The top-level keys of `config_dict` for configurations of class `cls`."""
    types = typing.get_type_hints(cls)
    return [key for field in dataclasses.fields(cls)
            for key in (_stored_keys(types[field.name]) if _is_inline(field) else [field.name])]


def _route(config, name: str, key: str) -> list[str]:
    """The fields from `config` to its setting `name` (through inlined configurations); `key`: the full name."""
    fields = [field for field in dataclasses.fields(config) if field.init]
    if name in {field.name for field in fields}:
        return [name]
    for field in fields:
        if _is_inline(field):
            try:
                return [field.name, *_route(getattr(config, field.name), name, key)]
            except ConfigError:
                pass
    raise ConfigError(f"unknown setting {key!r}")


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
                raise (error if _is_inline(field) else ConfigError(f"{field.name}.{error}")) from None
        values[field.name] = value
    return dataclasses.replace(config, **values)
