"""Options as data: frozen ``XxxOptions`` dataclasses built from nested mappings (YAML
presets, command-line and ROS parameter overrides), unknown keys rejected, and back to plain
dicts for reports and fingerprints."""

from __future__ import annotations

import dataclasses
import math
import os
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from cusfm_ros.errors import ConfigError

T = TypeVar("T")


def _field_types(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001 - unresolvable hints: fall back to no type checks
        return {}


def _nested_class(hint: Any) -> type | None:
    return hint if dataclasses.is_dataclass(hint) and isinstance(hint, type) else None


def _coerce(value: Any, hint: Any, where: str) -> Any:
    """Light type checks for YAML/parameter values: numbers, booleans, strings, tuples."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        hint = next((a for a in args if a is not type(None)), hint)
        origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true or false, got {value!r}")
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise ConfigError(f"{where}: must be finite, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    if origin is tuple:
        if isinstance(value, str) or not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        inner = args[0] if args else Any
        return tuple(_coerce(v, inner, f"{where}[{i}]") if inner in (int, float, str, bool)
                     else v for i, v in enumerate(value))
    return value


def options_from_dict(cls: type[T], data: dict[str, Any] | None, where: str,
                      reserved: dict[str, str] | None = None) -> T:
    """Build ``cls`` from a (nested) mapping; unknown keys, wrong types and invalid values
    raise ``ConfigError`` naming ``where`` and the key. ``reserved`` maps keys that may not be
    set here to the reason (options set once at the top level and handed down)."""
    at = f"{where}: " if where else ""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{at}expected a mapping of options, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{at}unknown option(s) {unknown} (known: "
                          f"{', '.join(sorted(fields))})")
    hints = _field_types(cls)
    values = {}
    for name, value in data.items():
        key = f"{where}.{name}" if where else name
        if reserved and name in reserved:
            raise ConfigError(f"{key}: {reserved[name]}")
        nested = _nested_class(hints.get(name))
        if nested is not None:
            values[name] = options_from_dict(nested, value, key, reserved)
        else:
            values[name] = _coerce(value, hints.get(name, Any), key)
    try:
        return cls(**values)
    except (ConfigError, TypeError) as exc:
        raise ConfigError(f"{at}{exc}") from None


def options_as_dict(options: Any) -> dict[str, Any]:
    """Plain nested dict (tuples as lists) of an options dataclass."""
    def plain(value):
        if isinstance(value, tuple):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        return value
    return plain(dataclasses.asdict(options))


def merge(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """``base`` updated by ``overrides`` (dotted keys ``a.b.c`` or nested mappings)."""
    out = {k: (merge(v, {}) if isinstance(v, dict) else v) for k, v in base.items()}
    for key, value in overrides.items():
        parts = key.split(".")
        target = out
        for part in parts[:-1]:
            child = target.get(part)
            if not isinstance(child, dict):
                child = {} if child is None else child
                if not isinstance(child, dict):
                    raise ConfigError(f"{key}: {part} is not a section")
                target[part] = child
            target = child
        if isinstance(value, dict) and isinstance(target.get(parts[-1]), dict):
            target[parts[-1]] = merge(target[parts[-1]], value)
        else:
            target[parts[-1]] = value
    return out


def load_config(path: str | os.PathLike) -> dict[str, Any]:
    """A YAML preset: a mapping of section name -> option mapping (and top-level values)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such config file")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file; a preset is YAML") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: invalid YAML: {exc}".replace("\n", " ")) from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of section -> options")
    return data
