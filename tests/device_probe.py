"""A CPU stand-in for a second device: tensors created without a device go to ``meta``.

A stage that runs on the device of its inputs must name ``device=`` in every tensor it
creates; one that forgets creates on the CPU, which a CUDA run only finds on a GPU (``Expected
all tensors to be on the same device``). Under :class:`UnplacedOnMeta` such a tensor is put
on PyTorch's ``meta`` device (shapes, no data) instead, so the first operation mixing it with
the inputs' CPU tensors, or reading its values, fails on any machine, naming the line.

Only factory functions given no ``device`` and called from the code under ``packages`` are
moved; ``torch.as_tensor`` / ``torch.tensor`` of an existing tensor keeps that tensor's
device, as it does everywhere. :mod:`pgm` keeps its graph structure (node and edge indices)
on the CPU by design and is checked on a real GPU by its own CUDA tests.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode

__all__ = ["UnplacedOnMeta"]

#: the factory functions whose device defaults to the CPU
FACTORIES = frozenset(
    {
        torch.arange,
        torch.empty,
        torch.eye,
        torch.full,
        torch.linspace,
        torch.logspace,
        torch.ones,
        torch.rand,
        torch.randint,
        torch.randn,
        torch.randperm,
        torch.scalar_tensor,
        torch.zeros,
        torch.tensor,
        torch.as_tensor,
    }
)


ROOT = Path(__file__).resolve().parents[1]


class UnplacedOnMeta(TorchFunctionMode):
    """Within ``with UnplacedOnMeta():`` a factory call without ``device=`` from a file under
    ``packages`` (folders or ``.py`` files of the repository) creates on ``meta`` (see the module's
    docstring)."""

    def __init__(self, packages: tuple[str, ...] = ("motion",)):
        super().__init__()
        self.folders = tuple(str(ROOT / p) + ("" if p.endswith(".py") else "/") for p in packages)

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        caller = sys._getframe(1).f_code.co_filename
        if func in FACTORIES and "device" not in kwargs and caller.startswith(self.folders):
            wraps_tensor = func in (torch.tensor, torch.as_tensor) and isinstance(
                args[0] if args else kwargs.get("data"), torch.Tensor
            )
            if not wraps_tensor:
                kwargs["device"] = "meta"
        return func(*args, **kwargs)
