"""Skeletons as data and batched forward kinematics.

Conventions (stated once for this module): right-handed world, column vectors, rotation
matrices act on the left (``x_world = R x_local + t``); angles in radians inside, degrees
only where a BVH file stores them; lengths in metres once a :class:`Skeleton` is built
(``metres_per_unit`` converts the file's units). Euler angles follow BVH: a joint whose
channels read ``Zrotation Xrotation Yrotation`` has local rotation ``Rz(a) Rx(b) Ry(c)``
(intrinsic, in channel order); the Euler conversions live in :mod:`motion.geometry` and are
re-exported here.

Shapes: ``J`` joints, any leading batch shape ``(...)`` (typically ``(B, T)``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from motion.bvh import BVH
from motion.geometry import euler_to_matrix, matrix_to_euler

__all__ = [
    "FKResult",
    "Skeleton",
    "SkeletonError",
    "end_site_positions",
    "end_site_positions_by_joint",
    "euler_to_matrix",  # from motion.geometry
    "forward_kinematics",
    "local_from_global",
    "local_rotations",
    "matrix_to_euler",  # from motion.geometry
    "offset_points",
]

_AXIS = {"X": 0, "Y": 1, "Z": 2}


class SkeletonError(ValueError):
    """An inconsistent skeleton (parent after child, unknown rotation order, bad shapes)."""


@dataclass
class Skeleton:
    """A skeleton as data.

    Attributes:
        names: ``J`` joint names (unique), parents before children.
        parents: ``(J,)`` long, -1 for the root.
        offsets: ``(J, 3)`` metres, each joint's position in its parent's frame at rest.
        rotation_orders: per joint, e.g. ``"ZYX"`` (``""`` for a joint without rotation channels).
        end_sites: ``{joint: (3,) offset in metres}`` of leaf end points.
        metres_per_unit: the factor that converted the source file's units.
        units_note: where that factor came from (declared, or estimated and how).
    """

    names: list[str]
    parents: Tensor
    offsets: Tensor
    rotation_orders: list[str]
    end_sites: dict[int, Tensor] = field(default_factory=dict)
    metres_per_unit: float = 1.0
    units_note: str = "metres"

    def __post_init__(self):
        j = len(self.names)
        if len(set(self.names)) != j:
            dup = sorted({n for n in self.names if self.names.count(n) > 1})
            raise SkeletonError(f"joint names must be unique; repeated: {dup}")
        if self.parents.shape != (j,) or self.offsets.shape != (j, 3):
            raise SkeletonError(
                f"parents must be ({j},) and offsets ({j}, 3); got {tuple(self.parents.shape)} "
                f"and {tuple(self.offsets.shape)}"
            )
        if j == 0 or self.parents[0] != -1:
            raise SkeletonError("joint 0 must be the root (parent -1)")
        for child, parent in enumerate(self.parents.tolist()[1:], start=1):
            if not 0 <= parent < child:
                raise SkeletonError(
                    f"joint {child} ({self.names[child]!r}) has parent {parent}: parents must "
                    "come before their children"
                )
        for order in self.rotation_orders:
            if order and (len(order) != 3 or set(order) != {"X", "Y", "Z"}):
                raise SkeletonError(f"rotation order must be a permutation of 'XYZ'; got {order!r}")

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """Joint index by name (``KeyError`` listing the names if absent)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no joint {name!r}; joints are {self.names}") from None

    def depth_levels(self) -> list[Tensor]:
        """Joints grouped by depth (root first): FK runs level by level, batched in a level."""
        depth = [0] * self.num_joints
        for j, p in enumerate(self.parents.tolist()):
            if p >= 0:
                depth[j] = depth[p] + 1
        levels = [[] for _ in range(max(depth) + 1)]
        for j, d in enumerate(depth):
            levels[d].append(j)
        return [torch.tensor(lv, dtype=torch.long, device=self.parents.device) for lv in levels]

    @classmethod
    def from_bvh(cls, bvh: BVH, metres_per_unit: float | None = None) -> Skeleton:
        """Build from a BVH file; ``metres_per_unit=None`` estimates it (see
        :func:`estimate_metres_per_unit`)."""
        orders = []
        for joint, channels in enumerate(bvh.channels):
            rot = "".join(c[0] for c in channels if c.endswith("rotation"))
            if rot and len(rot) != 3:
                raise SkeletonError(
                    f"{bvh.path}: joint {bvh.names[joint]!r} has {len(rot)} rotation channels; "
                    "3 or none are supported"
                )
            orders.append(rot)
        offsets = torch.from_numpy(bvh.offsets)
        if metres_per_unit is None:
            metres_per_unit, note = estimate_metres_per_unit(bvh)
        else:
            low, high = _UNIT_RANGE_M
            if (
                isinstance(metres_per_unit, bool)
                or not isinstance(metres_per_unit, int | float)
                or not low <= metres_per_unit <= high
            ):
                raise SkeletonError(
                    f"{bvh.path}: metres_per_unit must be a number in [{low:g}, {high:g}]; got "
                    f"{metres_per_unit!r}"
                )
            note = f"declared: {metres_per_unit} m per file unit"
        return cls(
            names=list(bvh.names),
            parents=torch.from_numpy(bvh.parents),
            offsets=offsets * metres_per_unit,
            rotation_orders=orders,
            end_sites={j: torch.from_numpy(o) * metres_per_unit for j, o in bvh.end_sites.items()},
            metres_per_unit=metres_per_unit,
            units_note=note,
        )


# Plausible metres per file unit for an estimate: from micrometres to 100 m. Outside this the
# rest pose is degenerate (all offsets ~0) or corrupt, and a guess would silently scale the
# root translation by an absurd factor.
_UNIT_RANGE_M = (1e-6, 100.0)


def estimate_metres_per_unit(bvh: BVH, leg_length_m: float = 0.85) -> tuple[float, str]:
    """Guess the file's length unit from its rest-pose leg length.

    The longest root-to-end-site chain below the root's height (a leg, from the hip down to
    the toe, taken straight at rest) is assumed to be ``leg_length_m`` (an adult's ~0.85 m).
    Exact units are unknowable from a BVH file; the estimate is right to ~15 % for adults,
    which is enough to tell metres, centimetres, inches and CMU's ~5.6 cm units apart.
    Returns the factor and a note saying it was estimated.

    Raises:
        SkeletonError: naming the file when the rest pose gives no length to measure (every
            OFFSET and End Site offset zero, as in files that animate per-joint positions
            instead) or an implausible one. There is no sensible fallback: the factor also
            scales the root translation, so a guess of 1 could be wrong by 100x without any
            sign; pass ``metres_per_unit`` to :meth:`Skeleton.from_bvh` instead.
    """
    parents = bvh.parents
    offsets = bvh.offsets
    pos = np.zeros_like(offsets)
    for j in range(1, len(parents)):
        pos[j] = pos[parents[j]] + offsets[j]
    tips = [pos[j] + o for j, o in bvh.end_sites.items()] or list(pos)
    drop = max(-float(t[1]) for t in tips)  # Y is up in BVH files
    if drop <= 0:
        drop = max(float(np.linalg.norm(t)) for t in tips)
    if drop <= 0:
        raise SkeletonError(
            f"{bvh.path}: cannot estimate the length unit: every OFFSET and End Site offset is "
            "zero, so the rest pose has no size; pass metres_per_unit explicitly"
        )
    factor = leg_length_m / drop
    low, high = _UNIT_RANGE_M
    if not low <= factor <= high:
        raise SkeletonError(
            f"{bvh.path}: cannot estimate the length unit: the rest leg is {drop:.3g} file units, "
            f"which would make {factor:.3g} m per unit (expected {low:g} to {high:g}); pass "
            "metres_per_unit explicitly"
        )
    # snap to a common unit when close (metres, centimetres, inches)
    for unit in (1.0, 0.01, 0.0254):
        if abs(np.log(factor / unit)) < np.log(1.45):  # units differ by >= 2.54x
            return unit, f"estimated: {unit} m per unit (rest leg {drop:.3g} units)"
    return (
        factor,
        f"estimated: {factor:.4g} m per unit (rest leg {drop:.3g} units = {leg_length_m} m)",
    )


def local_rotations(
    skeleton: Skeleton, bvh_motion: Tensor, channels: list[list[str]]
) -> tuple[Tensor, Tensor]:
    """Split BVH channel rows into local rotation matrices and root translation.

    Args:
        skeleton: from the same file.
        bvh_motion: ``(..., C)`` channel values as stored (degrees, file units).
        channels: the file's per-joint channel names.

    Returns:
        rotations ``(..., J, 3, 3)`` and root translation ``(..., 3)`` in metres.
    """
    lead = bvh_motion.shape[:-1]
    j = skeleton.num_joints
    rot = torch.eye(3, dtype=bvh_motion.dtype).expand(*lead, j, 3, 3).clone()
    root = torch.zeros((*lead, 3), dtype=bvh_motion.dtype)
    col = 0
    by_order: dict[str, tuple[list[int], list[list[int]]]] = {}
    for joint, chans in enumerate(channels):
        rot_cols = [col + i for i, c in enumerate(chans) if c.endswith("rotation")]
        for i, c in enumerate(chans):
            if c.endswith("position") and joint == 0:
                root[..., _AXIS[c[0]]] = bvh_motion[..., col + i] * skeleton.metres_per_unit
        if rot_cols:
            order = skeleton.rotation_orders[joint]
            by_order.setdefault(order, ([], []))
            by_order[order][0].append(joint)
            by_order[order][1].append(rot_cols)
        col += len(chans)
    for order, (joints, cols) in by_order.items():  # one batched call per rotation order
        angles = torch.deg2rad(bvh_motion[..., torch.tensor(cols)])  # (..., n, 3)
        rot[..., torch.tensor(joints), :, :] = euler_to_matrix(angles, order)
    return rot, root


@dataclass
class FKResult:
    """Global joint frames. positions ``(..., J, 3)`` metres; rotations ``(..., J, 3, 3)``."""

    positions: Tensor
    rotations: Tensor


def forward_kinematics(
    skeleton: Skeleton,
    rotations: Tensor,
    root_translation: Tensor,
    offsets: Tensor | None = None,
) -> FKResult:
    """Batched forward kinematics over the parents array, one tensor op per depth level.

    ``G_j = G_parent R_j``, ``p_j = p_parent + G_parent o_j``; the root is at
    ``root_translation + o_root`` with ``G_root = R_root``.

    Args:
        skeleton: the joint tree.
        rotations: ``(..., J, 3, 3)`` local rotations.
        root_translation: ``(..., 3)`` metres.
        offsets: optional ``(..., J, 3)`` per-sample offsets (body-size changes G), metres.

    Returns:
        :class:`FKResult`. Differentiable in every input.
    """
    j = skeleton.num_joints
    if rotations.shape[-3:] != (j, 3, 3):
        raise SkeletonError(f"rotations must be (..., {j}, 3, 3); got {tuple(rotations.shape)}")
    lead = rotations.shape[:-3]
    if root_translation.shape != (*lead, 3):
        raise SkeletonError(
            f"root_translation must be {(*lead, 3)}; got {tuple(root_translation.shape)}"
        )
    off = skeleton.offsets.to(rotations) if offsets is None else offsets
    off = off.expand(*lead, j, 3)
    levels = skeleton.depth_levels()
    g_rot = torch.zeros_like(rotations)
    g_pos = torch.zeros((*lead, j, 3), dtype=rotations.dtype, device=rotations.device)
    root = levels[0]
    g_rot[..., root, :, :] = rotations[..., root, :, :]
    g_pos[..., root, :] = root_translation.unsqueeze(-2) + off[..., root, :]
    for nodes in levels[1:]:  # every parent is on an earlier level
        par = skeleton.parents[nodes]
        parent_rot = g_rot[..., par, :, :]  # advanced indexing copies: safe to write below
        parent_pos = g_pos[..., par, :]
        g_rot[..., nodes, :, :] = parent_rot @ rotations[..., nodes, :, :]
        g_pos[..., nodes, :] = parent_pos + (parent_rot @ off[..., nodes, :].unsqueeze(-1)).squeeze(
            -1
        )
    return FKResult(g_pos, g_rot)


def offset_points(fk: FKResult, offsets: dict[int, Tensor], scale: float = 1.0) -> Tensor:
    """World positions of points fixed in joint frames: ``p_j + G_j (scale * o)`` for each
    ``{joint j: (3,) offset o}`` (metres, in the joint's frame), in the dict's order.

    Shapes: ``fk`` ``(..., J, 3)`` / ``(..., J, 3, 3)`` -> ``(..., n, 3)`` metres
    (``(..., 0, 3)`` for no offsets). Differentiable in ``fk``."""
    if not offsets:
        return fk.positions[..., :0, :]
    joints = torch.tensor(list(offsets), dtype=torch.long, device=fk.positions.device)
    offs = torch.stack(list(offsets.values())).to(fk.positions) * scale  # (n, 3)
    rot = fk.rotations[..., joints, :, :]
    return fk.positions[..., joints, :] + (rot @ offs.unsqueeze(-1)).squeeze(-1)


def end_site_positions(skeleton: Skeleton, fk: FKResult, scale: float = 1.0) -> Tensor:
    """World positions of the skeleton's End Sites, one row per End Site in
    ``skeleton.end_sites`` order.

    Args:
        skeleton: the joint tree (``end_sites`` offsets in metres).
        fk: its forward kinematics, positions ``(..., J, 3)`` metres, rotations
            ``(..., J, 3, 3)``.
        scale: body scale G applied to the End Site offsets (as to the bones of ``fk``).

    Returns:
        ``(..., E, 3)`` metres. :func:`end_site_positions_by_joint` gives them indexed by joint.
    """
    return offset_points(fk, skeleton.end_sites, scale)


def end_site_positions_by_joint(skeleton: Skeleton, fk: FKResult, scale: float = 1.0) -> Tensor:
    """:func:`end_site_positions` laid out by joint: ``(..., J, 3)`` metres, row ``j`` the End
    Site of joint ``j``, NaN where joint ``j`` has none (the layout of
    :func:`motion.registration.export.joint_flexion`'s ``end_sites``). Arguments as
    :func:`end_site_positions`."""
    out = torch.full_like(fk.positions, float("nan"))
    if skeleton.end_sites:
        idx = torch.tensor(list(skeleton.end_sites), dtype=torch.long)
        out[..., idx, :] = end_site_positions(skeleton, fk, scale)
    return out


def local_from_global(skeleton: Skeleton, global_rotations: Tensor) -> Tensor:
    """Relative (local) joint rotations from global part orientations: ``R_j = G_parent^T G_j``
    (the root's local rotation is its global one). This is how articulation differences A are
    read off estimated part poses; :func:`matrix_to_euler` turns them into BVH angles.

    Shapes: ``(..., J, 3, 3)`` -> ``(..., J, 3, 3)``.
    """
    parents = skeleton.parents.clamp_min(0)
    parent_rot = global_rotations[..., parents, :, :]
    local = parent_rot.transpose(-1, -2) @ global_rotations
    root = skeleton.parents < 0
    return torch.where(root[:, None, None], global_rotations, local)
