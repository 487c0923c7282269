"""Experiment configs: YAML files validated against typed schemas, with key=value overrides.

A config file names its experiment and sets that experiment's fields::

    experiment: stick_time
    seed: 0
    corrupt: true
    sweep:                      # optional: one run per entry, one combined table
      - {corrupt: false}
      - {corrupt: true}

Every experiment accepts ``seed``, ``out_dir`` and ``tiny`` (a few frames, for tests). An
unknown key -- in the file, in an override or in a sweep entry -- fails loudly, naming the
known keys. Only this package reads config files; ``pgm`` and ``motion`` take plain arguments.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import yaml

__all__ = ["ConfigError", "ExperimentSkipped", "apply_overrides", "load_config", "parse_overrides"]


class ConfigError(ValueError):
    """A config that does not match its schema."""


class ExperimentSkipped(RuntimeError):
    """An experiment cannot run here (e.g. its data set is absent); the message says why."""


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["a=1", "b=x,y"]`` -> ``{"a": 1, "b": "x,y"}`` (values parsed as YAML scalars/lists)."""
    out = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"expected key=value, got {item!r}")
        key, value = item.split("=", 1)
        out[key.strip()] = yaml.safe_load(value) if value.strip() else None
    return out


def apply_overrides(config, overrides: dict[str, Any], where: str = "override"):
    """A copy of the dataclass ``config`` with ``overrides`` applied and type-checked."""
    fields = {f.name: f for f in dataclasses.fields(config)}
    changes = {}
    for key, value in overrides.items():
        if key not in fields:
            raise ConfigError(
                f"{where}: unknown key {key!r} for {type(config).__name__}; known: {', '.join(fields)}"
            )
        current = getattr(config, key)
        if current is not None and value is not None:
            if isinstance(current, bool) and not isinstance(value, bool):
                raise ConfigError(f"{where}: {key} must be true or false; got {value!r}")
            if isinstance(current, (int, float)) and not isinstance(current, bool):
                if not isinstance(value, (int, float)) or isinstance(value, bool):
                    raise ConfigError(f"{where}: {key} must be a number; got {value!r}")
                value = type(current)(value) if isinstance(current, float) else value
            if isinstance(current, str) and not isinstance(value, str):
                value = str(value)
            if isinstance(current, list) and not isinstance(value, list):
                raise ConfigError(f"{where}: {key} must be a list; got {value!r}")
        changes[key] = value
    return dataclasses.replace(config, **changes)


def load_config(
    path: str | Path, schemas: dict[str, type], overrides: dict[str, Any] | None = None
):
    """Read a config file: returns (experiment name, validated config, sweep entries)."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({err})") from None
    if not isinstance(raw, dict) or "experiment" not in raw:
        raise ConfigError(f"{path}: a config must be a mapping with an 'experiment' key")
    name = raw.pop("experiment")
    if name not in schemas:
        raise ConfigError(
            f"{path}: unknown experiment {name!r}; known: {', '.join(sorted(schemas))}"
        )
    sweep = raw.pop("sweep", None) or []
    config = apply_overrides(schemas[name](), raw, where=str(path))
    config = apply_overrides(config, overrides or {}, where="command line")
    for i, entry in enumerate(sweep):
        apply_overrides(config, entry, where=f"{path}: sweep[{i}]")  # validate early
    return name, config, sweep
