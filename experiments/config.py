"""Experiment configs: YAML files validated against typed schemas, with key=value overrides.

A config file names its experiment and sets that experiment's fields::

    experiment: stick_time
    seed: 0
    corrupt: true
    sweep:                      # optional: one run per entry, one combined table
      - {corrupt: false}
      - {corrupt: true}

Every experiment accepts ``seed``, ``out_dir`` and ``tiny`` (a few frames, for tests; a sweep's
entries are all checked but only its first and last run). A schema
is a dataclass deriving from :class:`ExperimentConfig` whose fields declare their type, range
and meaning in one place (:func:`motion.settings.setting`). Files are read strictly: YAML 1.2
scalars (only ``true``/``false`` are booleans, ``1e3`` is a number), no duplicate keys, every
key a field of the schema, every value of its type and in its range. Any mistake -- in the
file, an override or a sweep entry -- raises :class:`ConfigError`, one line naming the file
and line (or ``command line``), the key, what was expected and what was given.

Precedence: schema defaults < the file < ``tiny``'s reductions (the schema's ``TINY``) < the
command line < each sweep entry; a key given on the command line that a sweep entry also sets
is an error (the sweep would silently win). Only this package reads config files; ``pgm``
and ``motion`` take plain arguments.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import yaml

from motion.settings import SettingError, Settings, coerce, echo, show, unknown_key

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


class ConfigError(SettingError):
    """A config that does not match its schema (or is not valid YAML); a ``ValueError``."""


class ExperimentSkipped(RuntimeError):
    """An experiment cannot run here because its data set is absent from the default
    location (the test suite's case); the message says why. A path the user names that
    does not exist is a :class:`ConfigError` instead."""


class ExperimentConfig(Settings):
    """Base of the experiment schemas: fields checked at construction (raising
    :class:`ConfigError`); ``TINY`` maps fields to the values ``tiny=true`` gives them."""

    setting_error: ClassVar[type[SettingError]] = ConfigError
    TINY: ClassVar[dict[str, Any]] = {}


# ---------------------------------------------------------------------------- strict YAML

_TAG = "tag:yaml.org,2002:"


class _DuplicateKey(yaml.YAMLError):
    def __init__(self, key: Any, line: int, first: int):
        super().__init__(f"duplicate key {key!r}")
        self.key, self.line, self.first = key, line, first


class _Mapping(dict):
    """A mapping read from YAML, with the line (1-based) of each key in ``lines``."""

    lines: dict[Any, int]


class _StrictLoader(yaml.SafeLoader):
    """``SafeLoader`` with YAML 1.2 core scalars, duplicate keys refused and key lines kept."""


_StrictLoader.yaml_implicit_resolvers = {
    first: [
        (tag, rx)
        for tag, rx in resolvers
        if tag not in (_TAG + "bool", _TAG + "int", _TAG + "float")
    ]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_StrictLoader.add_implicit_resolver(
    _TAG + "bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)
_StrictLoader.add_implicit_resolver(
    _TAG + "int",
    re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"),
    list("-+0123456789"),
)
_StrictLoader.add_implicit_resolver(
    _TAG + "float",
    re.compile(
        r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
        r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
    ),
    list("-+.0123456789"),
)


def _construct_int(loader: _StrictLoader, node: yaml.Node) -> int:
    text = loader.construct_scalar(node).replace("_", "")
    body = text.lstrip("+-")
    return int(text, 0) if body[:2] in ("0x", "0o", "0b") else int(text)


def _construct_map(loader: _StrictLoader, node: yaml.MappingNode):
    data = _Mapping()
    yield data
    lines: dict[Any, int] = {}
    for key_node, _ in node.value:
        if key_node.tag == _TAG + "merge":
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            hash(key)
        except TypeError:
            continue  # construct_mapping reports unhashable keys
        line = key_node.start_mark.line + 1
        if key in lines:
            raise _DuplicateKey(key, line, lines[key])
        lines[key] = line
    data.update(loader.construct_mapping(node))
    data.lines = lines


_StrictLoader.add_constructor(_TAG + "int", _construct_int)
_StrictLoader.add_constructor(_TAG + "map", _construct_map)


def _yaml_problem(text: str, err: Exception) -> tuple[str, str]:
    """A YAML problem as (``:LINE:COLUMN`` or ``:LINE`` or ``""``, one-line description)."""
    if isinstance(err, _DuplicateKey):
        return f":{err.line}", (
            f"duplicate key {err.key!r} (first given on line {err.first}); expected each key once"
        )
    if isinstance(err, yaml.reader.ReaderError):
        line = text[: err.position].count("\n") + 1
        code = err.character if isinstance(err.character, int) else ord(err.character)
        return f":{line}", f"not valid YAML: character U+{code:04X} is not allowed"
    mark = getattr(err, "problem_mark", None)
    problem = " ".join(str(getattr(err, "problem", None) or err).split())
    context = getattr(err, "context", None)
    more = f" ({' '.join(context.split())})" if context else ""
    where = f":{mark.line + 1}:{mark.column + 1}" if mark is not None else ""
    return where, f"not valid YAML: {problem}{more}"


def _load_yaml(text: str, name: str, inline: bool = False) -> Any:
    """``text`` read strictly; errors name ``name`` and the line (``inline``: a one-line
    value, so ``name: problem`` without a line)."""
    try:
        return yaml.load(text, Loader=_StrictLoader)  # a SafeLoader subclass
    except yaml.YAMLError as err:
        where, problem = _yaml_problem(text, err)
        raise ConfigError(f"{name}{'' if inline else where}: {problem}") from None
    except RecursionError:
        raise ConfigError(f"{name}: not valid YAML: nested too deeply") from None
    except (ValueError, TypeError, KeyError, AttributeError, OverflowError) as err:
        # a tagged scalar the constructors cannot read (!!float x, !!bool maybe, !!timestamp 1)
        text = " ".join(f"{type(err).__name__}: {err}".split())
        raise ConfigError(
            f"{name}: not valid YAML: a tagged value cannot be read ({text})"
        ) from None


def read_yaml(path: str | Path) -> Any:
    """A YAML file read strictly (see the module docstring); mappings carry their keys'
    line numbers. Raises :class:`ConfigError` naming the file (and line) on any problem."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the config file ({err.strerror})") from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        line = data[: err.start].count(b"\n") + 1
        raise ConfigError(
            f"{path}:{line}: expected UTF-8 text; got byte 0x{data[err.start]:02x}"
        ) from None
    return _load_yaml(text, str(path))


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
            _load_yaml(text, f"command line: {echo(item)}", inline=True) if text.strip() else None
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


def _line_of(mapping: Any, key: Any, path: Path) -> str:
    line = getattr(mapping, "lines", {}).get(key)
    return f"{path}:{line}" if line else str(path)


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
    at = _line_of(raw, "experiment", path)
    if not isinstance(name, str):
        raise ConfigError(f"{at}: experiment must be one of {known}; got {show(name)}")
    if name not in schemas:
        raise ConfigError(f"{at}: unknown experiment {name!r}; known: {known}")
    schema = schemas[name]
    sweep = _sweep(body.pop("sweep", None), path, _line_of(raw, "sweep", path))
    overrides = dict(overrides or {})
    config = apply_overrides(schema(), body, lambda key: _line_of(raw, key, path))
    given = apply_overrides(config, overrides, "command line")
    if given.tiny:  # tiny replaces the file's values; the command line's stay
        tiny = {k: v for k, v in schema.TINY.items() if k not in overrides}
        config = apply_overrides(apply_overrides(config, tiny, "tiny"), overrides, "command line")
    else:
        config = given
    labels: dict[str, int] = {}
    for i, entry in enumerate(sweep):
        at = _line_of(raw, "sweep", path)
        for key in entry:
            if key in overrides:
                raise ConfigError(
                    f"command line: {key} is also set by {at}: sweep[{i}]; expected each key "
                    f"in one place (drop {key}= from the command line, or edit the sweep)"
                )
        apply_overrides(
            config, entry, lambda key, e=entry, i=i: f"{_line_of(e, key, path)}: sweep[{i}]"
        )
        label = sweep_label(entry)
        if label in labels:
            raise ConfigError(
                f"{at}: sweep[{i}] repeats sweep[{labels[label]}] ({label}); expected each run once"
            )
        labels[label] = i
    if config.tiny and len(sweep) > 2:  # every entry checked above; the first and last run
        sweep = [sweep[0], sweep[-1]]
    return name, config, [dict(entry) for entry in sweep]
