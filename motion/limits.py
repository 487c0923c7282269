"""Joint-angle limits as data: per joint and rotation axis, a range in degrees.

Limits are stored in YAML (``motion/data/limits/*.yaml``) as ``{joint: {X: [lo, hi], ...}}``
in the BVH's own Euler channels; an axis absent from a joint's entry is free, a joint absent
from the file is free. The bundled files were *estimated from motion capture*: the range of
each channel over the shared CMU recordings, widened by a margin (see :func:`estimate_limits`)
-- an axis that never moves there (e.g. CMU's hip-offset joints) gets a zero-width range,
i.e. no degree of freedom.

Shapes: ``J`` joints; angles ``(..., J, 3)`` in each joint's rotation order, radians.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import yaml
from torch import Tensor

from motion.bvh import BVH
from motion.kinematics import Skeleton

__all__ = ["estimate_limits", "limit_violation", "limits_tensor", "load_limits"]

DATA = Path(__file__).resolve().parent / "data" / "limits"


def estimate_limits(bvhs: list[BVH], margin_deg: float = 15.0, skip_first: bool = True) -> dict:
    """Per joint and axis: [min - margin, max + margin] degrees over all frames (clipped to
    +-180); an axis whose channel never moves gets [0, 0]. All files must share a skeleton."""
    names = bvhs[0].names
    lo = hi = None
    for b in bvhs:
        if b.names != names:
            raise ValueError(f"{b.path}: skeleton differs from {bvhs[0].path}")
        m = b.motion[1:] if skip_first and len(b.motion) > 1 else b.motion
        lo = m.min(0) if lo is None else np.minimum(lo, m.min(0))
        hi = m.max(0) if hi is None else np.maximum(hi, m.max(0))
    out: dict[str, dict[str, list[float]]] = {}
    col = 0
    for joint, chans in zip(names, bvhs[0].channels, strict=True):
        entry = {}
        for i, c in enumerate(chans):
            if c.endswith("rotation"):
                a, z = float(lo[col + i]), float(hi[col + i])
                entry[c[0]] = (
                    [0.0, 0.0]
                    if a == z == 0
                    else [
                        max(-180.0, round(a - margin_deg, 1)),
                        min(180.0, round(z + margin_deg, 1)),
                    ]
                )
        if entry and joint != names[0]:  # the root's rotation is the global orientation: free
            out[joint] = entry
        col += len(chans)
    return out


def load_limits(name_or_path: str | Path) -> dict:
    """Read a limits file (a path, or a bundled name such as ``"cmu_cgspeed"``)."""
    path = Path(name_or_path)
    if not path.suffix:
        path = DATA / f"{name_or_path}.yaml"
    data = yaml.safe_load(path.read_text()) or {}
    return data.get("limits", data)


def limits_tensor(skeleton: Skeleton, limits: dict) -> Tensor:
    """``(J, 3, 2)`` radians, in each joint's rotation order; free axes are [-inf, inf].

    Raises:
        KeyError: a joint in ``limits`` that the skeleton does not have.
    """
    out = torch.tensor([-math.inf, math.inf], dtype=torch.float64).repeat(skeleton.num_joints, 3, 1)
    for joint, axes in limits.items():
        j = skeleton.index(joint)
        order = skeleton.rotation_orders[j]
        for axis, (lo, hi) in axes.items():
            if axis not in order:
                raise KeyError(
                    f"limits give axis {axis} for {joint!r}, whose rotation order is {order!r}"
                )
            out[j, order.index(axis)] = torch.tensor([math.radians(lo), math.radians(hi)])
    return out


def limit_violation(angles: Tensor, limits: Tensor) -> Tensor:
    """How far (radians) each angle lies outside its range; 0 inside.

    Shapes: angles ``(..., J, 3)``, limits ``(J, 3, 2)`` -> ``(..., J, 3)``.
    """
    lim = limits.to(angles)
    return (lim[..., 0] - angles).clamp_min(0) + (angles - lim[..., 1]).clamp_min(0)
