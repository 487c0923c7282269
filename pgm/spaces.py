"""State spaces of continuous nodes: where particles live and how they move.

A state space says how to perturb particles (on the manifold, not on raw coordinates), the
normalised density of its perturbation kernel (for the importance weights ``1 / q``), a
weighted mean that respects the manifold, and a distance.

* :class:`Euclidean` -- R^D.
* :class:`SE3` -- rigid poses stored as 7 numbers ``(x, y, z, qw, qx, qy, qz)``: position in
  metres and a unit quaternion (see :mod:`pgm.rotations` for the conventions). Perturbations
  are isotropic: a Gaussian in position and, in rotation, an isotropic Bingham density
  (default) or a Gaussian on the rotation vector (see :mod:`pgm.kernels`).
* :class:`Discrete` -- ``n`` states; the support is all of them (index stored as a float),
  never resampled.

Shapes: ``(..., D)`` values with any leading batch shape; kernels between ``K`` points and
``M`` centres are ``(..., K, M)``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from pgm.kernels import (
    ROTATION_KERNELS,
    rotation_noise,
    se3_kernel_mixture,
    se3_kernel_table,
)
from pgm.rotations import qangle, qmul, qnormalize

__all__ = ["SE3", "Discrete", "Euclidean", "StateSpace"]

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


class StateSpace:
    """Interface of a particle state space."""

    #: width D of a stored value
    dim: int
    #: dimension d of the tangent space (perturbation kernels are (d,)-scaled)
    tangent_dim: int
    #: a discrete space's support is fixed: its nodes are never resampled
    discrete: bool = False
    #: a discrete space's number of states (``None`` for continuous spaces)
    num_states: int | None = None

    def perturb(self, x: Tensor, scale, generator: torch.Generator | None = None) -> Tensor:
        """Move each point by the perturbation kernel. Shapes: (..., D) -> (..., D)."""
        raise NotImplementedError

    def log_kernel(self, x: Tensor, centres: Tensor, scale) -> Tensor:
        """Normalised log density of the perturbation kernel around each centre.

        Shapes: x (..., K, D), centres (..., M, D) -> (..., K, M).
        """
        raise NotImplementedError

    def log_kernel_mixture(self, x: Tensor, centres: Tensor, log_weights: Tensor, scale) -> Tensor:
        """``log sum_m w_m kernel(x_k | centre_m)``. Shapes: x (..., K, D), centres (..., M, D),
        log_weights (..., M) -> (..., K). Override when the table can be skipped."""
        table = self.log_kernel(x, centres, scale)
        return torch.logsumexp(table + log_weights.unsqueeze(-2), -1)

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
    ``p + e_p`` with ``e_p ~ N(0, s_p^2 I_3)``, and ``n * q`` with ``n`` from
    :func:`rotation_noise` of the kind ``rotation``: ``"bingham"`` (default: near the centre
    the Gaussian of rotation vectors with std ``s_r`` per axis, exactly normalised, and a
    kernel table is one matrix product) or ``"gaussian"`` (``exp(e_r)``,
    ``e_r ~ N(0, s_r^2 I_3)``).
    """

    dim = 7
    tangent_dim = 6

    def __init__(self, rotation: str = "bingham"):
        if rotation not in ROTATION_KERNELS:
            raise ValueError(f"rotation must be one of {ROTATION_KERNELS}; got {rotation!r}")
        self.rotation = rotation

    def perturb(self, x, scale, generator=None):
        s = _as_scale(scale, 2, x)
        lead = x.shape[:-1]
        ep = torch.randn((*lead, 3), generator=generator, dtype=x.dtype, device=x.device) * s[0]
        noise = rotation_noise(lead, float(s[1]), self.rotation, generator, x.dtype, x.device)
        q = qnormalize(qmul(noise, x[..., 3:]))
        return torch.cat([x[..., :3] + ep, q], -1)

    def log_kernel(self, x, centres, scale):
        s = _as_scale(scale, 2, x)
        return se3_kernel_table(
            x[..., :3], x[..., 3:], centres[..., :3], centres[..., 3:], s[0], s[1], self.rotation
        )

    def log_kernel_mixture(self, x, centres, log_weights, scale):
        s = _as_scale(scale, 2, x)
        return se3_kernel_mixture(
            x[..., :3],
            x[..., 3:],
            centres[..., :3],
            centres[..., 3:],
            log_weights,
            s[0],
            s[1],
            self.rotation,
        )

    def weighted_mean(self, x, log_weights):
        w = torch.softmax(log_weights, -1)
        pos = (w.unsqueeze(-1) * x[..., :3]).sum(-2)
        q = x[..., 3:]
        # Markley's average: principal eigenvector of sum_k w_k q_k q_k^T (sign-invariant),
        # as one batched product rather than a (..., K, 4, 4) temporary.
        m = (q * w.unsqueeze(-1)).transpose(-1, -2) @ q
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
        return f"SE3(rotation={self.rotation!r})"


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
        return torch.arange(self.num_states, dtype=dtype, device="cpu").unsqueeze(-1)

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
