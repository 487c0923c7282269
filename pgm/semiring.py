"""Semirings: the only thing that changes between marginal, MAP and counting inference.

Every inference routine in :mod:`pgm` is written against the small interface below
(``mul``, ``sum``, ``cumsum``, ``window_sum``, ``one``, ``zero``) so that sum-product,
max-product, tempered and counting inference share one code path, as in torch-struct.

Values live in the semiring's own domain:

* :class:`LogSemiring`, :class:`MaxSemiring`, :class:`TemperedSemiring` work on
  log-potentials (scores, higher is better); ``mul`` is ``+`` and ``zero`` is ``-inf``.
* :class:`CountingSemiring` works in linear space on ``{0, 1, 2, ...}``; ``from_log`` maps a
  log-potential to 1 where it is finite (allowed) and 0 where it is ``-inf`` (forbidden),
  so running any algorithm with it counts the allowed configurations.

Algorithms receive log-potentials and call ``semiring.from_log`` once on the way in.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "CountingSemiring",
    "LogSemiring",
    "MaxSemiring",
    "Semiring",
    "TemperedSemiring",
]


class Semiring:
    """Interface of a commutative semiring over tensors.

    Subclasses implement ``sum`` and ``mul``; ``cumsum`` and ``window_sum`` have generic
    (correct but not fastest) defaults that subclasses may override with a fused kernel.
    """

    #: human-readable name used in reprs and error messages
    name: str = "semiring"
    #: identity of ``mul`` and annihilator of ``sum``, as Python floats
    one: float = 0.0
    zero: float = -math.inf
    #: True where ``sum`` selects one term (max); lets decoders backtrack
    selects: bool = False
    #: True where values are log-potentials, so a message may be shifted by a constant
    log_space: bool = True
    #: True where ``mul``, ``sum`` and ``normalize`` give every element the same bits however
    #: the elements are batched: only exactly rounded operations (``+``, ``-``, ``max``).
    #: ``exp`` / ``log`` and long sums are not (torch computes a tensor's tail elements on a
    #: scalar path that may differ from the vectorised one in the last bit, and a sum's
    #: order follows the tensor's shape). Where True, loopy BP recomputes only the messages
    #: that can change and gets the bits of recomputing them all.
    batch_invariant: bool = False

    def from_log(self, log_potential: Tensor) -> Tensor:
        """Map log-potentials into this semiring's domain (identity for log-space semirings)."""
        return log_potential

    def mul(self, a: Tensor, b: Tensor) -> Tensor:
        raise NotImplementedError

    def sum(self, x: Tensor, dim: int) -> Tensor:
        raise NotImplementedError

    def prod(self, x: Tensor, dim: int) -> Tensor:
        """Semiring product along ``dim`` (a plain sum in log space)."""
        return x.sum(dim)

    def cumsum(self, x: Tensor, dim: int = -1) -> Tensor:
        """Inclusive prefix semiring-sum along ``dim``: ``out[i] = sum_{j <= i} x[j]``."""
        raise NotImplementedError

    def cumprod(self, x: Tensor, dim: int) -> Tensor:
        """Inclusive prefix semiring-product along ``dim`` (a plain cumsum in log space)."""
        return x.cumsum(dim)

    def window_sum(self, x: Tensor, width: int) -> Tensor:
        """Trailing window semiring-sum on the last axis.

        ``out[..., i] = sum_{j = i - width + 1}^{i} x[..., j]`` (terms before 0 are ``zero``).

        Shapes: ``x`` (..., K) -> (..., K). Generic O(K * width) fallback via ``unfold``.
        """
        padded = F.pad(x, (width - 1, 0), value=self.zero)
        return self.sum(padded.unfold(-1, width, 1), dim=-1)

    def normalize(self, belief: Tensor, dim: int = -1) -> Tensor:
        """Turn an unnormalised belief into this semiring's normalised marginal (log space)."""
        return belief - self.sum(belief, dim).unsqueeze(dim)

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class LogSemiring(Semiring):
    """Sum-product in log space: ``sum`` = log-sum-exp, ``mul`` = ``+``. Gives log Z and marginals."""

    name = "log"

    def mul(self, a: Tensor, b: Tensor) -> Tensor:
        return a + b

    def sum(self, x: Tensor, dim: int) -> Tensor:
        return torch.logsumexp(x, dim)

    def cumsum(self, x: Tensor, dim: int = -1) -> Tensor:
        return torch.logcumsumexp(x, dim)


class MaxSemiring(Semiring):
    """Max-product in log space: ``sum`` = max. Gives MAP values (and argmax by backtracking)."""

    name = "max"
    selects = True
    batch_invariant = True

    def mul(self, a: Tensor, b: Tensor) -> Tensor:
        return a + b

    def sum(self, x: Tensor, dim: int) -> Tensor:
        return x.amax(dim)

    def cumsum(self, x: Tensor, dim: int = -1) -> Tensor:
        return torch.cummax(x, dim).values

    def window_sum(self, x: Tensor, width: int) -> Tensor:
        # max_pool1d is a fused O(K) kernel; without return_indices it is ~4x faster
        # than asking for indices (DESIGN.md section 7), so decoders backtrack instead.
        if width == 1:
            return x
        lead = x.shape[:-1]
        flat = x.reshape(-1, 1, x.shape[-1])
        padded = F.pad(flat, (width - 1, 0), value=-math.inf)
        out = F.max_pool1d(padded, kernel_size=width, stride=1)
        return out.reshape(*lead, x.shape[-1])

    def normalize(self, belief: Tensor, dim: int = -1) -> Tensor:
        """Max-marginals shifted so that their maximum is 0 (not probabilities)."""
        return belief - belief.amax(dim, keepdim=True)


class TemperedSemiring(Semiring):
    """Tempered log-sum-exp: ``sum(x) = tau * logsumexp(x / tau)``.

    ``tau = 1`` is :class:`LogSemiring`; ``tau -> 0`` tends to :class:`MaxSemiring` (the
    difference is bounded by ``tau * log(n)`` for n terms). Marginals are the Gibbs
    distribution at temperature ``tau``: ``softmax(belief / tau)``.
    """

    name = "tempered"

    def __init__(self, temperature: float):
        if not (isinstance(temperature, (int, float)) and math.isfinite(temperature)):
            raise ValueError(f"temperature must be a finite positive number, got {temperature!r}")
        if temperature <= 0:
            raise ValueError(f"temperature must be > 0 (use MaxSemiring for 0), got {temperature}")
        self.temperature = float(temperature)

    def mul(self, a: Tensor, b: Tensor) -> Tensor:
        return a + b

    def sum(self, x: Tensor, dim: int) -> Tensor:
        return self.temperature * torch.logsumexp(x / self.temperature, dim)

    def cumsum(self, x: Tensor, dim: int = -1) -> Tensor:
        return self.temperature * torch.logcumsumexp(x / self.temperature, dim)

    def normalize(self, belief: Tensor, dim: int = -1) -> Tensor:
        scaled = belief / self.temperature
        return scaled - torch.logsumexp(scaled, dim, keepdim=True)

    def __repr__(self) -> str:
        return f"TemperedSemiring(temperature={self.temperature})"


class CountingSemiring(Semiring):
    """Counts allowed configurations: linear space, ``sum`` = +, ``mul`` = *.

    ``from_log`` maps a log-potential to 1 where finite and 0 where ``-inf``. Use float64
    inputs: counts are exact up to 2**53.
    """

    name = "counting"
    log_space = False
    one = 1.0
    zero = 0.0

    def from_log(self, log_potential: Tensor) -> Tensor:
        return torch.isfinite(log_potential).to(log_potential.dtype)

    def mul(self, a: Tensor, b: Tensor) -> Tensor:
        return a * b

    def sum(self, x: Tensor, dim: int) -> Tensor:
        return x.sum(dim)

    def prod(self, x: Tensor, dim: int) -> Tensor:
        return x.prod(dim)

    def cumsum(self, x: Tensor, dim: int = -1) -> Tensor:
        return torch.cumsum(x, dim)

    def cumprod(self, x: Tensor, dim: int) -> Tensor:
        return torch.cumprod(x, dim)

    def normalize(self, belief: Tensor, dim: int = -1) -> Tensor:
        return torch.log(belief) - torch.log(belief.sum(dim, keepdim=True))
