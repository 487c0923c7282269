"""Joint-angle limits on the body graph's kinematic edges, from per-joint Euler limits.

A limits file (``motion/data/limits/*.yaml``, :mod:`motion.limits`) gives each BVH joint a
range per Euler channel of its *local* rotation, in degrees and the joint's channel order.
A kinematic edge of the body graph joins two parts whose frames are the global rotations of
two skeleton joints (:attr:`BodySpec.frame_joints`), so its relative rotation
``R_parent^T R_child`` is the product of the local rotations on the skeleton path between
them: down from their lowest common ancestor to the child's frame joint, times the inverse
of the product down to the parent's. In a BVH rest pose every joint's frame is the world's,
so no rest-orientation offsets enter. Per edge, with "moving" = a joint with rotation
channels not all fixed at ``[0, 0]`` (a joint absent from the file is free):

* **none moves**: the edge is rigid, its box ``[0, 0]`` on every channel;
* **one moves** (the common case: knee, elbow, ankle, the hip below CMU's fixed
  ``LHipJoint``): the relative rotation *is* that joint's local rotation -- or its inverse
  when the joint is on the parent's side (order reversed, bounds negated) -- and its box
  applies exactly (``exact``);
* **several move** (spine, neck, the shoulder below the spine): a conservative box in the
  child's frame joint's order (else the last moving joint's): every corner of the joints'
  boxes and ``samples`` draws uniform in them (fixed seed), composed, read as Euler angles
  (:func:`motion.geometry.matrix_to_euler`); each channel's circular range widened by
  ``margin_deg`` on each side, a channel whose widened range covers the circle left free.
  Not exact: it bounds the composite's angles channel by channel, so it admits
  combinations no joint setting reaches.

Angles in radians inside (degrees only in the files). Shapes: ``E`` edges, ``P`` parts.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from motion.geometry import euler_to_matrix, matrix_to_euler
from motion.kinematics import Skeleton
from motion.limits import limits_tensor
from pgm import EulerBox

if TYPE_CHECKING:
    from motion.body.spec import BodySpec

__all__ = ["EdgeLimits", "edge_limits"]

#: corners of the joints' boxes are enumerated up to this many bounded channels
MAX_CORNER_CHANNELS = 12


@dataclass(frozen=True)
class EdgeLimits:
    """Euler-angle limits of each kinematic edge's relative rotation ``R_parent^T R_child``.

    Attributes:
        lower, upper: ``(E, 3)`` radians in each edge's channel order, in
            :attr:`BodySpec.edges` order; ``-inf, inf`` on a free channel.
        orders: E rotation orders (intrinsic, as BVH channels: ``"ZYX"`` = ``Rz Ry Rx``).
        exact: ``(E,)`` bool, the box is one joint's own (else a conservative composite).
        joints: the moving skeleton joints between the two part frames, per edge.
    """

    lower: Tensor
    upper: Tensor
    orders: list[str]
    exact: Tensor
    joints: list[list[str]]

    @property
    def num_edges(self) -> int:
        return self.lower.shape[0]

    def box(self, softness: float = 0.1) -> EulerBox:
        """The :class:`pgm.EulerBox` of these limits, a violation of ``softness`` radians
        costing half a nat."""
        return EulerBox(self.lower, self.upper, self.orders, softness)

    def excess(self, spec: BodySpec, poses: Tensor) -> Tensor:
        """How far (radians) each edge's relative rotation in part poses lies outside its
        box, per channel: ``(..., P, 7)`` -> ``(..., E, 3)`` (0 inside)."""
        edges = spec.edges.to(poses.device)
        flat = poses.reshape(-1, spec.num_parts, poses.shape[-1])
        qa, qb = flat[:, edges[:, 0], 3:7], flat[:, edges[:, 1], 3:7]  # (B, E, 4)
        out = self.box().excess(qa, qb)
        return out.reshape(*poses.shape[:-2], self.num_edges, 3)


def _path(skeleton: Skeleton, parent: int, child: int) -> tuple[list[int], list[int]]:
    """Joints whose local rotations make ``G_parent^T G_child``: ``(up, down)``, each listed
    from the common ancestor (exclusive) downwards to ``parent`` / ``child`` (inclusive)."""

    def ancestry(j: int) -> list[int]:
        out = []
        while j >= 0:
            out.append(j)
            j = int(skeleton.parents[j])
        return out  # j, its parent, ..., root

    up, down = ancestry(parent), ancestry(child)
    common = next(j for j in up if j in down)
    return up[: up.index(common)][::-1], down[: down.index(common)][::-1]


def _moves(box: Tensor, order: str) -> bool:
    """A joint moves unless it has no rotation channels or all are fixed at [0, 0]."""
    return bool(order) and not bool((box == 0).all())


def _samples(box: Tensor, count: int, g: torch.Generator) -> Tensor:
    """Euler angles ``(n, 3)`` of one joint: uniform in its box (free channels over the
    circle)."""
    lo = torch.where(torch.isfinite(box[:, 0]), box[:, 0], -math.pi)
    hi = torch.where(torch.isfinite(box[:, 1]), box[:, 1], math.pi)
    return lo + (hi - lo) * torch.rand(count, 3, generator=g, dtype=torch.float64)


def _corners(boxes: list[Tensor]) -> list[Tensor] | None:
    """Every corner of the joints' boxes (per joint ``(n, 3)``), or ``None`` if too many."""
    bounded = [
        torch.where(torch.isfinite(b), b, torch.tensor([-math.pi, math.pi]).to(b)) for b in boxes
    ]
    if 3 * len(boxes) > MAX_CORNER_CHANNELS:
        return None
    combos = torch.tensor(list(itertools.product([0, 1], repeat=3 * len(boxes))))
    out = []
    for i, b in enumerate(bounded):
        pick = combos[:, 3 * i : 3 * i + 3]  # (n, 3): which end of each channel
        out.append(torch.gather(b.T.expand(len(combos), 2, 3), 1, pick[:, None]).squeeze(1))
    return out


def _circular_range(angles: Tensor) -> tuple[float, float]:
    """The shortest arc ``[lo, hi]`` (``hi - lo < 2 pi``, ``lo`` in ``(-pi, pi]``) holding
    every angle of ``(n,)``: the complement of the largest gap between sorted angles."""
    a = torch.sort(torch.remainder(angles + math.pi, 2 * math.pi) - math.pi).values
    gaps = torch.cat([a[1:] - a[:-1], (a[:1] + 2 * math.pi) - a[-1:]])
    g = int(gaps.argmax())
    if g == len(a) - 1:  # the wrap-around gap: no wrap inside the range
        return float(a[0]), float(a[-1])
    return float(a[g + 1]), float(a[g] + 2 * math.pi)


def edge_limits(
    spec: BodySpec,
    skeleton: Skeleton,
    limits: dict,
    margin_deg: float = 5.0,
    samples: int = 20_000,
    seed: int = 0,
) -> EdgeLimits:
    """Per-edge limits of ``spec``'s kinematic edges from per-joint Euler limits (the module
    docstring says how).

    Args:
        spec: the parts, their tree and frame joints.
        skeleton: the skeleton the spec was built on (rotation orders, hierarchy).
        limits: ``{joint: {axis: [lo, hi]}}`` degrees (:func:`motion.limits.load_limits`).
        margin_deg: widening of a composite box, per side.
        samples: uniform draws per composite edge (besides the corners).

    Raises:
        KeyError: a joint in ``limits`` the skeleton does not have (:func:`limits_tensor`).
    """
    boxes = limits_tensor(skeleton, limits)  # (J, 3, 2) radians, free = -inf, inf
    orders = skeleton.rotation_orders
    margin = math.radians(margin_deg)
    g = torch.Generator().manual_seed(seed)
    lower, upper, edge_orders, exact, names = [], [], [], [], []
    for parent, child in spec.edges.tolist():
        up, down = _path(skeleton, int(spec.frame_joints[parent]), int(spec.frame_joints[child]))
        moving = [(j, j in up) for j in up + down if _moves(boxes[j], orders[j])]
        names.append([skeleton.names[j] for j, _ in moving])
        if not moving:  # rigid
            lo, hi = torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
            order = orders[int(spec.frame_joints[child])] or "ZYX"
            exact.append(True)
        elif len(moving) == 1:
            j, inverted = moving[0]
            lo, hi, order = boxes[j, :, 0], boxes[j, :, 1], orders[j]
            if inverted:  # (R_i(a) R_j(b) R_k(c))^T = R_k(-c) R_j(-b) R_i(-a)
                lo, hi, order = -hi.flip(0), -lo.flip(0), order[::-1]
            exact.append(True)
        else:
            cf = int(spec.frame_joints[child])
            order = orders[cf] if orders[cf] else orders[moving[-1][0]]
            lo, hi = _composite(boxes, orders, moving, order, samples, margin, g)
            exact.append(False)
        lower.append(lo)
        upper.append(hi)
        edge_orders.append(order)
    return EdgeLimits(
        torch.stack(lower), torch.stack(upper), edge_orders, torch.tensor(exact), names
    )


def _composite(boxes, orders, moving, order, samples, margin, g) -> tuple[Tensor, Tensor]:
    """A conservative box (radians, in ``order``) of ``U^T D`` over the moving joints'
    boxes: ``U`` the product of those on the parent's side, ``D`` of the child's."""
    per_joint = [_samples(boxes[j], samples, g) for j, _ in moving]
    corners = _corners([boxes[j] for j, _ in moving])
    if corners is not None:
        per_joint = [torch.cat([s, c]) for s, c in zip(per_joint, corners, strict=True)]
    n = per_joint[0].shape[0]
    up = torch.eye(3, dtype=torch.float64).expand(n, 3, 3)
    down = up
    for (j, inverted), angles in zip(moving, per_joint, strict=True):
        r = euler_to_matrix(angles, orders[j])
        if inverted:
            up = up @ r
        else:
            down = down @ r
    angles = matrix_to_euler(up.transpose(-1, -2) @ down, order)  # (n, 3)
    lo, hi = torch.empty(3, dtype=torch.float64), torch.empty(3, dtype=torch.float64)
    for c in range(3):
        a, b = _circular_range(angles[:, c])
        a, b = a - margin, b + margin
        lo[c], hi[c] = (a, b) if b - a < 2 * math.pi else (-math.inf, math.inf)
    return lo, hi
