"""Smoothing along time: a normalised Gaussian kernel for vectors, its chordal mean for
rotations.

Both work on the first dimension (frames) of any tensor and treat the two ends the same
way: the kernel is cut at the ends and renormalised, so a constant sequence stays constant
up to the last frame (no padding value leaks in) and a linear one stays linear away from
the ends (the kernel is symmetric).

Units: ``sigma`` is in frames; convert seconds with the frame rate.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["gaussian_kernel", "smooth_rotations", "smooth_values"]

#: the kernel reaches this many standard deviations either side (the weight left out
#: beyond 3 sigma is 0.3 % of the total)
TRUNCATE_SIGMAS = 3.0


def gaussian_kernel(sigma: float, dtype=torch.float64, device=None) -> Tensor:
    """``(2 r + 1,)`` weights ``exp(-k^2 / (2 sigma^2))`` for ``k = -r .. r``,
    ``r = ceil(3 sigma)``, not normalised (the ends renormalise); on ``device`` (``None``:
    the CPU)."""
    if not (sigma > 0 and math.isfinite(sigma)):
        raise ValueError(f"sigma must be a finite number > 0 (frames); got {sigma}")
    radius = math.ceil(TRUNCATE_SIGMAS * sigma)
    k = torch.arange(-radius, radius + 1, dtype=dtype, device=device or "cpu")
    return torch.exp(-0.5 * (k / sigma) ** 2)


def smooth_values(values: Tensor, sigma: float) -> Tensor:
    """Each frame replaced by the Gaussian-weighted mean of the frames around it:
    ``(T, ...)`` -> ``(T, ...)``, the same dtype. ``sigma`` in frames; 0 returns a copy.

    ``out[t] = sum_s w(t - s) values[s] / sum_s w(t - s)`` over frames ``s`` inside the
    sequence (the weights renormalised at the ends)."""
    if sigma == 0 or values.shape[0] == 0:
        return values.clone()
    kernel = gaussian_kernel(sigma, values.dtype, values.device)
    radius = (len(kernel) - 1) // 2
    flat = values.reshape(values.shape[0], -1).T.unsqueeze(1)  # (M, 1, T)
    weight = kernel.view(1, 1, -1)
    summed = torch.nn.functional.conv1d(flat, weight, padding=radius)
    ones = torch.ones(1, 1, values.shape[0], dtype=values.dtype, device=values.device)
    total = torch.nn.functional.conv1d(ones, weight, padding=radius)
    return (summed / total).squeeze(1).T.reshape(values.shape)


def smooth_rotations(rotations: Tensor, sigma: float) -> Tensor:
    """Rotations ``(T, ..., 3, 3)`` smoothed along frames: at each frame the rotation
    nearest (Frobenius) to the Gaussian-weighted mean of the matrices around it -- the
    chordal L2 mean, by SVD. For rotations about one axis it is the rotation by the
    weighted circular mean of the angles. Meant for rotations that change by well under
    90 degrees within a few ``sigma`` (the mean of matrices far apart loses rank).
    ``sigma`` in frames; 0 returns a copy."""
    if rotations.shape[-2:] != (3, 3):
        raise ValueError(f"expected rotations (T, ..., 3, 3); got {tuple(rotations.shape)}")
    if sigma == 0:
        return rotations.clone()
    mean = smooth_values(rotations, sigma)
    u, _, vh = torch.linalg.svd(mean)
    fix = torch.ones(*mean.shape[:-1], dtype=mean.dtype, device=mean.device)
    fix[..., 2] = torch.det(u @ vh)
    return u @ torch.diag_embed(fix) @ vh
