"""State spaces of continuous nodes: where particles live and how they move.

A state space says how to perturb particles (on the manifold, not on raw coordinates), the
normalised density of its perturbation kernel (for the importance weights ``1 / q``), a
weighted mean that respects the manifold, and a distance.

* :class:`Euclidean` -- R^D.
* :class:`SE3` -- rigid poses stored as 7 numbers ``(x, y, z, qw, qx, qy, qz)``: position in
  metres and a unit quaternion (see :mod:`pgm.rotations` for the conventions). Perturbations
  are isotropic Gaussians in the tangent space (position, rotation vector).
* :class:`Discrete` -- ``n`` states; the support is all of them (index stored as a float),
  never resampled.

Shapes: ``(..., D)`` values with any leading batch shape; kernels between ``K`` points and
``M`` centres are ``(..., K, M)``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from pgm.rotations import qangle, qexp, qmul, qnormalize

__all__ = [
    "SE3",
    "Discrete",
    "Euclidean",
    "StateSpace",
    "so3_log_kernel",
    "so3_log_kernel_from_dot",
]

_LOG_2PI = math.log(2 * math.pi)


def _as_scale(scale, n: int, like: Tensor) -> Tensor:
    s = torch.as_tensor(scale, dtype=like.dtype, device=like.device)
    if s.dim() == 0:
        s = s.expand(n)
    if s.shape != (n,):
        raise ValueError(
            f"kernel scale must be a scalar or have shape ({n},); got {tuple(s.shape)}"
        )
    if not torch.isfinite(s).all() or (s <= 0).any():
        raise ValueError(f"kernel scale must be finite and > 0; got {s.tolist()}")
    return s


def so3_log_kernel(angle: Tensor, std: Tensor | float) -> Tensor:
    """Log density on SO(3) of ``exp(e) R_c`` with ``e ~ N(0, std^2 I_3)``, at relative angle
    ``angle`` (radians) from the centre ``R_c``.

    Taken w.r.t. the measure of exponential coordinates, ``dR = 2 (1 - cos a) / a^2 de``, so
    the Gaussian is divided by that Jacobian; wrap-around past pi is ignored (fine for
    ``std`` well below pi). Shapes: broadcast of ``angle`` and ``std``.
    """
    return _so3_log_kernel_half(0.5 * angle, std)


def _so3_log_kernel_half(half: Tensor, std: Tensor | float) -> Tensor:
    """:func:`so3_log_kernel` from the half angle ``h = a / 2`` (what ``acos`` of quaternion
    dot products gives), in one fused polynomial: the Gaussian is ``-2 h^2 / std^2`` and the
    Jacobian ``log(h^2 / sin^2 h) = -2 log(sin h / h)``, whose Taylor series
    ``h^2/3 + h^4/90 + 2h^6/2835 + h^8/18900 + 2h^10/467775 + 1382h^12/3831077250`` is
    truncated with an error below 3e-5 for h <= pi/2 (tested against the closed form)."""
    std = torch.as_tensor(std, dtype=half.dtype, device=half.device)
    h2 = half * half
    # Horner's scheme in place: these tensors are (B, E, K, K) tables, so every avoided
    # temporary is a pass over memory saved.
    poly = h2 * (1382.0 / 3831077250)
    poly.add_(2.0 / 467775)
    for c in (1.0 / 18900, 2.0 / 2835, 1.0 / 90):
        poly.mul_(h2).add_(c)
    poly.mul_(h2).add_(1.0 / 3 - 2.0 / std**2)
    return poly.mul_(h2).sub_(3 * torch.log(std) + 1.5 * _LOG_2PI)


def so3_log_kernel_from_dot(dot: Tensor, std: Tensor | float) -> Tensor:
    """:func:`so3_log_kernel` from quaternion dot products ``<q, q_c>`` (e.g. a batched
    matmul of two particle sets). Overwrites nothing; shapes: broadcast of inputs."""
    return _so3_log_kernel_half(torch.acos_(dot.abs().clamp_(max=1.0)), std)


class StateSpace:
    """Interface of a particle state space."""

    #: width D of a stored value
    dim: int
    #: dimension d of the tangent space (perturbation kernels are (d,)-scaled)
    tangent_dim: int
    #: a discrete space's support is fixed: its nodes are never resampled
    discrete: bool = False

    def perturb(self, x: Tensor, scale, generator: torch.Generator | None = None) -> Tensor:
        """Move each point by the perturbation kernel. Shapes: (..., D) -> (..., D)."""
        raise NotImplementedError

    def log_kernel(self, x: Tensor, centres: Tensor, scale) -> Tensor:
        """Normalised log density of the perturbation kernel around each centre.

        Shapes: x (..., K, D), centres (..., M, D) -> (..., K, M).
        """
        raise NotImplementedError

    def weighted_mean(self, x: Tensor, log_weights: Tensor) -> Tensor:
        """Mean of weighted points on the manifold. Shapes: (..., K, D), (..., K) -> (..., D)."""
        raise NotImplementedError

    def distance(self, x: Tensor, y: Tensor) -> Tensor:
        """Distance between points. Shapes: (..., D), (..., D) -> (...)."""
        raise NotImplementedError

    def validate(self, x: Tensor, name: str = "particles") -> None:
        """Raise ``ValueError`` unless ``x`` has width D and finite values."""
        if x.shape[-1] != self.dim:
            raise ValueError(
                f"{name} of a {self!r} node must have last dimension {self.dim}; got "
                f"{tuple(x.shape)}"
            )
        if not torch.isfinite(x).all():
            raise ValueError(f"{name} contain NaN or inf")


class Euclidean(StateSpace):
    """R^D with an axis-aligned Gaussian kernel of per-axis standard deviation ``scale``."""

    def __init__(self, dim: int):
        if not isinstance(dim, int) or dim < 1:
            raise ValueError(f"dim must be an int >= 1; got {dim!r}")
        self.dim = self.tangent_dim = dim

    def perturb(self, x, scale, generator=None):
        s = _as_scale(scale, self.dim, x)
        noise = torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)
        return x + noise * s

    def log_kernel(self, x, centres, scale):
        s = _as_scale(scale, self.dim, x)
        z = (x.unsqueeze(-2) - centres.unsqueeze(-3)) / s  # (..., K, M, D)
        return -0.5 * z.square().sum(-1) - torch.log(s).sum() - 0.5 * self.dim * _LOG_2PI

    def weighted_mean(self, x, log_weights):
        w = torch.softmax(log_weights, -1).unsqueeze(-1)
        return (w * x).sum(-2)

    def distance(self, x, y):
        return (x - y).norm(dim=-1)

    def __repr__(self) -> str:
        return f"Euclidean({self.dim})"


class SE3(StateSpace):
    """Rigid poses ``(x, y, z, qw, qx, qy, qz)``: metres and a unit quaternion.

    Kernel scale: ``(position std in metres, rotation std in radians)``. Perturbation:
    ``p + e_p``, ``exp(e_r) * q`` with ``e_p ~ N(0, s_p^2 I_3)``, ``e_r ~ N(0, s_r^2 I_3)``.
    """

    dim = 7
    tangent_dim = 6

    def perturb(self, x, scale, generator=None):
        s = _as_scale(scale, 2, x)
        shape = (*x.shape[:-1], 3)
        ep = torch.randn(shape, generator=generator, dtype=x.dtype, device=x.device) * s[0]
        er = torch.randn(shape, generator=generator, dtype=x.dtype, device=x.device) * s[1]
        q = qnormalize(qmul(qexp(er), x[..., 3:]))
        return torch.cat([x[..., :3] + ep, q], -1)

    def log_kernel(self, x, centres, scale):
        s = _as_scale(scale, 2, x)
        out = torch.cdist(x[..., :3], centres[..., :3]).square_()  # (..., K, M), in place
        out.mul_(-0.5 / s[0] ** 2).sub_(3 * torch.log(s[0]) + 1.5 * _LOG_2PI)
        dot = x[..., 3:] @ centres[..., 3:].transpose(-1, -2)
        return out.add_(so3_log_kernel_from_dot(dot, s[1]))

    def weighted_mean(self, x, log_weights):
        w = torch.softmax(log_weights, -1)
        pos = (w.unsqueeze(-1) * x[..., :3]).sum(-2)
        q = x[..., 3:]
        # Markley's average: principal eigenvector of sum_k w_k q_k q_k^T (sign-invariant).
        m = (w[..., None, None] * q.unsqueeze(-1) * q.unsqueeze(-2)).sum(-3)
        _, vecs = torch.linalg.eigh(m)
        return torch.cat([pos, qnormalize(vecs[..., -1])], -1)

    def distance(self, x, y):
        """Position distance (metres) plus rotation angle (radians): a tangent-space norm
        with 1 m = 1 rad. Use :meth:`position_distance` / :meth:`rotation_distance` apart."""
        return self.position_distance(x, y) + self.rotation_distance(x, y)

    @staticmethod
    def position_distance(x: Tensor, y: Tensor) -> Tensor:
        return (x[..., :3] - y[..., :3]).norm(dim=-1)

    @staticmethod
    def rotation_distance(x: Tensor, y: Tensor) -> Tensor:
        return qangle(x[..., 3:], y[..., 3:])

    def validate(self, x, name="particles"):
        super().validate(x, name)
        norm = x[..., 3:].norm(dim=-1)
        if ((norm - 1).abs() > 1e-3).any():
            raise ValueError(
                f"{name}: SE3 quaternions must have unit norm (max |norm - 1| = "
                f"{float((norm - 1).abs().max()):.3g})"
            )

    def __repr__(self) -> str:
        return "SE3()"


class Discrete(StateSpace):
    """``n`` states indexed 0..n-1 (value = the index as a float); never resampled."""

    dim = 1
    tangent_dim = 0
    discrete = True

    def __init__(self, num_states: int):
        if not isinstance(num_states, int) or num_states < 1:
            raise ValueError(f"num_states must be an int >= 1; got {num_states!r}")
        self.num_states = num_states

    def support(self, dtype=torch.float32) -> Tensor:
        """``(n, 1)`` the states as values."""
        return torch.arange(self.num_states, dtype=dtype).unsqueeze(-1)

    def perturb(self, x, scale, generator=None):
        return x

    def log_kernel(self, x, centres, scale):
        return torch.where(x.unsqueeze(-2) == centres.unsqueeze(-3), 0.0, -math.inf).squeeze(-1)

    def weighted_mean(self, x, log_weights):
        w = torch.softmax(log_weights, -1).unsqueeze(-1)
        return (w * x).sum(-2)

    def distance(self, x, y):
        return (x - y).abs().squeeze(-1)

    def validate(self, x, name="particles"):
        super().validate(x, name)

    def __repr__(self) -> str:
        return f"Discrete({self.num_states})"
