"""Loading ``XxxOptions`` dataclasses from YAML presets, rejecting unknown keys."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, TypeVar

import yaml

from cusfm_ros.errors import ConfigError

T = TypeVar("T")


def options_from_dict(cls: type[T], data: dict[str, Any] | None, where: str) -> T:
    """Build ``cls`` from a mapping; unknown keys raise ``ConfigError`` naming ``where``."""
    data = dict(data or {})
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown option(s) {unknown} (known: "
                          f"{', '.join(sorted(fields))})")
    for name, value in data.items():
        if isinstance(value, list):
            data[name] = tuple(value)
    try:
        return cls(**data)
    except TypeError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def load_config(path: str | os.PathLike) -> dict[str, Any]:
    """A YAML preset: a mapping of stage name -> option mapping."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such config file")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: invalid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of stage -> options")
    return data


def options_as_dict(options: Any) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v)
            for k, v in dataclasses.asdict(options).items()}
