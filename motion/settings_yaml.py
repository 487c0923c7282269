"""Settings files read strictly: the one YAML reader of ``motion register --config`` and of
``experiments`` (its config files and ``key=value`` overrides).

Strict means: YAML 1.2 core scalars (only ``true``/``false`` are booleans -- ``yes``, ``on``
stay text --, ``1e3`` is a number, ``010`` is ten), no duplicate keys, and every problem a
:class:`~motion.settings.ConfigError` of one line naming the file and line. Mappings come
back as :class:`LineMapping`, a ``dict`` that knows the line of each key
(:func:`line_of`), so that a bad setting can be reported at its line.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from motion.settings import ConfigError

__all__ = ["LineMapping", "line_of", "load_yaml", "read_yaml"]

_TAG = "tag:yaml.org,2002:"


class _DuplicateKey(yaml.YAMLError):
    def __init__(self, key: Any, line: int, first: int):
        super().__init__(f"duplicate key {key!r}")
        self.key, self.line, self.first = key, line, first


class LineMapping(dict):
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
    data = LineMapping()
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


def load_yaml(text: str, name: str, inline: bool = False) -> Any:
    """``text`` read strictly (mappings as :class:`LineMapping`); a problem raises
    :class:`~motion.settings.ConfigError` naming ``name`` and the line (``inline``: a
    one-line value, so ``name: problem`` without a line)."""
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
    line numbers. Raises :class:`~motion.settings.ConfigError` naming the file (and line)
    on any problem, a missing or unreadable file included."""
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
    return load_yaml(text, str(path))


def line_of(mapping: Any, key: Any, path: str | Path) -> str:
    """``PATH:LINE`` of ``key`` in a :class:`LineMapping` read from ``path`` (``PATH`` when
    the line is not known)."""
    line = getattr(mapping, "lines", {}).get(key)
    return f"{path}:{line}" if line else str(path)
