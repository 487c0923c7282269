"""Settings that check themselves: each dataclass field declares its type, range and meaning.

A settings class is a dataclass deriving from :class:`Settings` whose fields are made with
:func:`setting`, one place per field::

    @dataclass
    class Config(Settings):
        fps: float = setting(25.0, "video frame rate (Hz)", gt=0, le=1000)

The annotation gives the type (``bool``, ``int``, ``float``, ``str``, ``list[...]`` of those,
``tuple[float, ...]`` or ``tuple[float, float, float]`` (kept a tuple, of that length),
``dict[str, float]``, another :class:`Settings` class (a nested group of settings, its
default a ``default_factory``; given as an instance, or as a mapping of its keys), or any other
class whose values are listed as ``choices``; optionally ``... | None``); the metadata gives the
range, the allowed choices and a one-line meaning. A field declared ``opaque=True`` (a schedule
object, a plain dataclass of a lower layer) is not checked, not read from text and not
settable in a file (shown so by :func:`describe`).
Construction checks every field (``__post_init__``); :func:`coerce` checks one value as it
arrives (from YAML or from Python), :func:`from_text` parses the text of a ``key=value``
command-line setting, :func:`describe` lists the fields (plain text, for ``--help``) and
:func:`unknown_key` words the error for a key that is not a field. Every failure is a
:class:`SettingError` (a ``ValueError``, or the class's ``setting_error`` subclass) of one
line: ``WHERE: KEY must be EXPECTED; got GIVEN``; a settings file or command line that does
not fit is a :class:`ConfigError` (one class for ``motion register`` and ``experiments``).
"""

from __future__ import annotations

import copy
import dataclasses
import datetime
import difflib
import functools
import math
import numbers
import os
import re
import textwrap
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

__all__ = [
    "ConfigError",
    "SettingError",
    "Settings",
    "coerce",
    "describe",
    "echo",
    "from_text",
    "is_opaque",
    "setting",
    "show",
    "unknown_key",
]


class SettingError(ValueError):
    """A setting outside its declared type or range (the message names it, what was
    expected and what was given)."""


class ConfigError(SettingError):
    """A settings file, ``key=value`` override or sweep entry that does not fit its settings
    (or is not valid YAML): one line naming where (file and line, or ``command line``), the
    key, what was expected and what was given. The one error class of ``motion register``'s
    settings (:mod:`motion.registration.config`) and of ``experiments`` (its configs)."""


@dataclass(frozen=True)
class Spec:
    """What one field accepts (the metadata :func:`setting` attaches to a field).

    Attributes:
        doc: one-line meaning, plain text (shown by ``--help``).
        ge, gt, le, lt: bounds of a number (or of every number of a list or mapping).
        choices: allowed values of a string (or of every string of a list), or of a field of
            another class (``torch.dtype``: ``(torch.float32, torch.float64)``).
        length: exact length of a list; min_length: its least length.
        sep: characters separating a list's items in command-line text (``"x,"``: either).
        example: the command-line text form, shown in errors and help (e.g. ``"320x240"``).
        path: ``"file"`` or ``"dir"``: the value names one that must exist (checked when
            :func:`coerce` is asked to, i.e. for values a user gave, not for defaults).
        opaque: the value is not checked, parsed from text or settable in a file (only
            Python code sets it); its annotation may be any type.
    """

    doc: str = ""
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple[Any, ...] | None = None
    length: int | None = None
    min_length: int | None = None
    sep: str = ","
    example: str | None = None
    path: str | None = None
    opaque: bool = False


#: the text that says a field is set only by Python code (help, templates, errors)
NOT_SETTABLE = "(not settable in a file)"


def setting(
    default: Any = dataclasses.MISSING,
    doc: str = "",
    *,
    default_factory: Any = dataclasses.MISSING,
    **spec: Any,
) -> Any:  # a dataclasses.Field
    """A dataclass field with its checks: ``setting(default, "meaning", gt=0, ...)`` (see
    :class:`Spec` for the keywords). Mutable defaults (lists, dicts) are copied per instance;
    a group of settings or an object takes ``default_factory`` instead of ``default``."""
    if "choices" in spec and spec["choices"] is not None:
        spec["choices"] = tuple(spec["choices"])
    meta = {"setting": Spec(doc=doc, **spec)}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    if isinstance(default, (list, dict)):
        return dataclasses.field(
            default_factory=functools.partial(copy.deepcopy, default), metadata=meta
        )
    return dataclasses.field(default=default, metadata=meta)


@dataclass(frozen=True)
class _Type:
    """A field's type: ``base`` is bool, int, float, str, list, tuple, dict or another class
    (whose values the field's ``choices`` list); ``item`` the type of a list's or tuple's
    items or a mapping's values; ``length`` a fixed-length tuple's length."""

    base: type
    item: _Type | None = None
    optional: bool = False
    length: int | None = None


#: the types :func:`_coerce` reads itself (any other class needs ``choices``)
_KNOWN = (bool, int, float, str, list, tuple, dict)


def _parse_type(annotation: Any) -> _Type:
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        rest = [a for a in args if a is not type(None)]
        if len(rest) != 1:
            raise TypeError(f"unsupported setting type {annotation!r}")
        return dataclasses.replace(_parse_type(rest[0]), optional=True)
    if annotation in (bool, int, float, str):
        return _Type(annotation)
    if origin is list or annotation is list:
        return _Type(list, _parse_type(args[0]) if args else _Type(str))
    if origin is tuple or annotation is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return _Type(tuple, _parse_type(args[0]))
        if not args or len(set(args)) != 1:
            raise TypeError(f"unsupported setting type {annotation!r} (one item type only)")
        return _Type(tuple, _parse_type(args[0]), length=len(args))
    if origin is dict:
        return _Type(dict, _parse_type(args[1]))
    if isinstance(annotation, type) and origin is None and annotation not in _KNOWN:
        return _Type(annotation)  # values listed by the field's choices (checked by _fields)
    raise TypeError(f"unsupported setting type {annotation!r}")


#: the type of an opaque field (its annotation is not read)
_OPAQUE = _Type(object, optional=True)


def _group(t: _Type) -> bool:
    """Whether ``t`` is a nested group of settings (a :class:`Settings` class)."""
    return isinstance(t.base, type) and issubclass(t.base, Settings)


@functools.cache
def _fields(cls: type) -> dict[str, tuple[_Type, Spec]]:
    """Field name -> (type, spec) of a settings dataclass (cached per class)."""
    hints = typing.get_type_hints(cls)
    out = {}
    for f in dataclasses.fields(cls):
        spec = f.metadata.get("setting", Spec())
        out[f.name] = (_OPAQUE if spec.opaque else _parse_type(hints[f.name]), spec)
    for name, (t, spec) in out.items():
        if t.base not in _KNOWN and not spec.choices and not spec.opaque and not _group(t):
            raise TypeError(f"{cls.__name__}.{name}: a {t.base.__name__} setting needs choices")
    return out


def _num(x: float) -> str:
    """A bound or default as written: ``0``, ``0.018``, ``4294967295``."""
    if float(x).is_integer() and abs(x) < 1e15:
        return str(int(x))
    return f"{x:g}"


def show(value: Any, limit: int = 80) -> str:
    """A value as a user would write it, for messages: ``nothing`` for an empty value,
    strings quoted, ``true``/``false``, lists and mappings in YAML flow style (truncated)."""
    if value is None:
        return "nothing (an empty value)"
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, str):
        text = repr(value)
    elif isinstance(value, Mapping):
        text = (
            "{"
            + ", ".join(
                f"{k if isinstance(k, str) else show(k)}: {show(v)}" for k, v in value.items()
            )
            + "}"
        )
    elif isinstance(value, (list, tuple)):
        text = "[" + ", ".join(show(v) for v in value) + "]"
    else:
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def echo(text: str) -> str:
    """Text a user typed, for a message: as typed, or quoted with escapes if it holds
    characters that do not print (a newline would break the one-line message)."""
    return text if text.isprintable() else repr(text)


def _range(spec: Spec) -> str:
    """``"> 0"``, ``"in [0, 1)"``, ... or ``""`` for an unbounded number."""
    low = (f"({_num(spec.gt)}" if spec.gt is not None else None) or (
        f"[{_num(spec.ge)}" if spec.ge is not None else None
    )
    high = (f"{_num(spec.lt)})" if spec.lt is not None else None) or (
        f"{_num(spec.le)}]" if spec.le is not None else None
    )
    if low and high:
        return f"in {low}, {high}"
    if low:
        return ("> " if spec.gt is not None else ">= ") + low[1:]
    if high:
        return ("< " if spec.lt is not None else "<= ") + high[:-1]
    return ""


def _scalar(t: _Type, spec: Spec, plural: bool = False) -> str:
    """What a scalar of type ``t`` must be, with its range (``"a number > 0"``)."""
    if t.base is bool:
        return "true or false"
    if t.base not in _KNOWN:
        return "one of " + ", ".join(show(c) for c in spec.choices)
    if t.base is str:
        if spec.choices:
            return "one of " + ", ".join(repr(c) for c in spec.choices)
        if spec.path:
            noun = "file" if spec.path == "file" else "folder"
            return f"{noun} paths" if plural else f"a {noun} path"
        return "strings" if plural else "a string"
    noun = {int: ("an integer", "integers"), float: ("a number", "numbers")}[t.base][plural]
    bounds = _range(spec)
    return f"{noun} {bounds}" if bounds else noun


def expected(t: _Type, spec: Spec) -> str:
    """What a value of type ``t`` under ``spec`` must be, in words."""
    if spec.opaque:
        return f"an object {NOT_SETTABLE}"
    if _group(t):
        text = f"a group of settings ({t.base.__name__}: a mapping of its keys)"
    elif t.base in (list, tuple):
        length = t.length if t.length is not None else spec.length
        lead = "a list of"
        if length is not None:
            lead = f"a list of {length}"
        elif spec.min_length == 1:
            lead = "a non-empty list of"
        elif spec.min_length:
            lead = f"a list of at least {spec.min_length}"
        items = _scalar(t.item, spec, plural=True)
        if t.item.base is str and spec.choices:
            items = "names from " + ", ".join(repr(c) for c in spec.choices)
        text = f"{lead} {items}"
    elif t.base is dict:
        text = f"a mapping of name: {_scalar(t.item, spec)}"
    else:
        text = _scalar(t, spec)
    if spec.example:
        text += f", e.g. {spec.example}"
    return text + (", or none" if t.optional else "")


class _Bad(Exception):
    """Internal: one field's value is wrong (``key`` names it, ``message`` says how)."""

    def __init__(self, key: str, message: str):
        super().__init__(f"{key} {message}")


def _must(key: str, what: str, value: Any) -> _Bad:
    return _Bad(key, f"must be {what}; got {show(value)}")


def _check_range(key: str, value: float, spec: Spec) -> None:
    ok = (
        (spec.gt is None or value > spec.gt)
        and (spec.ge is None or value >= spec.ge)
        and (spec.lt is None or value < spec.lt)
        and (spec.le is None or value <= spec.le)
    )
    if not ok:
        raise _must(key, _range(spec), value)


def _coerce(value: Any, t: _Type, spec: Spec, key: str, paths: bool) -> Any:
    """Check (and normalise: int -> float, tuple -> list) one value; raises :class:`_Bad`."""
    if spec.opaque:
        return value
    if value is None:
        if t.optional:
            return None
        raise _must(key, expected(t, spec), value)
    base = t.base
    if _group(t):
        return _coerce_group(value, t, spec, key, paths)
    if base is bool:
        if not isinstance(value, bool):
            raise _must(key, "true or false", value)
        return value
    if base not in _KNOWN:
        if not (isinstance(value, base) and value in spec.choices):
            raise _must(key, _scalar(t, spec), value)
        return value
    if base in (int, float):
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise _must(key, _scalar(t, spec), value)
        try:
            finite = math.isfinite(value)
        except OverflowError:  # an int beyond any float
            finite = False
        if not finite:
            raise _must(key, "a finite number", value)
        if base is int and not isinstance(value, numbers.Integral):
            if not float(value).is_integer():
                raise _must(key, _scalar(t, spec), value)
        _check_range(key, value, spec)
        return int(value) if base is int else float(value)
    if base is str:
        if isinstance(value, (int, float, datetime.date)) and not isinstance(value, bool):
            value = str(value)  # a YAML scalar that was meant as text: 2024, 1.5
        if not isinstance(value, str):
            raise _must(key, _scalar(t, spec), value)
        if spec.choices and value not in spec.choices:
            raise _must(key, _scalar(t, spec), value)
        if paths and spec.path:
            _check_path(key, value, spec.path)
        return value
    if base in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise _must(key, expected(t, spec), value)
        length = t.length if t.length is not None else spec.length
        if (length is not None and len(value) != length) or (
            spec.min_length is not None and len(value) < spec.min_length
        ):
            raise _must(key, expected(t, spec), value)
        return base(_coerce(v, t.item, spec, f"{key}[{i}]", paths) for i, v in enumerate(value))
    if not isinstance(value, Mapping):  # dict
        raise _must(key, expected(t, spec), value)
    out = {}
    for name, v in value.items():
        if not isinstance(name, str):
            raise _must(f"{key} key", "a name", name)
        out[name] = _coerce(v, t.item, spec, f"{key}[{name!r}]", paths)
    return out


def _coerce_group(value: Any, t: _Type, spec: Spec, key: str, paths: bool) -> Any:
    """A nested group of settings: an instance of its class as it is, or one built from a
    mapping of its keys (each checked as its field says, then the group's own checks)."""
    cls = t.base
    if isinstance(value, cls):
        return value
    if not isinstance(value, Mapping):
        raise _must(key, expected(t, spec), value)
    fields = _fields(cls)
    values = {}
    for name, v in value.items():
        if name not in fields:
            raise _Bad(
                f"{key}.{name}", f"is not a setting of {cls.__name__}; known: {', '.join(fields)}"
            )
        values[name] = _coerce(v, *fields[name], f"{key}.{name}", paths)
    try:
        return cls(**values)
    except SettingError as err:
        raise _Bad(key, f"does not fit together: {err}") from None


def _check_path(key: str, value: str, kind: str) -> None:
    path = Path(value)
    try:
        found = path.is_file() if kind == "file" else path.is_dir()
    except OSError:  # e.g. a name too long for the file system
        found = False
    if not found:
        where = "" if path.is_absolute() else f", relative to {os.getcwd()}"
        raise _Bad(key, f"must name an existing {kind}; got {show(value)} (not found{where})")


def _prefix(where: str) -> str:
    return f"{where}: " if where else ""


def _error_class(cls: type, error: type[SettingError] | None) -> type[SettingError]:
    return error or getattr(cls, "setting_error", SettingError)


def coerce(
    cls: type,
    key: str,
    value: Any,
    where: str = "",
    *,
    paths: bool = False,
    error: type[SettingError] | None = None,
) -> Any:
    """``value`` checked against field ``key`` of the settings class ``cls`` (ints become
    floats for float fields, tuples lists); with ``paths``, values naming files or folders
    must exist. Raises ``error`` (default: the class's ``setting_error``) prefixed by
    ``where``; an unknown ``key`` raises it too (see :func:`unknown_key`)."""
    fields = _fields(cls)
    if key not in fields:
        raise _error_class(cls, error)(unknown_key(cls, key, where))
    t, spec = fields[key]
    try:
        return _coerce(value, t, spec, key, paths)
    except _Bad as bad:
        raise _error_class(cls, error)(f"{_prefix(where)}{bad}") from None


def is_opaque(cls: type, key: str) -> bool:
    """Whether field ``key`` of the settings class ``cls`` is declared ``opaque`` (set only
    by Python code, not checked; not settable in a file)."""
    return _fields(cls)[key][1].opaque


def unknown_key(cls: type, key: Any, where: str = "", noun: str = "key") -> str:
    """The message for a key that is not a field of ``cls``: the close matches, then all."""
    names = list(_fields(cls))
    close = difflib.get_close_matches(str(key), names, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return (
        f"{_prefix(where)}unknown {noun} {key!r} for {cls.__name__}{hint}; "
        f"known: {', '.join(names)}"
    )


def _text_item(text: str, t: _Type) -> Any:
    """One scalar from command-line text (left as text when it does not parse: then
    :func:`_coerce` says what was expected)."""
    s = text.strip()
    if t.optional and s.lower() in ("none", "null"):
        return None
    if s == "":
        return None
    if t.base is bool:
        return {"true": True, "1": True, "false": False, "0": False}.get(s.lower(), s)
    if t.base in (int, float):
        for parse in (int, float):
            try:
                return parse(s)
            except ValueError:
                pass
        return s
    return s


def _text_value(text: str, t: _Type, spec: Spec, key: str) -> Any:
    if spec.opaque:
        raise _Bad(key, f"is not settable from text {NOT_SETTABLE}; got {show(text)}")
    if _group(t):
        raise _Bad(
            key, f"is a group of settings ({t.base.__name__}), not one value; got {show(text)}"
        )
    s = text.strip()
    empty = s == "" or (t.optional and s.lower() in ("none", "null"))
    if t.base not in _KNOWN and not empty:  # one of the choices, as printed (torch.float64)
        return next((c for c in spec.choices if str(c) == s), s)
    if t.base not in (list, tuple, dict) or empty:
        return _text_item(text, t)
    if t.base in (list, tuple):
        return [_text_item(p, t.item) for p in re.split(f"[{re.escape(spec.sep)}]", s)]
    out: dict[str, Any] = {}
    for pair in filter(None, (p.strip() for p in s.split(","))):
        name, colon, amount = pair.partition(":")
        if not colon or not name.strip():
            raise _must(key, expected(t, spec), text)
        if name.strip() in out:
            raise _Bad(key, f"names {name.strip()!r} twice; got {show(text)}")
        out[name.strip()] = _text_item(amount, t.item)
    return out


def from_text(
    cls: type, key: str, text: str, where: str = "", *, error: type[SettingError] | None = None
) -> Any:
    """The value of field ``key`` of ``cls`` from command-line text: numbers, ``true`` /
    ``false``, ``none`` (optional fields), lists as items separated by the field's ``sep``
    (``0.4,0.5``, ``320x240``), mappings as ``name:number`` pairs separated by commas.
    Checked as by :func:`coerce` (paths included); raises ``error`` prefixed by ``where``."""
    fields = _fields(cls)
    if key not in fields:
        raise _error_class(cls, error)(unknown_key(cls, key, where, noun="setting"))
    t, spec = fields[key]
    try:
        return _coerce(_text_value(text, t, spec, key), t, spec, key, True)
    except _Bad as bad:
        raise _error_class(cls, error)(f"{_prefix(where)}{bad}") from None


def _text_form(value: Any, t: _Type, spec: Spec) -> str:
    """A default in the command-line syntax of :func:`from_text`."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return spec.sep[0].join(_text_form(v, t.item, spec) for v in value) or "empty"
    if isinstance(value, dict):
        return ",".join(f"{k}:{_num(v)}" for k, v in value.items()) or "empty"
    if isinstance(value, float):
        return _num(value)
    return str(value)


def describe(
    cls: type,
    text_syntax: bool = True,
    width: int = 100,
    prefix: str = "",
    meanings: dict[str, str] | None = None,
) -> list[str]:
    """Plain-text help lines for the fields of ``cls``: name, default, what it accepts and
    its meaning (defaults in command-line syntax, or YAML's when ``text_syntax`` is false);
    a nested group's fields follow its line, dotted (``prefix``: the group's key and a dot).
    ``meanings`` replaces the declared meaning of the (top-level) fields it names (e.g. a
    base class's generic field that each subclass explains its own way)."""
    lines = []
    meanings = meanings or {}
    defaults = cls()
    for name, (t, spec) in _fields(cls).items():
        value = getattr(defaults, name)
        if spec.opaque:
            lines.append(f"  {prefix}{name}: {show(value, limit=60)} {NOT_SETTABLE}")
        elif _group(t):
            lines.append(f"  {prefix}{name}: a group of settings ({t.base.__name__})")
        else:
            default = _text_form(value, t, spec) if text_syntax else show(value, limit=60)
            lines.append(f"  {prefix}{name} (default {default}): {expected(t, spec)}")
        doc = meanings.get(name, spec.doc)
        if doc:
            lines += textwrap.wrap(doc, width, initial_indent="      ", subsequent_indent="      ")
        if _group(t) and not spec.opaque:
            lines += describe(t.base, text_syntax, width, f"{prefix}{name}.")
    return lines


class Settings:
    """Mixin for settings dataclasses: every field is checked at construction (and by
    :meth:`validate`), raising ``setting_error`` prefixed by the class name."""

    setting_error: ClassVar[type[SettingError]] = SettingError

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Check (and normalise) every field; subclasses add checks across fields (frozen
        dataclasses too: a normalised value is set past ``__setattr__``)."""
        for name in _fields(type(self)):
            value = coerce(type(self), name, getattr(self, name), type(self).__name__)
            object.__setattr__(self, name, value)
