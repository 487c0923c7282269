"""Annealing schedules: a positive multiplier per iteration.

A pairwise potential's covariance (or a kernel's width) is ``base * schedule(n)`` at iteration
``n`` (0-based). The proposal anneals the connection covariance Lambda^n over 6 iterations and
runs the whole sequence twice (restarts restart the schedule).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

__all__ = ["Constant", "Geometric", "Linear", "Schedule", "Stepwise"]


class Schedule:
    """Maps an iteration index to a positive multiplier."""

    def __call__(self, iteration: int) -> float:
        raise NotImplementedError


def _check_positive(name: str, value: float) -> float:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number > 0; got {value!r}")
    return float(value)


class Constant(Schedule):
    """Always ``value`` (default 1: no annealing)."""

    def __init__(self, value: float = 1.0):
        self.value = _check_positive("value", value)

    def __call__(self, iteration: int) -> float:
        return self.value

    def __repr__(self) -> str:
        return f"Constant({self.value})"


class _Ramp(Schedule):
    """From ``start`` at iteration 0 to ``end`` at iteration ``steps - 1``, then ``end``."""

    def __init__(self, start: float, end: float, steps: int):
        self.start = _check_positive("start", start)
        self.end = _check_positive("end", end)
        if not isinstance(steps, int) or steps < 1:
            raise ValueError(f"steps must be an int >= 1; got {steps!r}")
        self.steps = steps

    def __call__(self, iteration: int) -> float:
        if self.steps == 1 or iteration >= self.steps - 1:
            return self.end
        return self._between(iteration / (self.steps - 1))

    def _between(self, fraction: float) -> float:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.start}, {self.end}, {self.steps})"


class Geometric(_Ramp):
    """``start * (end / start) ** (n / (steps - 1))``, then ``end``: a constant ratio per step."""

    def _between(self, fraction: float) -> float:
        return self.start * (self.end / self.start) ** fraction


class Linear(_Ramp):
    """``start + (end - start) * n / (steps - 1)``, then ``end``."""

    def _between(self, fraction: float) -> float:
        return self.start + (self.end - self.start) * fraction


class Stepwise(Schedule):
    """An explicit list of multipliers; the last one holds afterwards."""

    def __init__(self, values: Sequence[float]):
        if len(values) == 0:
            raise ValueError("Stepwise needs at least one value")
        self.values = [_check_positive(f"values[{i}]", v) for i, v in enumerate(values)]

    def __call__(self, iteration: int) -> float:
        return self.values[min(iteration, len(self.values) - 1)]

    def __repr__(self) -> str:
        return f"Stepwise({self.values})"
