"""Settings of ``python -m motion register`` from a YAML file and ``key=value`` overrides.

Every tuning constant already lives in a frozen settings dataclass of its stage
(:class:`~motion.registration.video.VideoSettings`,
:class:`~motion.registration.approximate.Stage1Settings`,
:class:`~motion.registration.refine.RefineSettings`); this module only changes some of their
fields by name. A key is a dotted path through those dataclasses -- ``seed``, ``scale``,
``video.width``, ``stage1.yaw_starts``, ``refine.particles``, ``refine.temporal.pos_std`` --
in a YAML mapping (nested or dotted) or as ``key=value`` on the command line (the value is
read as YAML: ``true``, ``3``, ``0.5``, ``none``, ``[1, 2]``). A key that is not a field, or
a value of another type than the field's, is a :class:`ConfigError` naming it.
"""

from __future__ import annotations

import dataclasses
import difflib
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

__all__ = ["ConfigError", "RegisterConfig", "load_config", "override", "settings_dict"]


class ConfigError(ValueError):
    """A settings file or override that does not fit the settings (names key and value)."""


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
    out: dict[str, object] = {}
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(_flatten(value, f"{name}."))
        else:
            out[name] = value
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
            "video.*, perception.*, stage1.*, refine.*, movement.*, scale, seed (python -m "
            "motion register --help)"
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
        if not _accepts(hints[head], current, item.value):
            raise ConfigError(
                f"{item.where}: {name} must be {_type_name(hints[head])}; got {item.value!r}"
            )
        leaves[head] = _convert(hints[head], item.value)
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


def override(obj, key: str, value, where: str = "settings"):
    """A copy of the settings dataclass ``obj`` with the field at dotted ``key`` set to
    ``value`` (checked against the field's annotation)."""
    return _apply(obj, [_Item(key, key, value, where)])


#: top-level shortcuts: ``seed=1`` means ``registration.seed=1``
_SHORTCUTS = ("seed", "scale", "stage1", "refine")


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
        value = yaml.safe_load(text) if text.strip() else None
    except yaml.YAMLError:
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
        try:
            loaded = yaml.safe_load(path.read_text(encoding="utf-8"))
        except yaml.YAMLError as err:
            raise ConfigError(f"{path}: not valid YAML ({' '.join(str(err).split())})") from None
        if loaded is None:
            loaded = {}
        if not isinstance(loaded, Mapping):
            raise ConfigError(
                f"{path}: expected a mapping of settings; got {type(loaded).__name__}"
            )
        values += [(k, v, str(path)) for k, v in _flatten(loaded).items()]
    for item in overrides or []:
        key, value = _parse_assignment(item)
        values.append((key, value, "command line"))
    return _apply(cfg, [_Item(_route(key), key, value, where) for key, value, where in values])


def settings_dict(cfg: RegisterConfig) -> dict:
    """The settings as plain data (for ``summary.json``)."""
    return dataclasses.asdict(cfg)
