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
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import yaml

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
        registration: the pipeline's settings (stages 1-3, G, seed).
    """

    video: VideoSettings = field(default_factory=VideoSettings)
    registration: RegistrationSettings = field(default_factory=RegistrationSettings)


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


def _accepts(hint, current, value) -> bool:
    """Whether ``value`` fits a field annotated ``hint`` (holding ``current``)."""
    args = typing.get_args(hint)
    if value is None:
        return current is None or type(None) in args
    types = [a for a in args if a is not type(None)] or [hint]
    for t in types:
        origin = typing.get_origin(t) or t
        if origin is float and isinstance(value, int | float) and not isinstance(value, bool):
            return True
        if origin is int and isinstance(value, int) and not isinstance(value, bool):
            return True
        if origin in (bool, str) and isinstance(value, origin):
            return True
        if origin in (list, tuple) and isinstance(value, list | tuple):
            return True
        if dataclasses.is_dataclass(origin) and isinstance(value, origin):
            return True
    return False


def _convert(hint, value):
    """YAML's value as the field's type (a float field given ``3`` gets ``3.0``; a tuple
    field given a list gets a tuple)."""
    args = [a for a in typing.get_args(hint) if a is not type(None)] or [hint]
    origin = typing.get_origin(args[0]) or args[0]
    if origin is float and isinstance(value, int):
        return float(value)
    if origin is tuple and isinstance(value, list):
        return tuple(value)
    return value


def override(obj, key: str, value, where: str = "settings"):
    """A copy of the settings dataclass ``obj`` with the field at dotted ``key`` set to
    ``value`` (checked against the field's annotation)."""
    head, _, rest = key.partition(".")
    fields = _fields(obj)
    if head not in fields:
        close = difflib.get_close_matches(head, fields, n=3)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        known = ", ".join(sorted(fields))
        raise ConfigError(f"{where}: unknown setting {key!r}{hint}; known here: {known}")
    current = getattr(obj, head)
    hints = typing.get_type_hints(type(obj))
    if rest:
        if not dataclasses.is_dataclass(current):
            raise ConfigError(f"{where}: {head!r} has no sub-settings; got {key!r}")
        return dataclasses.replace(obj, **{head: override(current, rest, value, f"{where}.{head}")})
    if dataclasses.is_dataclass(current) and not isinstance(value, type(current)):
        names = ", ".join(f"{head}.{f}" for f in _fields(current))
        raise ConfigError(f"{where}: {head!r} is a group of settings; set one of {names}")
    if not _accepts(hints[head], current, value):
        raise ConfigError(f"{where}: {head} must be {_type_name(hints[head])}; got {value!r}")
    return dataclasses.replace(obj, **{head: _convert(hints[head], value)})


def _type_name(hint) -> str:
    return str(hint).replace("typing.", "").replace("<class '", "").replace("'>", "")


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
    for key, value, where in values:
        cfg = override(cfg, _route(key), value, where)
    return cfg


def settings_dict(cfg: RegisterConfig) -> dict:
    """The settings as plain data (for ``summary.json``)."""
    return dataclasses.asdict(cfg)
