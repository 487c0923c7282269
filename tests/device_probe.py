"""Device placement checked on a machine without a GPU: two CPU stand-ins for a second device.

A stage that runs on the device of its inputs must place every tensor it makes, and move the
host's tensors it reads; a slip is found on a GPU only (``Expected all tensors to be on the
same device``). Two checks find them on any machine (decision 006):

* :class:`UnplacedOnMeta` puts a tensor made without ``device=`` (by a factory function called
  from the code under ``packages``) on PyTorch's ``meta`` device (shapes, no data), so the
  first operation mixing it with the inputs' CPU tensors, or reading its values, fails,
  naming the line. ``torch.as_tensor`` / ``torch.tensor`` of an existing tensor keeps that
  tensor's device, as it does everywhere.
* :class:`EmulatedDevice` emulates a second device whose tensors (:class:`OnDevice`) hold CPU
  data but read ``meta`` as their device: what the code makes on the inputs' device is the
  device's, what it makes on the CPU on purpose (``device="cpu"``, NumPy, ``.cpu()``) the
  host's, and an operation mixing the two fails where a GPU would refuse it (:class:`Mixed`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode

__all__ = [
    "META",
    "EmulatedDevice",
    "Mixed",
    "OnDevice",
    "UnplacedOnMeta",
    "emulated_to_device",
]

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
    ``packages`` (folders or ``.py`` files of the repository) creates on ``meta`` (see the
    module's docstring)."""

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


# -- a second device, emulated on the CPU ---------------------------------------------------

META = torch.device("meta")


class Mixed(RuntimeError):
    """A host tensor met a device tensor where a GPU would refuse it."""


#: operations where a GPU takes a host tensor beside its own: indexing with host indices,
#: moving and copying between devices, printing
MIXING_ALLOWED = frozenset(
    {
        torch.Tensor.__getitem__,
        torch.Tensor.__setitem__,
        torch.Tensor.to,
        torch.Tensor.copy_,
        torch.Tensor.cpu,
        torch.Tensor.__format__,
        torch.Tensor.__repr__,
    }
)


def _tensors(x):
    if isinstance(x, torch.Tensor):
        yield x
    elif isinstance(x, list | tuple):
        for y in x:
            yield from _tensors(y)
    elif isinstance(x, dict):
        for y in x.values():
            yield from _tensors(y)


def _inside_torch_optim() -> bool:
    """An optimiser's step: its state follows the gradients, which autograd hands out as
    plain (host) tensors here; on a GPU they are the GPU's."""
    frame = sys._getframe(2)
    for _ in range(4):
        if frame is None:
            return False
        if "/torch/optim/" in frame.f_code.co_filename:
            return True
        frame = frame.f_back
    return False


class OnDevice(torch.Tensor):
    """A CPU tensor that stands for one on the emulated device: its ``device`` reads
    ``meta`` (so ``torch.zeros(..., device=x.device)`` and ``y.to(x.device)`` make more of
    them under :class:`EmulatedDevice`), operations on it give ``OnDevice`` results, and an
    operation that meets a plain (host) tensor of one or more dimensions beside it raises
    :class:`Mixed`, as a GPU would, except those in :data:`MIXING_ALLOWED`; ``numpy()``
    raises too."""

    @property
    def device(self):
        return META

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func is torch.Tensor.numpy:
            raise Mixed("numpy() of a device tensor: move it to the CPU first")
        if func not in MIXING_ALLOWED and not _inside_torch_optim():
            tensors = [*_tensors(args), *_tensors(kwargs)]
            if any(type(t) is cls for t in tensors):
                host = [t for t in tensors if type(t) is not cls and t.dim() > 0]
                if host:
                    name = getattr(func, "__name__", str(func))
                    raise Mixed(
                        f"{name}: a host tensor of shape {tuple(host[0].shape)} meets a "
                        "device tensor"
                    )
        return super().__torch_function__(func, types, args, kwargs)


def _is_meta(a) -> bool:
    return (isinstance(a, torch.device) and a.type == "meta") or a == "meta"


def _is_cpu(a) -> bool:
    return (isinstance(a, torch.device) and a.type == "cpu") or (
        isinstance(a, str) and a.startswith("cpu")
    )


def _plain(x):
    return x.as_subclass(torch.Tensor) if isinstance(x, torch.Tensor) else x


class _Placement(TorchFunctionMode):
    """Factories with ``device=meta`` (an :class:`OnDevice`'s device) make ``OnDevice``
    tensors on the CPU; with ``device="cpu"`` plain ones (a copy to the host); ``.to``
    moves between the two kinds as a GPU's would."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        if func is torch.Tensor.cpu:
            return func(_plain(args[0]), *args[1:], **kwargs).as_subclass(torch.Tensor)
        if func is torch.Tensor.to:
            rest = [*args[1:], *kwargs.values()]
            onto = any(_is_meta(a) or type(a) is OnDevice for a in rest)
            home = any(_is_cpu(a) for a in rest)
            moved = [("cpu" if _is_meta(a) else _plain(a)) for a in args[1:]]
            kw = {k: ("cpu" if _is_meta(v) else _plain(v)) for k, v in kwargs.items()}
            out = func(_plain(args[0]), *moved, **kw)
            stays = type(args[0]) is OnDevice and not home
            return out.as_subclass(OnDevice if onto or stays else torch.Tensor)
        device = kwargs.get("device")
        if func in FACTORIES and device is not None and _is_meta(torch.device(device)):
            kwargs["device"] = "cpu"
            grad = kwargs.pop("requires_grad", False)
            return func(*args, **kwargs).as_subclass(OnDevice).requires_grad_(grad)
        if func in FACTORIES and device is not None and _is_cpu(torch.device(device)):
            return func(*map(_plain, args), **kwargs).as_subclass(torch.Tensor)
        return func(*args, **kwargs)


_Generator = torch.Generator


class _EmulatedGenerator(_Generator):
    """``torch.Generator(device=meta)``: the CPU's, reading ``meta`` as its device."""

    def __new__(cls, device="cpu"):
        emulated = _is_meta(torch.device(device))
        self = _Generator.__new__(cls, device="cpu" if emulated else device)
        self.emulated = emulated
        return self

    def __init__(self, device="cpu"):
        pass

    @property
    def device(self):
        return META if self.emulated else super().device


def emulated_to_device(tree, device):
    """:func:`motion.devices.to_device` for the emulated device: ``meta`` wraps every
    tensor of ``tree`` as :class:`OnDevice`, ``cpu`` unwraps them (their data is there)."""
    from motion.devices import map_tensors

    if _is_meta(torch.device(device)):
        return map_tensors(tree, lambda t: t.as_subclass(OnDevice))
    return map_tensors(tree, _plain)


class EmulatedDevice:
    """Within ``with EmulatedDevice():`` a device named ``meta`` behaves, for placement, like a
    GPU beside the CPU (:class:`OnDevice`): tensors made for it or derived from it are its,
    tensors made on the CPU (``device="cpu"``, NumPy, ``.cpu()``) are the host's, and an
    operation mixing the two fails where a GPU would refuse it. ``torch.Generator(device=
    meta)`` gives a CPU generator that says ``meta``. Meant for ``register()`` with its
    device resolved to ``meta`` and :func:`emulated_to_device` as its mover (see
    ``tests/motion/registration/test_device.py``)."""

    def __enter__(self):
        self._mode = _Placement()
        self._mode.__enter__()
        torch.Generator = _EmulatedGenerator
        return self

    def __exit__(self, *exc):
        torch.Generator = _Generator
        return self._mode.__exit__(*exc)
