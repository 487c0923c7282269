"""The method's own error of a joint-angle difference, per clinical coordinate.

A finding (:class:`motion.registration.export.JointDifference`) is stated only when its
interval clears 0, and the interval counts two errors in quadrature: the inference's (the
particle spread, which measures how far the posterior lets a part turn) and the method's --
how far the estimated difference of a coordinate is from the true one on students whose
truth is known. The second depends on the coordinate (a knee's flexion shows in a silhouette,
a hip's rotation hardly at all) and on how many cameras see the student.

:class:`MethodError` is that table. The shipped one (:data:`METHOD_ERROR_FILE`) is written by
``python -m experiments.findings_calibration`` from the run records of synthetic students of
*other performers* (``experiments/configs/register_cross.yaml``): per coordinate, the RMS over
trusted frames of the estimated minus the true difference. The page it writes beside
(``docs/results/findings_calibration.md``) shows the table and scores the findings with it on
pairs left out of the calibration.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

from motion.registration.types import RegistrationError

__all__ = ["METHOD_ERROR_FILE", "MethodError", "shipped_method_error"]

#: the shipped calibration (written by ``python -m experiments.findings_calibration``)
METHOD_ERROR_FILE = Path(__file__).resolve().parent / "data" / "method_error.json"


@dataclass(frozen=True)
class MethodError:
    """Per camera count and clinical coordinate, the method's error of a joint-angle
    difference, degrees.

    Attributes:
        degrees: ``{cameras: {coordinate: degrees}}``; a registration with ``n`` cameras
            reads the entry of the largest camera count ``<= n`` (1 when ``n`` is below every
            count).
        source: where the figures come from (runs, commit), for the record.
        frames: ``{cameras: {coordinate: frames}}``, how many trusted frames each error
            was measured on.
    """

    degrees: dict[int, dict[str, float]]
    source: str = ""
    frames: dict[int, dict[str, int]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.degrees:
            raise RegistrationError("a method error table needs at least one camera count")
        for cameras, table in self.degrees.items():
            if not isinstance(cameras, int) or cameras < 1:
                raise RegistrationError(f"camera counts must be integers >= 1; got {cameras!r}")
            bad = {k: v for k, v in table.items() if not (math.isfinite(v) and v >= 0)}
            if bad:
                raise RegistrationError(
                    f"method errors must be finite and >= 0 degrees; got {bad} for {cameras} "
                    "camera(s)"
                )

    def table(self, cameras: int) -> dict[str, float]:
        """The errors for a registration with ``cameras`` cameras."""
        counts = sorted(self.degrees)
        below = [c for c in counts if c <= cameras]
        return self.degrees[below[-1] if below else counts[0]]

    def error_deg(self, coordinate: str, cameras: int) -> float | None:
        """The error of ``coordinate`` with ``cameras`` cameras, degrees; ``None`` when the
        table does not cover it."""
        return self.table(cameras).get(coordinate)

    def to_json(self) -> str:
        record = {
            "source": self.source,
            "degrees": {str(c): dict(sorted(t.items())) for c, t in sorted(self.degrees.items())},
            "frames": {str(c): dict(sorted(t.items())) for c, t in sorted(self.frames.items())},
        }
        return json.dumps(record, indent=2) + "\n"

    def write(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(self.to_json())
        return path

    @classmethod
    def read(cls, path: str | Path) -> MethodError:
        """The table in ``path`` (as :meth:`to_json` writes it)."""
        try:
            record = json.loads(Path(path).read_text())
            degrees = {
                int(c): {str(k): float(v) for k, v in t.items()}
                for c, t in record["degrees"].items()
            }
            frames = {
                int(c): {str(k): int(v) for k, v in t.items()}
                for c, t in record.get("frames", {}).items()
            }
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
            raise RegistrationError(f"{path}: not a method error table ({err})") from err
        return cls(degrees, str(record.get("source", "")), frames)


@cache
def shipped_method_error() -> MethodError:
    """The calibration shipped with the package (:data:`METHOD_ERROR_FILE`)."""
    return MethodError.read(METHOD_ERROR_FILE)
