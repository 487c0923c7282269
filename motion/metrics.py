"""Error measures of the research proposal and of this project.

Eqs. 21-23 (stick-figure pose), 36-37 (posture refinement), plus time-correspondence error,
per-joint articulation error and silhouette IoU. Heights normalise lengths as in the
proposal (h' for 2D figures in pixels, h for 3D bodies in metres). Shapes: ``n`` joints,
any leading batch ``(...)``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "articulation_error_deg",
    "correspondence_error",
    "joint_error_2d",
    "joint_error_3d",
    "position_error",
    "registration_error",
    "rotation_angle_error_deg",
    "rotation_error_deg",
    "silhouette_iou",
]


def _as(value: float | Tensor, like: Tensor) -> Tensor:
    """A height as a tensor of ``like``'s dtype (no silent float32 rounding)."""
    return torch.as_tensor(value, dtype=like.dtype, device=like.device)


def registration_error(projected: Tensor, observed: Tensor, height_2d: float | Tensor) -> Tensor:
    """Eq. 21: ``E_R = ||E_t||^2 / (n h')``, ``E_t`` the stacked 2D residuals.

    Shapes: ``(..., n, 2)`` pixels, ``height_2d`` pixels -> ``(...)``.
    """
    n = projected.shape[-2]
    return (projected - observed).square().sum((-1, -2)) / (n * _as(height_2d, projected))


def rotation_error_deg(angles_true: Tensor, angles_est: Tensor) -> Tensor:
    """Eq. 22: ``E_r = ||theta - theta_hat|| / 3`` over the three rotation angles, in degrees,
    with each difference wrapped to (-180, 180]. Shapes: ``(..., 3)`` radians -> ``(...)``."""
    d = torch.remainder(angles_est - angles_true + math.pi, 2 * math.pi) - math.pi
    return torch.rad2deg(d.norm(dim=-1) / 3)


def rotation_angle_error_deg(r_true: Tensor, r_est: Tensor) -> Tensor:
    """Geodesic angle between rotations (degrees), independent of any Euler convention.

    Shapes: ``(..., 3, 3)`` -> ``(...)``.
    """
    rel = r_true.transpose(-1, -2) @ r_est
    cos = ((torch.diagonal(rel, dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cos))


def position_error(p_true: Tensor, p_est: Tensor, height: float | Tensor) -> Tensor:
    """Eq. 23: ``E_p = ||p - p_hat|| / h``. Shapes: ``(..., 3)`` -> ``(...)``."""
    return (p_est - p_true).norm(dim=-1) / _as(height, p_true)


def joint_error_3d(joints_true: Tensor, joints_est: Tensor, height: float | Tensor) -> Tensor:
    """Eq. 36: mean 3D joint distance over body height. ``(..., n, 3)`` -> ``(...)``."""
    return (joints_est - joints_true).norm(dim=-1).mean(-1) / _as(height, joints_true)


def joint_error_2d(joints_true: Tensor, joints_est: Tensor, height: float | Tensor) -> Tensor:
    """Eq. 37: mean joint distance without depth (the first two coordinates) over body
    height. ``(..., n, 2 or 3)`` -> ``(...)``."""
    error = (joints_est[..., :2] - joints_true[..., :2]).norm(dim=-1).mean(-1)
    return error / _as(height, joints_true)


def correspondence_error(
    c_true: Tensor, c_est: Tensor, reference_rate: float
) -> tuple[Tensor, Tensor]:
    """Mean ``|C - C_true|`` over video frames, in reference frames and in milliseconds.

    Shapes: ``(..., T')`` -> two ``(...)``.
    """
    frames = (c_est - c_true).abs().double().mean(-1)
    return frames, frames * 1000.0 / reference_rate


def articulation_error_deg(local_true: Tensor, local_est: Tensor) -> Tensor:
    """Per-joint angle between true and estimated local rotations (degrees): how wrong the
    reported articulation A is at each joint. ``(..., J, 3, 3)`` -> ``(..., J)``."""
    return rotation_angle_error_deg(local_true, local_est)


def silhouette_iou(a: Tensor, b: Tensor) -> Tensor:
    """Intersection over union of binary masks ``(..., H, W)`` -> ``(...)`` (1 when both are empty)."""
    a, b = a.bool(), b.bool()
    inter = (a & b).sum((-1, -2)).double()
    union = (a | b).sum((-1, -2)).double()
    return torch.where(union > 0, inter / union.clamp_min(1), torch.ones_like(union))
