"""Unit quaternions for state spaces that contain rotations.

Conventions (stated once): quaternions are ``(w, x, y, z)`` (scalar first, kornia's order),
unit norm, Hamilton product; ``qrotate(q, v)`` rotates column vector ``v`` by ``q`` (active
rotation, right-handed); the tangent space is the rotation vector (axis times angle, radians),
``exp(r) = (cos(|r|/2), sin(|r|/2) r/|r|)``. ``q`` and ``-q`` are the same rotation; every
function here is invariant to that sign. All functions take any leading batch shape ``(...)``.
Conversions to and from rotation vectors are kornia's.
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import axis_angle_to_quaternion, quaternion_to_axis_angle
from torch import Tensor

__all__ = [
    "angle_from_dot",
    "qangle",
    "qconj",
    "qexp",
    "qlog",
    "qmatrix",
    "qmul",
    "qnormalize",
    "qrotate",
]


def qmul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``). Shapes: (..., 4) -> (..., 4)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        -1,
    )


def qconj(q: Tensor) -> Tensor:
    """Conjugate = inverse of a unit quaternion. Shapes: (..., 4) -> (..., 4)."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def qnormalize(q: Tensor) -> Tensor:
    """Unit norm, with the sign fixed so that ``w >= 0``. Shapes: (..., 4) -> (..., 4)."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny)
    return torch.where(q[..., :1] < 0, -q, q)


def qrotate(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors: ``R(q) v = v + w t + u x t`` with ``t = 2 u x v``, written out per
    component (``torch.cross`` on a last axis of 3 is ~1.5x slower here). Shapes:
    q (..., 4), v (..., 3) -> (..., 3)."""
    w, x, y, z = q.unbind(-1)
    vx, vy, vz = v.unbind(-1)
    tx, ty, tz = 2 * (y * vz - z * vy), 2 * (z * vx - x * vz), 2 * (x * vy - y * vx)
    return torch.stack(
        [
            vx + w * tx + (y * tz - z * ty),
            vy + w * ty + (z * tx - x * tz),
            vz + w * tz + (x * ty - y * tx),
        ],
        -1,
    )


def qmatrix(q: Tensor) -> Tensor:
    """Rotation matrix of a quaternion (normalised on the way, so a slightly off-unit
    particle gives a rotation): ``R v = qrotate(q, v)``. Shapes: (..., 4) -> (..., 3, 3)."""
    w, x, y, z = q.unbind(-1)
    s = 2.0 / (q * q).sum(-1).clamp_min(torch.finfo(q.dtype).tiny)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    return torch.stack(
        (
            torch.stack((1 - yy - zz, xy - wz, xz + wy), -1),
            torch.stack((xy + wz, 1 - xx - zz, yz - wx), -1),
            torch.stack((xz - wy, yz + wx, 1 - xx - yy), -1),
        ),
        -2,
    )


def qexp(r: Tensor) -> Tensor:
    """Rotation vector (radians) -> unit quaternion. Shapes: (..., 3) -> (..., 4)."""
    return axis_angle_to_quaternion(r)


def qlog(q: Tensor) -> Tensor:
    """Unit quaternion -> rotation vector with angle in [0, pi]. Shapes: (..., 4) -> (..., 3)."""
    return quaternion_to_axis_angle(qnormalize(q))


def qangle(a: Tensor, b: Tensor) -> Tensor:
    """Angle (radians, in [0, pi]) of the rotation between ``a`` and ``b``. (..., 4) -> (...).

    Uses ``2 atan2(|v|, |w|)`` of the relative quaternion: accurate for tiny angles too.
    """
    rel = qmul(qconj(a), b)
    return 2.0 * torch.atan2(rel[..., 1:].norm(dim=-1), rel[..., 0].abs())


def angle_from_dot(dot: Tensor) -> Tensor:
    """Rotation angle from quaternion dot products ``<a, b>`` (e.g. a batched matmul of
    particle sets): ``2 acos(|dot|)``. Less accurate than :func:`qangle` below ~1e-3 rad in
    float32, which is far below any kernel width used with it."""
    return 2.0 * torch.acos(dot.abs().clamp(max=1.0))
