"""Where the tensors of a run live: a device named in a setting, checked, and whole typed
inputs moved onto it.

A stage runs on the device of its inputs: every tensor it creates takes ``device=`` from
one of them (``torch.zeros(..., device=x.device)``, ``y.to(x)``), so moving the inputs moves
the work. :func:`to_device` moves a whole input -- a dataclass of dataclasses, lists and
tensors such as a :class:`~motion.registration.types.Reference` -- in one call.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TypeVar

import torch

__all__ = ["DeviceError", "map_tensors", "resolve_device", "to_device"]

Tree = TypeVar("Tree")


class DeviceError(ValueError):
    """A device name torch does not know, or a device this machine does not have."""


def resolve_device(name: str | torch.device) -> torch.device:
    """The device ``name`` (``"cpu"``, ``"cuda"``, ``"cuda:1"``), checked to exist here.

    Raises :class:`DeviceError` naming what was asked and what this machine has.
    """
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as err:
        raise DeviceError(f"unknown device {name!r}: expected 'cpu', 'cuda' or 'cuda:N'") from err
    if device.type == "cpu":
        return device
    if device.type != "cuda":
        raise DeviceError(f"unsupported device {name!r}: expected 'cpu', 'cuda' or 'cuda:N'")
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if count == 0:
        raise DeviceError(
            f"device {name!r} asked for, but this torch sees no CUDA device "
            f"(torch {torch.__version__}, built for CUDA {torch.version.cuda}): use device=cpu"
        )
    if device.index is not None and device.index >= count:
        raise DeviceError(
            f"device {name!r} asked for, but this machine has {count} CUDA device(s) "
            f"(cuda:0..cuda:{count - 1})"
        )
    return device


def map_tensors(tree: Tree, fn: Callable[[torch.Tensor], torch.Tensor]) -> Tree:
    """``tree`` with ``fn`` applied to every tensor in it: tensors, dataclass instances
    (rebuilt with :func:`dataclasses.replace` from their ``init`` fields), lists, tuples
    (named ones too) and dicts, to any depth; anything else is returned as it is."""
    if isinstance(tree, torch.Tensor):
        return fn(tree)
    if dataclasses.is_dataclass(tree) and not isinstance(tree, type):
        fields = [f for f in dataclasses.fields(tree) if f.init]
        return dataclasses.replace(
            tree, **{f.name: map_tensors(getattr(tree, f.name), fn) for f in fields}
        )
    if isinstance(tree, list):
        return [map_tensors(x, fn) for x in tree]
    if isinstance(tree, tuple):
        items = [map_tensors(x, fn) for x in tree]
        return tuple(items) if type(tree) is tuple else type(tree)(*items)  # a NamedTuple
    if isinstance(tree, dict):
        return {k: map_tensors(v, fn) for k, v in tree.items()}
    return tree


def to_device(tree: Tree, device: torch.device | str) -> Tree:
    """``tree`` with every tensor in it on ``device`` (:func:`map_tensors`). Tensors
    already there are not copied."""
    return map_tensors(tree, lambda t: t.to(device))
