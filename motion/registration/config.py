"""Settings of ``python -m motion register`` from a YAML file and ``key=value`` overrides.

Every tuning constant already lives in a frozen settings dataclass of its stage
(:class:`~motion.registration.video.VideoSettings`,
:class:`~motion.registration.approximate.Stage1Settings`,
:class:`~motion.registration.refine.RefineSettings`); this module only changes some of their
fields by name. A key is a dotted path through those dataclasses -- ``seed``, ``scale``,
``video.width``, ``stage1.yaw_starts``, ``refine.particles``, ``refine.temporal.pos_std`` --
in a YAML mapping (nested or dotted) or as ``key=value`` on the command line (the value is
read as YAML: ``true``, ``3``, ``0.5``, ``none``, ``[1, 2]``). Files and values are read by the
strict YAML reader of :mod:`motion.settings_yaml` (YAML 1.2 scalars, duplicate keys refused).
A key that is not a field, or a value of another type or range than the field's, is a
:class:`ConfigError` (:class:`motion.settings.ConfigError`) of one line naming where (the file
and line, or ``command line``), the key, what was expected and what was given. The groups
that are :class:`motion.settings.Settings` (video, perception, stage1, polish, movement, findings)
check each value against the field's declared type and range; the others (refine, the
pipeline's scale and seed) against the field's annotation, then their own checks.

:func:`config_template` writes every setting as such a YAML file, each with its value and its
meaning as a comment (``motion register --write-config PATH``); read back by
:func:`load_config` it gives the same settings.
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import itertools
import re
import textwrap
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from motion.perception.detector import PerceptionSettings
from motion.registration.export import FindingSettings
from motion.registration.movement import MovementSettings
from motion.registration.pipeline import RegistrationSettings
from motion.registration.video import VideoSettings
from motion.settings import ConfigError, SettingError, Settings, coerce
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


def _options(hint) -> tuple[list, bool]:
    """The types a field annotated ``hint`` takes, and whether ``None`` is one of them
    (``int | None`` -> ``([int], True)``; ``tuple[float, float]`` -> itself, not its
    elements)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        return [a for a in args if a is not type(None)], type(None) in args
    return [hint], False


def _elements(hint, value) -> list | None:
    """The element types of a list or tuple field for ``value``'s items (``None``: any)."""
    args = typing.get_args(hint)
    if not args:
        return None
    if typing.get_origin(hint) is tuple and not (len(args) == 2 and args[1] is Ellipsis):
        return list(args)
    return [args[0]] * len(value)


def _fits(t, value) -> bool:
    """Whether ``value`` (not ``None``) fits the type ``t``."""
    origin = typing.get_origin(t) or t
    if origin is typing.Any:
        return True
    if origin is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if origin is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if origin in (bool, str):
        return isinstance(value, origin)
    if origin in (list, tuple):
        if not isinstance(value, list | tuple):
            return False
        element = _elements(t, value)
        if element is None:
            return True
        return len(element) == len(value) and all(
            _accepts(e, None, v) for e, v in zip(element, value, strict=True)
        )
    if isinstance(origin, type):
        return isinstance(value, origin)
    return False


def _accepts(hint, current, value) -> bool:
    """Whether ``value`` fits a field annotated ``hint`` (holding ``current``)."""
    options, optional = _options(hint)
    if value is None:
        return optional or current is None
    return any(_fits(t, value) for t in options)


def _convert(hint, value):
    """YAML's value as the field's type (checked by :func:`_accepts`): a float field given
    ``3`` gets ``3.0``; a tuple field given a list gets a tuple, a list field a list, their
    items converted likewise."""
    if value is None:
        return None
    options, _ = _options(hint)
    t = next(t for t in options if _fits(t, value))
    origin = typing.get_origin(t) or t
    if origin is float:
        return float(value)
    if origin in (list, tuple):
        element = _elements(t, value)
        items = (
            list(value)
            if element is None
            else [_convert(e, v) for e, v in zip(element, value, strict=True)]
        )
        return tuple(items) if origin is tuple else items
    return value


def _type_name(hint) -> str:
    return str(hint).replace("typing.", "").replace("<class '", "").replace("'>", "")


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
            "video.*, perception.*, stage1.*, refine.*, polish.*, movement.*, findings.*, scale, seed "
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
    hints = typing.get_type_hints(type(obj))
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
        leaves[head] = _leaf(obj, head, hints[head], item)
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


def _leaf(obj, head: str, hint, item: _Item):
    """``item``'s value for the field ``head`` of ``obj``: checked against the field's
    declared type and range (:func:`motion.settings.coerce`) in a settings class, against
    its annotation (:func:`_accepts`) in a plain dataclass."""
    if isinstance(obj, Settings):
        try:
            return coerce(type(obj), head, item.value, paths=True)
        except SettingError as err:  # "KEY must be ...": the key as the user wrote it
            raise ConfigError(f"{item.where}: {_walked(item)}{err}") from None
    if not _accepts(hint, getattr(obj, head), item.value):
        name = _walked(item) + head
        raise ConfigError(f"{item.where}: {name} must be {_type_name(hint)}; got {item.value!r}")
    return _convert(hint, item.value)


def override(obj, key: str, value, where: str = "settings"):
    """A copy of the settings dataclass ``obj`` with the field at dotted ``key`` set to
    ``value`` (checked as :func:`load_config` checks it)."""
    return _apply(obj, [_Item(key, key, value, where)])


#: top-level shortcuts: ``seed=1`` means ``registration.seed=1``
_SHORTCUTS = ("seed", "scale", "stage1", "refine", "polish")


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
    try:
        value = load_yaml(text, "command line", inline=True) if text.strip() else None
    except ConfigError:  # not YAML: the text itself (the field's check says if it fits)
        value = text
    if isinstance(value, str) and value.lower() in ("none", "null"):
        value = None
    return key, value


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


# -- the settings template (motion register --write-config) ----------------------------------
#: longest meaning taken from a docstring (characters) before it is cut at a clause
BRIEF_LIMIT = 240
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

_NAMES = r"[a-z_][a-z0-9_]*(?:,\s*[a-z_][a-z0-9_]*)*"
_ENTRY = re.compile(rf"^(\s*)({_NAMES}):(?:\s+(.*))?$")
#: a second entry on the same line as another's: ``particles: K per part. iterations,
#: restarts: particle BP passes``
_INNER_ENTRY = re.compile(rf"(?<=\.)\s+({_NAMES}):\s")
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


def _names(text: str) -> tuple[str, ...]:
    return tuple(n.strip() for n in text.split(","))


@dataclass(frozen=True)
class _Doc:
    """A field's meaning: ``names`` are the fields one docstring entry documents together
    (the comment is written once above the first of them), ``text`` the comment."""

    names: tuple[str, ...]
    text: str


def _docstring(cls: type) -> tuple[list[_Doc], str]:
    """The entries of a dataclass's docstring (``name: meaning`` lines under
    ``Attributes:`` or any heading; ``a, b: meaning`` documents both; an entry's further
    lines indented deeper), and the rest of its text, all as plain text."""
    fields = {f.name for f in dataclasses.fields(cls)}
    raw: list[tuple[tuple[str, ...], list[str]]] = []
    prose: list[str] = []
    indent = None  # of the entry being read
    for line in inspect.cleandoc(cls.__doc__ or "").splitlines():
        m = _ENTRY.match(line)
        if m and set(_names(m[2])) <= fields:
            raw.append((_names(m[2]), [m[3] or ""]))
            indent = len(m[1])
        elif indent is not None and line.strip() and len(line) - len(line.lstrip()) > indent:
            raw[-1][1].append(line.strip())
        else:
            indent = None
            prose.append(line)
    entries: list[_Doc] = []
    for names, parts in raw:
        text = _plain(" ".join(parts))
        while True:  # entries written on the same line as this one
            inner = next(
                (m for m in _INNER_ENTRY.finditer(text) if set(_names(m[1])) <= fields), None
            )
            if inner is None:
                break
            entries.append(_Doc(names, text[: inner.start()].strip()))
            names, text = _names(inner[1]), text[inner.end() :]
        entries.append(_Doc(names, text.strip()))
    return entries, _plain(" ".join(prose))


def _depth_zero(text: str, chars: str) -> list[int]:
    """Positions of ``chars`` outside brackets followed by a space or the end."""
    depth, out = 0, []
    for i, ch in enumerate(text):
        if ch in "([":
            depth += 1
        elif ch in ")]":
            depth = max(depth - 1, 0)
        elif depth == 0 and ch in chars and text[i + 1 : i + 2] in ("", " "):
            out.append(i)
    return out


def _sentences(text: str) -> list[str]:
    """``text`` split after each full stop (outside brackets) that a capital or the end
    follows."""
    out, start = [], 0
    for i in _depth_zero(text, "."):
        if i + 2 >= len(text) or text[i + 2].isupper():
            out.append(text[start : i + 1].strip())
            start = i + 1
    rest = text[start:].strip()
    return [*out, rest] if rest else out


def _brief(text: str, limit: int = BRIEF_LIMIT) -> str:
    """The first sentence of ``text`` without its full stop; one longer than ``limit`` is
    cut at its last ``:`` or ``;`` (outside brackets) before it, else at a space, and ends
    with ``...``."""
    first = (_sentences(text) or [""])[0]
    if len(first) <= limit:
        return first.removesuffix(".")
    cuts = [i for i in _depth_zero(first, ":;") if i <= limit] or [
        i for i, ch in enumerate(first[: limit + 1]) if ch == " "
    ]
    return (first[: cuts[-1]] if cuts else first[:limit]).rstrip(" ,") + " ..."


def _mention(name: str, text: str, limit: int = BRIEF_LIMIT) -> str | None:
    """The first sentence of ``text`` that names ``name`` (or its clause between ``;``,
    when the sentence is longer than ``limit``)."""
    word = re.compile(rf"\b{re.escape(name)}\b")
    for sentence in _sentences(text):
        if not word.search(sentence):
            continue
        if len(sentence) <= limit:
            return sentence.removesuffix(".")
        cuts = [-1, *_depth_zero(sentence, ";"), len(sentence)]
        for lo, hi in itertools.pairwise(cuts):
            clause = sentence[lo + 1 : hi].strip()
            if word.search(clause) and len(clause) <= limit:
                return clause.removesuffix(".")
    return None


def _mentioned(name: str, entries: list[_Doc], prose: str) -> str:
    """What the docstring says of a field without an entry of its own: the sentence of
    another entry that names it (``with OTHER: ...``; ``see OTHER`` where that is too
    long), else of the docstring's text, else nothing."""
    word = re.compile(rf"\b{re.escape(name)}\b")
    for entry in entries:
        if word.search(entry.text):
            other = ", ".join(entry.names)
            found = _mention(name, entry.text)
            return f"with {other}: {found}" if found else f"see {other}"
    return _mention(name, prose) or ""


def _field_docs(cls: type) -> dict[str, _Doc]:
    """Field name -> its meaning. A settings class's fields carry their own
    (:func:`motion.settings.setting`); a plain dataclass's come from its docstring: the first
    sentence of the field's entry, else the sentence of another field's entry (or of the
    docstring's text) that names it, else nothing."""
    if issubclass(cls, Settings):
        return {
            f.name: _Doc((f.name,), getattr(f.metadata.get("setting"), "doc", ""))
            for f in dataclasses.fields(cls)
        }
    entries, prose = _docstring(cls)
    own: dict[str, _Doc] = {}
    for entry in entries:
        for name in entry.names:
            own.setdefault(name, entry)
    docs = {}
    for f in dataclasses.fields(cls):
        if f.name in own:
            entry = own[f.name]
            names = f"{', '.join(entry.names)}: " if len(entry.names) > 1 else ""
            docs[f.name] = _Doc(entry.names, names + _brief(entry.text))
        else:
            docs[f.name] = _Doc((f.name,), _mentioned(f.name, entries, prose))
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
    shared: tuple[str, ...] = ()  # the names of the comment just written
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
            lines += _comment(_group_doc(doc.text, type(value)), indent)
            lines.append(f"{indent}{'' if settable else '# '}{f.name}:")
            lines += inner
            shared = ()
            continue
        if not (len(doc.names) > 1 and doc.names == shared):
            lines += _comment(doc.text, indent)
        shared = doc.names
        text = _yaml_value(value)
        if text is None:
            lines.append(f"{indent}# {f.name}: {value!r} (not settable in a file)")
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
