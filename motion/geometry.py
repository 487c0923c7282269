"""Rotations: rotation vectors, Euler angles, skew matrices and rotation angles, in one place.

Conventions (stated once for this module):

* right-handed frames, column vectors, active rotations: ``x' = R x``; a product ``A B``
  applies ``B`` first;
* angles in radians (degrees only where a caller converts for a report or a file);
* a rotation vector ``w = theta * axis`` (unit ``axis``, right-hand rule) is the rotation of
  ``theta`` radians about ``axis``, ``R = exp([w]_x)`` (Rodrigues' formula);
* Euler angles are intrinsic, in the order named: ``order = "ZXY"`` means
  ``R = Rz(a) Rx(b) Ry(c)`` -- the BVH channel convention (``Zrotation Xrotation Yrotation``);
* shapes are batch first, any leading shape ``(...)``: vectors ``(..., 3)``, matrices
  ``(..., 3, 3)``. The one exception says so in its name
  (:func:`rotation_vector_to_matrix_batch_last`: ``(3, B) -> (3, 3, B)``, the layout of
  :mod:`motion.pose`'s Levenberg-Marquardt loop); :func:`matrix_to_rotation_vector` takes a
  single ``(3, 3)`` matrix.

Unit quaternions (``w`` first) live in :mod:`pgm.rotations`, which the inference core uses
without depending on :mod:`motion`.
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from torch import Tensor

__all__ = [
    "RotationOrderError",
    "euler_to_matrix",
    "matrix_to_euler",
    "matrix_to_rotation_vector",
    "relative_angle",
    "rotation_about_y",
    "rotation_angle",
    "rotation_vector_to_matrix",
    "rotation_vector_to_matrix_batch_last",
    "skew_matrix",
]

_AXIS = {"X": 0, "Y": 1, "Z": 2}


class RotationOrderError(ValueError):
    """An Euler order that is not a permutation of ``"XYZ"``."""


def _check_order(order: str) -> None:
    if len(order) != 3 or set(order) != {"X", "Y", "Z"}:
        raise RotationOrderError(f"rotation order must be a permutation of 'XYZ'; got {order!r}")


# --------------------------------------------------------------------------- rotation vectors


def skew_matrix(v: Tensor) -> Tensor:
    """The cross-product matrix ``[v]_x`` (``[v]_x u = v x u``): ``(..., 3) -> (..., 3, 3)``,
    in ``v``'s unit, dtype and device. Differentiable."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(*v.shape[:-1], 3, 3)


def rotation_vector_to_matrix(w: Tensor) -> Tensor:
    """Rotation matrices of rotation vectors (Rodrigues): ``R = I + a [w]_x + b [w]_x^2`` with
    ``a = sin(theta) / theta``, ``b = (1 - cos(theta)) / theta^2``, ``theta = |w|``; their
    Taylor series where ``theta^2 < 1e-8``. Any angle (not limited to ``[0, pi]``).

    Args:
        w: ``(..., 3)`` radians.

    Returns:
        ``(..., 3, 3)``, dtype and device of ``w``. Differentiable (also at ``w = 0``).
    """
    th2 = (w * w).sum(-1, keepdim=True).unsqueeze(-1)
    small = th2 < 1e-8
    th = th2.clamp_min(1e-30).sqrt()
    a = torch.where(small, 1 - th2 / 6, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24, (1 - torch.cos(th)) / th2.clamp_min(1e-30))
    k = skew_matrix(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a * k + b * (k @ k)


def rotation_vector_to_matrix_batch_last(w: Tensor) -> Tensor:
    """:func:`rotation_vector_to_matrix` with the batch *last*: ``w`` ``(3, B)`` radians ->
    ``(3, 3, B)`` (``out[i, j, n] = R_n[i, j]``), written as ``R = I + s [w]_x + c (w w^T -
    |w|^2 I)`` entry by entry so that every operation is one long loop over the batch (the
    layout of :mod:`motion.pose`'s Levenberg-Marquardt loop, whose speed this keeps); the
    series form where ``theta^2 < 1e-12``. Agrees with :func:`rotation_vector_to_matrix` to
    rounding error."""
    th2 = (w * w).sum(0)
    small = th2 < 1e-12
    th = th2.clamp_min(1e-30).sqrt()
    s = torch.where(small, 1 - th2 / 6, torch.sin(th) / th)
    c = torch.where(small, 0.5 - th2 / 24, (1 - torch.cos(th)) / th2.clamp_min(1e-30))
    r = (c * w)[:, None] * w[None]
    diag = 1 - c * th2
    sw = s * w
    for i in range(3):
        r[i, i] += diag
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        r[i, j] -= sw[k]
        r[j, i] += sw[k]
    return r


def matrix_to_rotation_vector(r: Tensor) -> Tensor:
    """The rotation vector of one rotation matrix, angle in ``[0, pi]`` (the inverse of
    :func:`rotation_vector_to_matrix` there). Accurate everywhere, float64 intended: away
    from pi the axis comes from the antisymmetric part; near pi (``cos < -0.9``, where that
    part vanishes) from the symmetric part ``(R + R^T) / 2 - cos I = (1 - cos) a a^T``, its
    sign fixed by the small antisymmetric remainder. At exactly pi the sign of the axis is
    that of the largest diagonal entry's column (``w`` and ``-w`` are the same rotation).

    Args:
        r: ``(3, 3)`` a rotation matrix (a single one: the branches are Python ``if``).

    Returns:
        ``(3,)`` radians, dtype of ``r``.
    """
    skew = torch.stack([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2
    sin = skew.norm()
    cos = ((torch.trace(r) - 1) / 2).clamp(-1.0, 1.0)
    angle = torch.atan2(sin, cos)
    if cos > -0.9:  # well away from pi: the antisymmetric part is reliable
        if sin < 1e-300:
            return torch.zeros(3, dtype=r.dtype, device=r.device)
        return skew * (angle / sin)
    sym = (r + r.T) / 2 - cos * torch.eye(3, dtype=r.dtype, device=r.device)  # (1 - cos) a a^T
    col = int(torch.argmax(torch.diagonal(sym)))
    axis = sym[:, col] / sym[col, col].clamp_min(1e-300).sqrt()
    axis = axis / axis.norm()
    if torch.dot(axis, skew) < 0:
        axis = -axis
    return axis * angle


def rotation_about_y(angle: Tensor) -> Tensor:
    """Rotations about +Y (the vertical of BVH files and of :mod:`motion.synth`), ``Ry(a)``:
    ``(...,)`` radians -> ``(..., 3, 3)``, dtype and device of ``angle``."""
    c, s = torch.cos(angle), torch.sin(angle)
    r = torch.zeros(*angle.shape, 3, 3, dtype=angle.dtype, device=angle.device)
    r[..., 0, 0], r[..., 0, 2], r[..., 1, 1], r[..., 2, 0], r[..., 2, 2] = c, s, 1.0, -s, c
    return r


# --------------------------------------------------------------------------- rotation angles


def rotation_angle(r: Tensor) -> Tensor:
    """The angle of rotations, ``atan2(|axial part|, (trace - 1) / 2)``: accurate near 0 and
    near pi (an ``acos`` of the trace alone loses half the digits near 0).

    Shapes: ``(..., 3, 3)`` -> ``(...)`` radians in ``[0, pi]``."""
    skew = r - r.transpose(-1, -2)
    sin = 0.5 * torch.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], -1).norm(dim=-1)
    cos = 0.5 * (r.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0)
    return torch.atan2(sin, cos)


def relative_angle(a: Tensor, b: Tensor) -> Tensor:
    """The angle of ``a^T b`` (the geodesic distance between two rotations), from the trace
    ``sum_ij a_ij b_ij`` without forming the product (cheap to broadcast over many pairs):
    ``acos((trace - 1) / 2)``. Resolution near 0 is ``sqrt`` of the dtype's epsilon (about
    3e-4 rad in float32, 1e-8 in float64); use :func:`rotation_angle` of ``a^T b`` where
    small angles matter.

    Shapes: ``a``, ``b`` ``(..., 3, 3)`` (broadcast) -> ``(...)`` radians in ``[0, pi]``."""
    trace = (a * b).sum((-1, -2))
    return torch.acos(((trace - 1) / 2).clamp(-1.0, 1.0))


# --------------------------------------------------------------------------- Euler angles


def euler_to_matrix(angles: Tensor, order: str) -> Tensor:
    """Intrinsic Euler angles to rotation matrices: ``R = R_o0(a0) R_o1(a1) R_o2(a2)``.

    Args:
        angles: ``(..., 3)`` radians, in the order of ``order``.
        order: three distinct axes, e.g. ``"ZYX"`` or ``"ZXY"`` (BVH channel order).

    Returns:
        ``(..., 3, 3)``. Differentiable.

    Raises:
        RotationOrderError: ``order`` is not a permutation of ``"XYZ"``.
    """
    _check_order(order)
    lead = angles.shape[:-1]
    out = None
    for i, axis in enumerate(order):
        vec = torch.zeros((*lead, 3), dtype=angles.dtype, device=angles.device)
        vec[..., _AXIS[axis]] = angles[..., i]
        r = axis_angle_to_rotation_matrix(vec.reshape(-1, 3)).reshape(*lead, 3, 3)
        out = r if out is None else out @ r
    return out


def matrix_to_euler(matrix: Tensor, order: str) -> Tensor:
    """Rotation matrices to intrinsic Euler angles: the inverse of :func:`euler_to_matrix`,
    ``R = R_o0(a) R_o1(b) R_o2(c)``, for the six Tait-Bryan orders.

    Robust at and near gimbal lock: the middle angle is ``atan2(s, c)`` of two
    well-conditioned entries (never an ``asin`` near 1), and the last angle is solved with
    the first one removed (Day, "Converting a rotation matrix to Euler angles", 2012), so the
    angles reproduce the matrix to rounding error for every rotation. At exact lock (cosine
    of the middle angle below 1e-12, where only ``a + c`` or ``a - c`` is defined) the first
    angle is 0 and the last one carries the whole turn. No negative zeros (files print
    ``0``, not ``-0``).

    Args:
        matrix: ``(..., 3, 3)`` rotation matrices.
        order: three distinct axes in BVH channel order, e.g. ``"ZYX"``.

    Returns:
        ``(..., 3)`` radians in ``order``: first and last in ``(-pi, pi]``, middle in
        ``[-pi/2, pi/2]``.

    Raises:
        RotationOrderError: ``order`` is not a permutation of ``"XYZ"``.
    """
    _check_order(order)
    perm = [_AXIS[a] for a in order]
    even = (perm[1] - perm[0]) % 3 == 1
    # in the permuted basis the rotation is Rx Ry Rz, angles negated for an odd permutation
    m = matrix[..., perm, :][..., :, perm]
    cos_b = torch.hypot(m[..., 0, 0], m[..., 0, 1])
    b = torch.atan2(m[..., 0, 2], cos_b)
    a = torch.atan2(-m[..., 1, 2], m[..., 2, 2])
    a = torch.where(cos_b < 1e-12, torch.zeros_like(a), a)
    sa, ca = torch.sin(a), torch.cos(a)
    c = torch.atan2(ca * m[..., 1, 0] + sa * m[..., 2, 0], ca * m[..., 1, 1] + sa * m[..., 2, 1])
    angles = torch.stack([a, b, c], -1)
    return (angles if even else -angles) + 0.0  # + 0.0: no negative zeros in files
