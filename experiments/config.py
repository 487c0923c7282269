"""Experiment configs: YAML files validated against typed schemas, with key=value overrides.

A config file names its experiment and sets that experiment's fields::

    experiment: stick_time
    seed: 0
    corrupt: true
    sweep:                      # optional: one run per entry, one combined table
      - {corrupt: false}
      - {corrupt: true}

Every experiment accepts ``seed``, ``out_dir`` (default ``runs/<experiment>``) and ``tiny`` (a
few frames, for tests; a sweep's entries are all checked but only its first and last run),
declared once, on :class:`ExperimentConfig`. A schema
is a dataclass deriving from :class:`ExperimentConfig` whose fields declare their type, range
and meaning in one place (:func:`motion.settings.setting`). Files are read strictly
(:mod:`motion.settings_yaml`, the reader of ``motion register --config`` too): YAML 1.2
scalars (only ``true``/``false`` are booleans, ``1e3`` is a number), no duplicate keys, every
key a field of the schema, every value of its type and in its range. Any mistake -- in the
file, an override or a sweep entry -- raises :class:`ConfigError`
(:class:`motion.settings.ConfigError`, re-exported here), one line naming the file and line
(or ``command line``), the key, what was expected and what was given.

Precedence: schema defaults < the file < ``tiny``'s reductions (the schema's ``TINY``) < the
command line < each sweep entry, except that ``tiny``'s reductions replace a sweep entry's own
value of their keys too (a tiny run stays tiny whatever its entries say); a key given on the command line that a sweep entry also sets
is an error (the sweep would silently win). Only this package (and the command lines) read
config files; ``pgm`` and ``motion``'s functions take plain arguments.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from motion.settings import (
    ConfigError,
    SettingError,
    Settings,
    coerce,
    echo,
    setting,
    show,
    unknown_key,
)
from motion.settings_yaml import line_of, load_yaml, read_yaml

__all__ = [
    "ConfigError",
    "ExperimentConfig",
    "ExperimentSkipped",
    "apply_overrides",
    "load_config",
    "parse_overrides",
    "read_yaml",
    "sweep_label",
]


class ExperimentSkipped(RuntimeError):
    """An experiment cannot run here because its data set is absent from the default
    location (the test suite's case); the message says why. A path the user names that
    does not exist is a :class:`ConfigError` instead."""


@dataclass
class ExperimentConfig(Settings):
    """Base of the experiment schemas: fields checked at construction (raising
    :class:`ConfigError`), ``seed``, ``out_dir`` and ``tiny`` declared here for every one.

    A schema says, as class variables: ``NAME``, its experiment's name (``out_dir``'s
    default is ``runs/<NAME>``); ``TINY``, the fields ``tiny=true`` reduces and their values;
    ``TINY_DOC``, what ``tiny=true`` does, in words (``python -m experiments list`` shows it
    as the meaning of ``tiny``).
    """

    setting_error: ClassVar[type[SettingError]] = ConfigError
    NAME: ClassVar[str] = ""
    TINY: ClassVar[dict[str, Any]] = {}
    TINY_DOC: ClassVar[str] = ""

    seed: int = setting(0, "seed of every random draw", ge=0, le=2**32 - 1)
    # None stands for runs/<NAME> (set by __post_init__) in Python only: a file's or the
    # command line's value is checked as a string first, so an empty value is refused there
    out_dir: str = setting(None, "output folder")
    tiny: bool = setting(False, "a quick run (fewer frames, less work), for tests")

    def __post_init__(self) -> None:
        if self.out_dir is None:
            object.__setattr__(self, "out_dir", f"runs/{self.NAME}")
        super().__post_init__()

    def gpus(self) -> int:
        """GPUs one run of this config holds while it runs (what a cluster backend asks for):
        none here; a schema with a device setting says 1 where it names ``cuda``."""
        return 0


# ------------------------------------------------------------------------------ overrides


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["a=1", "b=[x, y]"]`` -> ``{"a": 1, "b": ["x", "y"]}``: values are YAML (read as
    strictly as files); an empty value is ``None`` (which no field accepts). A missing ``=``,
    an empty key, a key given twice or a value that is not YAML raise :class:`ConfigError`."""
    out: dict[str, Any] = {}
    for item in items:
        key, eq, text = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise ConfigError(f"command line: expected key=value (e.g. seed=1); got {item!r}")
        if key in out:
            raise ConfigError(f"command line: {echo(key)} is given twice; expected each key once")
        value = (
            load_yaml(text, f"command line: {echo(item)}", inline=True) if text.strip() else None
        )
        out[key] = value
    return out


Where = str | Callable[[Any], str]


def apply_overrides(config, overrides: dict[str, Any], where: Where = "override"):
    """A copy of the schema dataclass ``config`` with ``overrides`` applied, each checked
    against its field (type, range, and that a named file exists). ``where`` prefixes the
    errors: a string, or a function of the key (to name each key's line)."""
    cls = type(config)
    fields = {f.name for f in dataclasses.fields(config)}
    changes = {}
    for key, value in overrides.items():
        at = where(key) if callable(where) else where
        if key not in fields:
            raise ConfigError(unknown_key(cls, key, at))
        changes[key] = coerce(cls, key, value, at, paths=True, error=ConfigError)
    return dataclasses.replace(config, **changes)


# ---------------------------------------------------------------------------------- files


def sweep_label(entry: dict) -> str:
    """A sweep entry's label, the suffix of its metric names: ``corrupt=True,fps=30``."""
    return ",".join(f"{k}={v}" for k, v in entry.items()) or "base"


def _sweep(value: Any, path: Path, at: str) -> list[dict]:
    """The sweep entries, each a mapping (``None`` or ``[]``: no sweep)."""
    if value is None:
        return []
    example = "e.g. [{corrupt: false}, {corrupt: true}]"
    if not isinstance(value, list):
        raise ConfigError(
            f"{at}: sweep must be a list of mappings, one per run, {example}; got {show(value)}"
        )
    for i, entry in enumerate(value):
        if not isinstance(entry, dict):
            raise ConfigError(
                f"{at}: sweep[{i}] must be a mapping of field: value, e.g. {{corrupt: false}}; "
                f"got {show(entry)}"
            )
    return value


def load_config(
    path: str | Path, schemas: dict[str, type], overrides: dict[str, Any] | None = None
):
    """Read a config file: returns (experiment name, validated config, sweep entries).

    ``overrides`` (from :func:`parse_overrides`) are applied after the file and after
    ``tiny``'s reductions, so an explicit value always wins over ``tiny``; each sweep entry
    is checked against the resulting config. Raises :class:`ConfigError`.
    """
    path = Path(path)
    raw = read_yaml(path)
    known = ", ".join(repr(k) for k in sorted(schemas))
    if not isinstance(raw, dict) or "experiment" not in raw:
        got = "an empty file" if raw is None else show(raw)
        raise ConfigError(
            f"{path}: a config must be a mapping with an 'experiment' key ({known}); got {got}"
        )
    body = dict(raw)
    name = body.pop("experiment")
    at = line_of(raw, "experiment", path)
    if not isinstance(name, str):
        raise ConfigError(f"{at}: experiment must be one of {known}; got {show(name)}")
    if name not in schemas:
        raise ConfigError(f"{at}: unknown experiment {name!r}; known: {known}")
    schema = schemas[name]
    sweep = _sweep(body.pop("sweep", None), path, line_of(raw, "sweep", path))
    overrides = dict(overrides or {})
    config = apply_overrides(schema(), body, lambda key: line_of(raw, key, path))
    given = apply_overrides(config, overrides, "command line")
    if given.tiny:  # tiny replaces the file's values; the command line's stay
        tiny = {k: v for k, v in schema.TINY.items() if k not in overrides}
        config = apply_overrides(apply_overrides(config, tiny, "tiny"), overrides, "command line")
    else:
        config = given
    labels: dict[str, int] = {}
    for i, entry in enumerate(sweep):
        at = line_of(raw, "sweep", path)
        for key in entry:
            if key in overrides:
                raise ConfigError(
                    f"command line: {key} is also set by {at}: sweep[{i}]; expected each key "
                    f"in one place (drop {key}= from the command line, or edit the sweep)"
                )
        apply_overrides(
            config, entry, lambda key, e=entry, i=i: f"{line_of(e, key, path)}: sweep[{i}]"
        )
        label = sweep_label(entry)
        if label in labels:
            raise ConfigError(
                f"{at}: sweep[{i}] repeats sweep[{labels[label]}] ({label}); expected each run once"
            )
        labels[label] = i
    if config.tiny:
        sweep = _tiny_sweep(sweep, schema.TINY, overrides)
    return name, config, [dict(entry) for entry in sweep]


def _tiny_sweep(sweep: list[dict], tiny: dict, overrides: dict) -> list[dict]:
    """A tiny run's sweep: its first and last entries (every entry was checked), each with
    ``tiny``'s reductions over its own values as over the rest of the file's (an entry's
    ``frames: 0`` would otherwise undo ``frames: 8``), the command line's kept; one entry where
    the two then coincide."""
    kept = [sweep[0], sweep[-1]] if len(sweep) > 2 else sweep
    reduced = []
    for entry in kept:
        entry = {**entry, **{k: v for k, v in tiny.items() if k in entry and k not in overrides}}
        if all(sweep_label(entry) != sweep_label(other) for other in reduced):
            reduced.append(entry)
    return reduced
