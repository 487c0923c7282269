"""Settings of ``python -m motion register`` from a YAML file and ``key=value`` overrides.

Every tuning constant already lives in a frozen settings dataclass of its stage
(:class:`~motion.registration.video.VideoSettings`,
:class:`~motion.registration.approximate.Stage1Settings`,
:class:`~motion.registration.refine.RefineSettings`); this module only changes some of their
fields by name. A key is a dotted path through those dataclasses -- ``seed``, ``scale``, ``device``,
``video.width``, ``stage1.yaw_starts``, ``refine.particles``, ``refine.temporal.pos_std`` --
in a YAML mapping (nested or dotted) or as ``key=value`` on the command line (the value is
read as YAML: ``true``, ``3``, ``0.5``, ``none``, ``[1, 2]``). Files and values are read by the
strict YAML reader of :mod:`motion.settings_yaml` (YAML 1.2 scalars, duplicate keys refused).
A key that is not a field, or a value of another type or range than the field's, is a
:class:`ConfigError` (:class:`motion.settings.ConfigError`) of one line naming where (the file
and line, or ``command line``), the key, what was expected and what was given. Every group is
a :class:`motion.settings.Settings` (video, perception, the pipeline's scale and seed, stage1,
refine, polish, movement, findings): each value is checked against the field's declared type
and range, then the group's own checks. The fields a group declares ``opaque`` are not
settable, except the plain number fields of refine's ``connection`` and ``temporal``
(dataclasses of :mod:`motion.body.graph`).

:func:`config_template` writes every setting as such a YAML file, each with its value and its
meaning as a comment (``motion register --write-config PATH``); read back by
:func:`load_config` it gives the same settings.
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import re
import textwrap
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from motion.perception.detector import PerceptionSettings
from motion.registration.export import FindingSettings
from motion.registration.movement import MovementSettings
from motion.registration.pipeline import RegistrationSettings
from motion.registration.video import VideoSettings
from motion.settings import (
    NOT_SETTABLE,
    ConfigError,
    SettingError,
    Settings,
    coerce,
    is_opaque,
    show,
)
from motion.settings_yaml import line_of, load_yaml, read_yaml

__all__ = [
    "ConfigError",
    "RegisterConfig",
    "config_template",
    "load_config",
    "override",
    "settings_dict",
    "user_key",
]


@dataclass(frozen=True)
class RegisterConfig:
    """Everything ``motion register`` can be told.

    Attributes:
        video: how videos become features (working size, background, person, frames).
        perception: the person detector that gives 2-D joints when no ``--keypoints`` are
            given (:class:`~motion.perception.detector.PerceptionSettings`).
        registration: the pipeline's settings (stages 1-3, G, seed).
        movement: when the student counts as performing another movement than the
            reference's (:class:`MovementSettings`).
        findings: when one of the largest differences is stated (:class:`FindingSettings`).
    """

    video: VideoSettings = field(default_factory=VideoSettings)
    perception: PerceptionSettings = field(default_factory=PerceptionSettings)
    registration: RegistrationSettings = field(default_factory=RegistrationSettings)
    movement: MovementSettings = field(default_factory=MovementSettings)
    findings: FindingSettings = field(default_factory=FindingSettings)


def _flatten(values: Mapping, prefix: str = "") -> dict[str, object]:
    """Nested mappings -> dotted keys (``{"refine": {"particles": 50}}`` ->
    ``{"refine.particles": 50}``)."""
    return {key: value for key, (value, _) in _flatten_at(values, "", prefix).items()}


def _flatten_at(values: Mapping, path: str, prefix: str = "") -> dict[str, tuple[object, str]]:
    """:func:`_flatten`, each value with where it was given (``PATH:LINE`` where the
    mapping was read from the file ``path`` by :func:`motion.settings_yaml.read_yaml`)."""
    out: dict[str, tuple[object, str]] = {}
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(_flatten_at(value, path, f"{name}."))
        else:
            out[name] = (value, line_of(values, key, path))
    return out


def _fields(obj) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(obj)}


@dataclass(frozen=True)
class _Item:
    """One setting to apply: ``rest`` is the dotted path still to walk from the settings
    object at hand, ``key`` the whole key as the user wrote it (for messages)."""

    rest: str
    key: str
    value: object
    where: str


def _walked(item: _Item) -> str:
    """The part of the user's key already walked (``"refine."`` when at ``particles``)."""
    n = len(item.key) - len(item.rest)
    return item.key[:n] if n > 0 else ""


def _leaf_keys(obj, prefix: str = "") -> list[str]:
    """Every settable dotted key under the settings dataclass ``obj``."""
    keys = []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            keys += _leaf_keys(value, f"{prefix}{f.name}.")
        else:
            keys.append(f"{prefix}{f.name}")
    return keys


def _user_keys() -> list[str]:
    """Every key as the user writes it (``refine.particles``, not
    ``registration.refine.particles``)."""
    cfg = RegisterConfig()
    return (
        _leaf_keys(cfg.video, "video.")
        + _leaf_keys(cfg.perception, "perception.")
        + _leaf_keys(cfg.registration)
        + _leaf_keys(cfg.movement, "movement.")
        + _leaf_keys(cfg.findings, "findings.")
    )


def _suggest(key: str) -> list[str]:
    """Known keys close to ``key``: the same last name elsewhere, else close spellings."""
    keys = _user_keys()
    last = key.rpartition(".")[2]
    same = [k for k in keys if k.rpartition(".")[2] == last and k != key]
    return same[:3] or difflib.get_close_matches(key, keys, n=3, cutoff=0.75)


def _unknown(obj, item: _Item, fields) -> ConfigError:
    walked = _walked(item)
    close = _suggest(item.key)
    if not close:
        head = item.rest.partition(".")[0]
        names = [*fields, *(_SHORTCUTS if isinstance(obj, RegisterConfig) else ())]
        close = [walked + c for c in difflib.get_close_matches(head, names, n=3)]
    hint = f" (did you mean {' or '.join(close)}?)" if close else ""
    if isinstance(obj, RegisterConfig):
        known = (
            "video.*, perception.*, stage1.*, refine.*, polish.*, movement.*, findings.*, scale, seed, "
            "device "
            "(python -m motion register --help)"
        )
    else:
        known = ", ".join(sorted(walked + n for n in fields))
    return ConfigError(f"{item.where}: unknown setting {item.key!r}{hint}; known: {known}")


def _apply(obj, items: list[_Item]):
    """A copy of the settings dataclass ``obj`` with every item set (later items win).

    The changes to one dataclass are made by one ``dataclasses.replace``, so settings that
    are checked together (``refine.band`` against ``refine.particles``) may be given in any
    order; a check that fails names where the settings came from."""
    fields = _fields(obj)
    leaves: dict[str, object] = {}
    nested: dict[str, list[_Item]] = {}
    wheres: list[str] = []  # where each change came from
    given: list[str] = []  # the keys changed here, as the user wrote them
    for item in items:
        head, _, rest = item.rest.partition(".")
        name = _walked(item) + head
        if head not in fields:
            raise _unknown(obj, item, fields)
        current = getattr(obj, head)
        if rest:
            if not dataclasses.is_dataclass(current):
                raise ConfigError(
                    f"{item.where}: {name} is a single setting, it has no sub-settings; "
                    f"got {item.key!r}"
                )
            nested.setdefault(head, []).append(dataclasses.replace(item, rest=rest))
            continue
        if dataclasses.is_dataclass(current) and not isinstance(item.value, type(current)):
            names = ", ".join(f"{name}.{f}" for f in _fields(current))
            raise ConfigError(
                f"{item.where}: {name} is a group of settings, not one value (got "
                f"{item.value!r}); set one of {names}"
            )
        leaves[head] = _leaf(obj, head, item)
        nested.pop(head, None)  # a whole group given later replaces earlier sub-settings
        wheres.append(item.where)
        given.append(item.key)
    changes = dict(leaves)
    for head, sub in nested.items():
        changes[head] = _apply(changes.get(head, getattr(obj, head)), sub)
        wheres += [i.where for i in sub]
        given += [i.key for i in sub]
    if not changes:
        return obj
    try:
        return dataclasses.replace(obj, **changes)
    except ValueError as err:
        where = ", ".join(dict.fromkeys(wheres))
        keys = ", ".join(dict.fromkeys(given))
        raise ConfigError(f"{where}: {' '.join(str(err).split())} (given: {keys})") from None


def _leaf(obj, head: str, item: _Item):
    """``item``'s value for the field ``head`` of ``obj``: checked against the field's
    declared type and range (:func:`motion.settings.coerce`) in a settings class; in a plain
    dataclass of a lower layer (the ``Connections`` and ``Temporal`` of
    :class:`~motion.registration.refine.RefineSettings`), a number, flag or text where the
    field holds one (:func:`_plain_leaf`)."""
    name = _walked(item) + head
    if isinstance(obj, Settings):
        if is_opaque(type(obj), head):
            raise ConfigError(f"{item.where}: {name} is {NOT_SETTABLE}; got {show(item.value)}")
        try:
            return coerce(type(obj), head, item.value, paths=True)
        except SettingError as err:  # "KEY must be ...": the key as the user wrote it
            raise ConfigError(f"{item.where}: {_walked(item)}{err}") from None
    return _plain_leaf(getattr(obj, head), item.value, f"{item.where}: {name}")


def _plain_leaf(current, value, what: str):
    """``value`` for a plain dataclass's field holding ``current``: a number for a number
    (``3`` -> ``3.0`` for a float), ``true``/``false`` for a flag, text for text, and nothing
    else (its ``None`` or object stays as it is)."""
    if isinstance(current, bool):
        ok, expected = isinstance(value, bool), "true or false"
    elif isinstance(current, int | float):
        number = isinstance(value, int | float) and not isinstance(value, bool)
        ok = number and (isinstance(current, float) or isinstance(value, int))
        expected = "a number" if isinstance(current, float) else "an integer"
        value = float(value) if ok and isinstance(current, float) else value
    elif isinstance(current, str):
        ok, expected = isinstance(value, str), "a string"
    elif value is current:
        return value
    else:
        raise ConfigError(f"{what} is {NOT_SETTABLE} (it is {current!r}); got {show(value)}")
    if not ok:
        raise ConfigError(f"{what} must be {expected}; got {show(value)}")
    return value


def override(obj, key: str, value, where: str = "settings"):
    """A copy of the settings dataclass ``obj`` with the field at dotted ``key`` set to
    ``value`` (checked as :func:`load_config` checks it)."""
    return _apply(obj, [_Item(key, key, value, where)])


#: top-level shortcuts: ``seed=1`` means ``registration.seed=1``, ``device=cuda`` ``registration.device=cuda``
_SHORTCUTS = ("seed", "scale", "device", "stage1", "refine", "polish")


def _route(key: str) -> str:
    head = key.partition(".")[0]
    return f"registration.{key}" if head in _SHORTCUTS else key


def _parse_assignment(item: str) -> tuple[str, object]:
    key, eq, text = item.partition("=")
    key = key.strip()
    if not eq or not key:
        raise ConfigError(
            f"expected a setting as key=value (e.g. refine.particles=50); got {item!r}"
        )
    return key, parse_value(text)


def parse_value(text: str) -> object:
    """A setting's value written as text, read as the command line reads ``key=value``:
    a YAML scalar or list (``0.15``, ``true``, ``[1, 2]``), ``none`` / ``null`` (or nothing)
    for None, any other text as itself (the field's check says whether it fits)."""
    try:
        value = load_yaml(text, "command line", inline=True) if text.strip() else None
    except ConfigError:  # not YAML: the text itself (the field's check says if it fits)
        value = text
    if isinstance(value, str) and value.lower() in ("none", "null"):
        value = None
    return value


def load_config(
    path: str | Path | None = None, overrides: list[str] | None = None
) -> RegisterConfig:
    """The defaults, changed by the YAML file at ``path`` (if any), then by ``overrides``
    (``["refine.particles=50", "video.width=240"]``; later ones win)."""
    cfg = RegisterConfig()
    values: list[tuple[str, object, str]] = []
    if path is not None:
        path = Path(path)
        loaded = read_yaml(path)  # strict: duplicate keys refused, problems at their line
        if loaded is None:
            loaded = {}
        if not isinstance(loaded, Mapping):
            raise ConfigError(
                f"{path}: expected a mapping of settings; got {type(loaded).__name__}"
            )
        values += [(k, v, where) for k, (v, where) in _flatten_at(loaded, str(path)).items()]
    for item in overrides or []:
        key, value = _parse_assignment(item)
        values.append((key, value, "command line"))
    return _apply(cfg, [_Item(_route(key), key, value, where) for key, value, where in values])


def settings_dict(cfg: RegisterConfig) -> dict:
    """The settings as plain data (for ``summary.json``)."""
    return dataclasses.asdict(cfg)


# -- the settings template (motion register --write-config)
#: the comment lines' width
TEMPLATE_WIDTH = 100

TEMPLATE_HEADER = """\
# Settings of `motion register` (python -m motion register, or motionreg register), each at
# its value here with its meaning above it. Give the file back with --config FILE: a key
# left out keeps its default, so you may keep only what you change. The same keys, dotted,
# may follow the command line's options as key=value (refine.particles=60): those win over
# the file. Values are YAML (null: none). A line "# key: VALUE (not settable in a file)" is
# a setting only Python code can change. Each group names the class that documents its
# settings."""

_ENTRY = re.compile(r"^(\s*)([a-z_][a-z0-9_]*):(?:\s+(.*))?$")
_ROLE = re.compile(r":[a-z]+:`(~?)([^`]+)`")
_LITERAL = re.compile(r"``([^`]+)``")


def user_key(key: str) -> str:
    """A dotted key of :class:`RegisterConfig` as the user writes it (the pipeline's
    settings by their shortcut: ``registration.refine.particles`` -> ``refine.particles``)."""
    head, _, rest = key.partition(".")
    if head == "registration" and rest.partition(".")[0] in _SHORTCUTS:
        return rest
    return key


def _plain(text: str) -> str:
    """Docstring text as plain words on one line (``:class:`~a.B``` -> ``B``, literals
    unquoted)."""
    text = _ROLE.sub(lambda m: m[2].rpartition(".")[2] if m[1] else m[2], text)
    return " ".join(_LITERAL.sub(r"\1", text).split())


def _docstring(cls: type) -> tuple[dict[str, str], str]:
    """The entries of a plain dataclass's docstring (``name: meaning`` lines, an entry's
    further lines indented deeper) and the rest of its text, all as plain text."""
    fields = {f.name for f in dataclasses.fields(cls)}
    raw: dict[str, list[str]] = {}
    prose: list[str] = []
    entry, indent = None, None  # the entry being read and its indentation
    for line in inspect.cleandoc(cls.__doc__ or "").splitlines():
        m = _ENTRY.match(line)
        if m and m[2] in fields:
            entry, indent = m[2], len(m[1])
            raw[entry] = [m[3] or ""]
        elif entry and line.strip() and len(line) - len(line.lstrip()) > indent:
            raw[entry].append(line.strip())
        else:
            entry = None
            prose.append(line)
    return {k: _plain(" ".join(v)) for k, v in raw.items()}, _plain(" ".join(prose))


def _sentences(text: str) -> list[str]:
    """``text`` split after each full stop (outside brackets) that a capital or the end
    follows."""
    out, start, depth = [], 0, 0
    for i, ch in enumerate(text):
        if ch in "([":
            depth += 1
        elif ch in ")]":
            depth = max(depth - 1, 0)
        elif depth == 0 and ch == "." and text[i + 1 : i + 2] in ("", " "):
            if i + 2 >= len(text) or text[i + 2].isupper():
                out.append(text[start : i + 1].strip())
                start = i + 1
    rest = text[start:].strip()
    return [*out, rest] if rest else out


def _field_docs(cls: type) -> dict[str, str]:
    """Field name -> its meaning. A settings class's fields carry their own
    (:func:`motion.settings.setting`); a plain dataclass's (``Connections``, ``Temporal``)
    come from its docstring: the first sentence of the field's entry, else the first sentence
    of its text that names the field, else nothing."""
    if issubclass(cls, Settings):
        return {
            f.name: getattr(f.metadata.get("setting"), "doc", "") for f in dataclasses.fields(cls)
        }
    entries, prose = _docstring(cls)
    docs = {}
    for f in dataclasses.fields(cls):
        if f.name in entries:
            docs[f.name] = (_sentences(entries[f.name]) or [""])[0].removesuffix(".")
            continue
        word = re.compile(rf"\b{re.escape(f.name)}\b")
        found = (s for s in _sentences(prose) if word.search(s))
        docs[f.name] = next(found, "").removesuffix(".")
    return docs


def _yaml_value(value) -> str | None:
    """``value`` in YAML's flow style (``0.002``, ``mog2``, ``[1.0, 0.85]``, ``null``), or
    ``None`` when YAML cannot hold it (a ``torch.dtype``, a schedule object)."""

    def plain(v):
        if v is None or isinstance(v, bool | int | float | str):
            return v
        if isinstance(v, list | tuple):
            return [plain(x) for x in v]
        if isinstance(v, dict) and all(isinstance(k, str) for k in v):
            return {k: plain(x) for k, x in v.items()}
        raise TypeError(type(v).__name__)

    try:
        data = plain(value)
    except TypeError:
        return None
    text = _dump(data, yaml.SafeDumper)
    if load_yaml(text, "the template") != data:  # a string YAML 1.2 reads otherwise ("1e3")
        text = _dump(data, _QuotedDumper)
    return text


class _QuotedDumper(yaml.SafeDumper):
    """Writes every string double-quoted (read back as a string by any YAML)."""


_QuotedDumper.add_representer(
    str, lambda dumper, s: dumper.represent_scalar("tag:yaml.org,2002:str", s, style='"')
)


def _dump(data, dumper: type[yaml.SafeDumper]) -> str:
    text = yaml.dump(data, Dumper=dumper, default_flow_style=True, width=10**9, sort_keys=False)
    return text.removesuffix("...\n").strip()


def _comment(text: str, indent: str) -> list[str]:
    width = max(TEMPLATE_WIDTH - len(indent) - 2, 40)
    return [f"{indent}# {line}" for line in textwrap.wrap(text, width, break_on_hyphens=False)]


def _group_doc(doc: str, cls: type) -> str:
    """A group's meaning naming its class in full (``stages 2-3
    (motion.registration.refine.RefineSettings)``)."""
    full = f"{cls.__module__}.{cls.__qualname__}"
    if re.search(rf"\b{cls.__name__}\b", doc):
        return re.sub(rf"\b{cls.__name__}\b", full, doc, count=1)
    return f"{doc} -- {full}" if doc else full


def _template_lines(obj, default, depth: int, only: tuple[str, ...] | None = None) -> list[str]:
    """The lines of the fields of the settings dataclass ``obj`` (``only``: those fields),
    ``depth`` levels deep; a value other than ``default``'s says the default."""
    indent = "  " * depth
    docs = _field_docs(type(obj))
    lines: list[str] = []
    for f in dataclasses.fields(obj):
        if only is not None and f.name not in only:
            continue
        value, base = getattr(obj, f.name), getattr(default, f.name, None)
        doc = docs[f.name]
        if depth == 0:
            lines.append("")
        if dataclasses.is_dataclass(value):
            inner = _template_lines(value, base if type(base) is type(value) else value, depth + 1)
            settable = any(line.strip() and not line.lstrip().startswith("#") for line in inner)
            lines += _comment(_group_doc(doc, type(value)), indent)
            lines.append(f"{indent}{'' if settable else '# '}{f.name}:")
            lines += inner
            continue
        lines += _comment(doc, indent)
        opaque = isinstance(obj, Settings) and is_opaque(type(obj), f.name)
        text = None if opaque else _yaml_value(value)
        if text is None:
            lines.append(f"{indent}# {f.name}: {value!r} {NOT_SETTABLE}")
            continue
        line = f"{indent}{f.name}: {text}"
        if repr(value) != repr(base):
            line += f"  # default: {_yaml_value(base) or repr(base)}"
        lines.append(line)
    return lines


def config_template(cfg: RegisterConfig | None = None) -> str:
    """Every setting of ``motion register`` as YAML: grouped as the user writes the keys
    (``video``, ``perception``, ``stage1``, ``refine``, ``scale``, ``seed``, ``movement``,
    ``findings``), each with its meaning as a comment above it and its value in ``cfg``
    (default: the defaults; a value that is not the default says which is). :func:`load_config`
    reads it back to ``cfg``; the settings YAML cannot hold (a ``torch.dtype``, a schedule)
    are commented out."""
    cfg = RegisterConfig() if cfg is None else cfg
    default = RegisterConfig()
    lines = TEMPLATE_HEADER.splitlines()
    for f in dataclasses.fields(RegisterConfig):
        if f.name != "registration":
            lines += _template_lines(cfg, default, 0, only=(f.name,))
            continue
        # the pipeline's settings at the top level, as the user writes them (seed=1)
        names = [g.name for g in dataclasses.fields(cfg.registration)]
        shortcuts = tuple(n for n in names if n in _SHORTCUTS)
        lines += _template_lines(cfg.registration, default.registration, 0, only=shortcuts)
        if len(shortcuts) < len(names):  # settings without a shortcut: under registration
            rest = tuple(n for n in names if n not in _SHORTCUTS)
            lines += ["", "registration:"]
            lines += _template_lines(cfg.registration, default.registration, 1, only=rest)
    return "\n".join(lines) + "\n"
