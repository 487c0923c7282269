"""Smoothing along time: a Gaussian kernel for vectors, its chordal mean for rotations.

Both work on the first dimension (frames) of any tensor. Each frame is a weighted fit to the
frames around it (Gaussian weights, cut at :data:`TRUNCATE_SIGMAS`), of one of two kinds
(``fit``):

* ``"linear"`` (the default): the local linear fit, evaluated at the frame (local linear
  kernel regression). Where the kernel is whole it is the plain weighted mean (a symmetric
  kernel's slope term vanishes, and the two agree bit for bit there); at the ends, where the
  kernel is cut, it still follows a trend: a sequence that moves at a steady rate keeps its
  rate to the last frame. The weighted mean there lags toward the inside instead (by about
  0.8 sigma frames' worth of movement at the last frame: a root moving through the video
  was registered 2-11 % short of its travel, 7 % on average, and the gait check's Froude
  number squares that; docs/results/smoothing_ends.md). The price is variance: at the last
  frame the fit extrapolates from one side, so its noise is about twice the interior's
  (Fan & Gijbels, *Local Polynomial Modelling and Its Applications*, 1996, ch. 3: local
  linear regression's bias is of the same order at the boundary as inside, the weighted
  mean's there of the order of sigma times the slope).
* ``"constant"``: the weighted mean (Nadaraya-Watson) with the kernel renormalised at the
  ends: a level, not a trend (a constant stays constant, nothing extrapolates).

Either way no padding value leaks in, a constant sequence stays constant and a linear one
stays linear away from the ends.

Units: ``sigma`` is in frames; convert seconds with the frame rate.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["FITS", "gaussian_kernel", "smooth_rotations", "smooth_values"]

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


#: the two kinds of local fit (see the module's docstring)
FITS = ("linear", "constant")


def smooth_values(values: Tensor, sigma: float, fit: str = "linear") -> Tensor:
    """Each frame replaced by a Gaussian-weighted fit to the frames around it:
    ``(T, ...)`` -> ``(T, ...)``, the same dtype. ``sigma`` in frames; 0 returns a copy.

    With weights ``w_s = exp(-(s - t)^2 / (2 sigma^2))`` over the frames ``s`` inside the
    sequence and within the kernel's reach, ``fit="constant"`` gives
    ``sum_s w_s values[s] / sum_s w_s``; ``fit="linear"`` the weighted least-squares line
    through them, at ``t``: ``(S2 M0 - S1 M1) / (S0 S2 - S1^2)`` with ``Sk = sum_s w_s
    (s - t)^k`` and ``Mk = sum_s w_s (s - t)^k values[s]``, which is the weighted mean where
    the kernel is whole (there ``S1 = 0``: the same numbers) and wherever fewer than two
    frames carry weight (a one-frame sequence)."""
    if fit not in FITS:
        raise ValueError(f"fit must be one of {FITS}; got {fit!r}")
    if sigma == 0 or values.shape[0] == 0:
        return values.clone()
    kernel = gaussian_kernel(sigma, values.dtype, values.device)
    radius = (len(kernel) - 1) // 2
    flat = values.reshape(values.shape[0], -1).T.unsqueeze(1)  # (M, 1, T)
    ones = torch.ones(1, 1, values.shape[0], dtype=values.dtype, device=values.device)
    offset = torch.arange(-radius, radius + 1, dtype=values.dtype, device=values.device)

    def moment(x: Tensor, power: int) -> Tensor:
        """sum_s w_s (s - t)^power x[s] at every t (conv1d correlates: tap j is s - t = j - r)"""
        weight = (kernel * offset**power).view(1, 1, -1)
        return torch.nn.functional.conv1d(x, weight, padding=radius)

    s0, m0 = moment(ones, 0), moment(flat, 0)
    mean = m0 / s0
    if fit == "constant" or values.shape[0] < 2:
        return mean.squeeze(1).T.reshape(values.shape)
    s1, s2 = moment(ones, 1), moment(ones, 2)
    det = s0 * s2 - s1 * s1
    line = (s2 * m0 - s1 * moment(flat, 1)) / det
    frames = torch.arange(values.shape[0], device=values.device)
    whole = (frames >= radius) & (frames < values.shape[0] - radius)
    # a line needs two frames of weight: where the weight sits on one (a kernel far narrower
    # than a frame: the others' weights underflow), the weighted mean is that frame anyway
    spread = det > 1e3 * torch.finfo(values.dtype).eps * s0 * s2
    out = torch.where(whole | ~spread, mean, line)
    return out.squeeze(1).T.reshape(values.shape)


def smooth_rotations(rotations: Tensor, sigma: float, fit: str = "linear") -> Tensor:
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
    mean = smooth_values(rotations, sigma, fit)
    u, _, vh = torch.linalg.svd(mean)
    fix = torch.ones(*mean.shape[:-1], dtype=mean.dtype, device=mean.device)
    fix[..., 2] = torch.det(u @ vh)
    return u @ torch.diag_embed(fix) @ vh
