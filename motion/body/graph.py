"""The body factor graph over frames: one SE(3) node per (frame, part), built from a spec.

Kinematic edges join each part to its parent in the same frame through the proposal's
connection potential ``psi_ij = N(T(x_i) - p_j; 0, Lambda^n)`` (Eq. 30) -- a
:class:`pgm.RigidConnection` whose joint is the child's proximal landmark, placed at the
spec's offset in the parent's frame, annealed by a schedule -- with a broad rotation kernel
around a mean relative rotation so that neighbours can propose each other's particles, and
optionally joint-angle limits on the relative rotation (``Connections(limits=spec.limits)``:
a :class:`pgm.LimitedConnection`, whose sampler proposes only what the limits allow).
Optional temporal edges join each part to itself in the next frame, and an optional unary
prior pulls each part toward a given posture (the reference's at C(t') in registration).
The graph is a :class:`pgm.SpatioTemporalTemplate` replicated over frames: nodes are
``t * P + p``, per-joint parameters are tiled, not copied.

Units: metres and radians. Shapes: ``T`` frames, ``P`` parts, ``E = P - 1`` joints.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from motion.body.limits import EdgeLimits
from motion.body.spec import BodySpec
from pgm import (
    SE3,
    Constant,
    Geometric,
    LimitedConnection,
    ParticleGraph,
    RigidConnection,
    Schedule,
    SpatioTemporalTemplate,
    UnaryFactor,
)
from pgm.rotations import qconj, qmul

__all__ = ["Connections", "PosturePrior", "Temporal", "body_graph", "relative_rotations"]


@dataclass(frozen=True)
class Connections:
    """The kinematic edges' potential.

    Attributes:
        pos_std: metres, the joints' spread before annealing.
        rot_std: radians, the rotation kernel's spread around ``rel_rot`` (broad: it lets a
            neighbour propose a part's rotation without pulling joints straight).
        schedule: multiplier of ``pos_std`` per iteration (the proposal's annealing).
        rotation_schedule: multiplier of ``rot_std`` (default constant: it does not tighten).
        rel_rot: ``(E, 4)`` mean relative rotation ``R_parent^T R_child`` of each joint in
            :attr:`BodySpec.edges` order (default identity).
        limits: joint-angle limits of each joint's relative rotation (e.g.
            ``spec.limits``, :class:`~motion.body.limits.EdgeLimits`); ``None`` (default):
            none, the plain connection.
        limit_softness: radians, how soft the limits are: ``-0.5 (d / softness)^2`` nats
            for a violation of ``d`` (default 0.1 rad = 5.7 degrees: 10 degrees outside
            cost 1.5 nats, 30 degrees 14).
    """

    pos_std: float = 0.02
    rot_std: float = 1.0
    schedule: Schedule = field(default_factory=lambda: Geometric(1.0, 0.25, 6))
    rotation_schedule: Schedule = field(default_factory=Constant)
    rel_rot: Tensor | None = None
    limits: EdgeLimits | None = None
    limit_softness: float = 0.1

    def factor(self, spec: BodySpec, dtype=torch.float32) -> RigidConnection:
        edges = spec.edges
        args = (
            spec.offsets[edges[:, 1]].to(dtype),
            torch.zeros(3, dtype=dtype),
            self.pos_std,
            self.rot_std,
            None if self.rel_rot is None else self.rel_rot.to(dtype),
        )
        kw = {"schedule": self.schedule, "rotation_schedule": self.rotation_schedule}
        if self.limits is None:
            return RigidConnection(*args, **kw)
        if self.limits.num_edges != len(edges):
            raise ValueError(
                f"limits are for {self.limits.num_edges} joints; the spec has {len(edges)}"
            )
        return LimitedConnection(*args, **kw, limits=self.limits.box(self.limit_softness))


@dataclass(frozen=True)
class Temporal:
    """Temporal edges: part p of frame t to part p of frame t + 1 (no offset), a Gaussian of
    ``pos_std`` metres on the position and a rotation kernel of ``rot_std`` radians.

    Attributes:
        pos_std: metres, how far a part may move from one frame to the next (a random walk:
            no velocity is assumed).
        rot_std: radians, how far a part may turn from one frame to the next.
    """

    pos_std: float = 0.05
    rot_std: float = 0.3

    def factor(self, dtype=torch.float32) -> RigidConnection:
        zero = torch.zeros(3, dtype=dtype, device="cpu")
        return RigidConnection(zero, zero, self.pos_std, self.rot_std)


class PosturePrior(UnaryFactor):
    """A pull of every part toward a given posture: ``-|p - p0|^2 / (2 pos_std^2) -
    kappa (1 - <q, q0>^2)`` with ``kappa = 2 / rot_std^2`` (the isotropic Bingham kernel of
    :mod:`pgm.kernels`, ~ a Gaussian of the rotation angle with ``rot_std``), unnormalised.

    Args:
        poses: ``(T, P, 7)`` the posture per frame (or ``(B, T, P, 7)``).
        pos_std: metres. rot_std: radians.
    """

    def __init__(self, poses: Tensor, pos_std: float, rot_std: float):
        if poses.shape[-1] != 7 or poses.dim() not in (3, 4):
            raise ValueError(
                f"poses must have shape (T, P, 7) or (B, T, P, 7); got {tuple(poses.shape)}"
            )
        if not (pos_std > 0 and rot_std > 0):
            raise ValueError(f"pos_std and rot_std must be > 0; got {pos_std}, {rot_std}")
        self.poses = poses if poses.dim() == 4 else poses.unsqueeze(0)
        self.pos_std, self.kappa = float(pos_std), 2.0 / float(rot_std) ** 2

    def log_potential(self, x, nodes, estimates):
        target = self.poses.reshape(self.poses.shape[0], -1, 7).to(x)[:, nodes.to(x.device)]
        d2 = (x[..., :3] - target[:, :, None, :3]).square().sum(-1)
        dot = (x[..., 3:7] * target[:, :, None, 3:7]).sum(-1)
        return -0.5 * d2 / self.pos_std**2 - self.kappa * (1 - dot.square())


def relative_rotations(spec: BodySpec, poses: Tensor) -> Tensor:
    """Each joint's relative rotation ``R_parent^T R_child`` (quaternions) in a posture:
    ``(..., P, 7)`` -> ``(..., E, 4)``, in :attr:`BodySpec.edges` order."""
    edges = spec.edges.to(poses.device)
    return qmul(qconj(poses[..., edges[:, 0], 3:7]), poses[..., edges[:, 1], 3:7])


def body_graph(
    spec: BodySpec,
    frames: int,
    observations: list[tuple[Tensor, UnaryFactor]] | None = None,
    connections: Connections | None = None,
    temporal: Temporal | None = None,
    dtype=torch.float32,
) -> ParticleGraph:
    """The body graph of ``frames`` frames.

    Args:
        spec: parts, tree and joints (:class:`BodySpec`).
        frames: T.
        observations: ``[(nodes, factor), ...]`` unary factors over the graph's nodes (e.g.
            ``(torch.arange(T * P), BodyObservation(...))``, a :class:`PosturePrior`).
        connections: the kinematic edges' potential (default :class:`Connections`).
        temporal: temporal edges per part (``None``: frames independent).

    Returns:
        a :class:`pgm.ParticleGraph` over ``T * P`` SE(3) nodes, node ``t * P + p``.
    """
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise ValueError(f"frames must be an int >= 1; got {frames!r}")
    connections = connections or Connections()
    template = SpatioTemporalTemplate(
        spec.num_parts,
        [(spec.edges, connections.factor(spec, dtype))],
        temporal=None if temporal is None else temporal.factor(dtype),
    )
    v = frames * spec.num_parts
    return ParticleGraph(
        v, [(SE3(), torch.arange(v))], template.build(frames), list(observations or [])
    )
