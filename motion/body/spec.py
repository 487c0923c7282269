"""A body as data: rigid parts in SE(3), the tree that joins them, and where they join.

Built from a skeleton and a reference motion, with nothing specific to one skeleton or to
bodies: the parts and their tree come from the parts file the :class:`BodyModel` was built
from (by default the human ``motion/data/bodyparts/parts.yaml``; each part's landmarks, radii
and ``parent``), the joints' positions from the motion, and optional joint-angle limits per
kinematic edge from a limits file (:mod:`motion.body.limits`). A new articulated object is a
spec file (``motion/data/examples/robot_arm.yaml``), not new code. Each part's
*frame* is the global rotation of one skeleton joint on the chain between its two landmarks
-- the one in whose frame the part's far landmark and its children's joints move least over
the reference motion (a single bone: exactly rigid; a chain such as the spine: its stiffest
link). The capsule axis and the joint offsets are their means in those frames, and the
residual motion is reported (:attr:`BodySpec.rigidity`), so a model error is a number, not a
surprise.

A part's pose is ``(x, y, z, qw, qx, qy, qz)``: its proximal landmark in metres and its frame
(unit quaternion, ``w`` first, as :mod:`pgm.rotations`). Shapes: ``T`` frames, ``P`` parts,
``J`` skeleton joints, ``R`` landmark roles.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import torch
import yaml
from kornia.geometry.conversions import rotation_matrix_to_quaternion
from torch import Tensor

from motion.body.limits import EdgeLimits, edge_limits
from motion.body.observation import PartShapes
from motion.bodyparts import BodyModel, joint_of_point, read_parts
from motion.kinematics import FKResult, Skeleton
from motion.limits import load_limits

__all__ = ["BodySpec", "BodySpecError", "joint_parts", "part_tree", "topological_order"]


class BodySpecError(ValueError):
    """A body-part spec that does not describe a tree of parts over the skeleton."""


def part_tree(model: BodyModel, path=None) -> Tensor:
    """``(P,)`` long, the parent part of each part (-1 for the root) from the parts file's
    ``parent`` entries (default: the file ``model`` was built from), checked to form one
    tree."""
    path = Path(path or model.parts_path)
    spec = yaml.safe_load(path.read_text())["parts"]
    index = {name: i for i, name in enumerate(model.part_names)}
    parents = []
    for name in model.part_names:
        parent = spec.get(name, {}).get("parent", "missing")
        if parent == "missing":
            raise BodySpecError(f"{path}: part {name!r} has no 'parent' entry (null for the root)")
        if parent is not None and parent not in index:
            raise BodySpecError(f"{path}: part {name!r} names an unknown parent {parent!r}")
        parents.append(-1 if parent is None else index[parent])
    parents = torch.tensor(parents)
    if int((parents < 0).sum()) != 1:
        raise BodySpecError(
            f"{path}: expected exactly one root part; got {int((parents < 0).sum())}"
        )
    for p in range(len(parents)):  # every part reaches the root without a cycle
        seen, q = set(), p
        while q >= 0:
            if q in seen:
                raise BodySpecError(
                    f"{path}: the parts' parents form a cycle through {model.part_names[q]!r}"
                )
            seen.add(q)
            q = int(parents[q])
    return parents


@dataclass(frozen=True)
class BodySpec:
    """Rigid parts, their tree and joints.

    Attributes:
        part_names: P names. parents: ``(P,)`` long, -1 for the root.
        shapes: each part's capsule in its frame (:class:`PartShapes`).
        offsets: ``(P, 3)`` metres, each part's proximal landmark in its parent's frame
            (the joint; 0 for the root).
        frame_joints: ``(P,)`` long, the skeleton joint whose global rotation is the part's
            frame.
        from_roles, to_roles: ``(P,)`` long, the landmark roles at each part's ends.
        rigidity: ``(P,)`` metres, the mean distance the part's far landmark and its
            children's joints move in its frame over the reference motion (0: rigid).
        limits: joint-angle limits per kinematic edge, in :attr:`edges` order
            (:class:`~motion.body.limits.EdgeLimits`), or ``None``: unlimited.
    """

    part_names: list[str]
    parents: Tensor
    shapes: PartShapes
    offsets: Tensor
    frame_joints: Tensor
    from_roles: Tensor
    to_roles: Tensor
    rigidity: Tensor
    limits: EdgeLimits | None = None

    @property
    def num_parts(self) -> int:
        return len(self.part_names)

    @property
    def edges(self) -> Tensor:
        """``(P - 1, 2)`` long joints ``(parent, child)``, parents before children."""
        order = self.topological_order()
        return torch.stack([self.parents[order[1:]], order[1:]], 1)

    def topological_order(self) -> Tensor:
        """Parts ordered root first, every parent before its children."""
        return topological_order(self.parents)

    @classmethod
    def from_motion(
        cls,
        skeleton: Skeleton,
        model: BodyModel,
        fk: FKResult,
        limits: dict | str | Path | None = None,
    ) -> BodySpec:
        """The spec of ``model`` on ``skeleton``, with frames, axes and offsets measured on
        the reference motion ``fk`` (``(T, J, ...)``; a single frame gives a rest pose).

        Args:
            limits: per-BVH-joint Euler limits (:mod:`motion.limits`: a ``{joint: {axis:
                [lo, hi]}}`` mapping in degrees, a bundled name such as ``"cmu_cgspeed"``
                or a file), turned into per-edge limits (:func:`~motion.body.limits.
                edge_limits`). ``None``: the parts file's own ``limits`` entry if it has one
                (inline, or a name or a path relative to that file), else no limits.
        """
        parents = part_tree(model)
        landmarks = model.landmarks(model.skeleton_points(skeleton, fk))  # (T, R, 3)
        roles = {r: i for i, r in enumerate(model.roles)}
        spec = read_parts(model.parts_path)
        from_roles = torch.tensor([roles[spec[p]["from"]] for p in model.part_names])
        to_roles = torch.tensor([roles[spec[p]["to"]] for p in model.part_names])
        joints = [_chain(skeleton, model, spec[p]) for p in model.part_names]
        frames, axes, rigidity = [], [], []
        for p in range(len(model.part_names)):
            children = (parents == p).nonzero().flatten()
            targets = torch.cat([to_roles[p : p + 1], from_roles[children]])
            rel = landmarks[:, targets] - landmarks[:, from_roles[p], None]  # (T, n, 3)
            best = min(joints[p], key=lambda j: _spread(fk.rotations[:, j], rel))
            frames.append(best)
            rigidity.append(_spread(fk.rotations[:, best], rel))
        frame_joints = torch.tensor(frames)
        rot = fk.rotations[:, frame_joints]  # (T, P, 3, 3)
        local_to = _in_frame(rot, landmarks[:, to_roles] - landmarks[:, from_roles])
        axes = local_to.mean(0)
        offsets = torch.zeros(len(parents), 3, dtype=landmarks.dtype)
        for q in range(len(parents)):
            p = int(parents[q])
            if p >= 0:
                rel = landmarks[:, from_roles[q]] - landmarks[:, from_roles[p]]
                offsets[q] = _in_frame(rot[:, p], rel).mean(0)
        out = cls(
            list(model.part_names),
            parents,
            PartShapes(axes, model.radii.to(axes)),
            offsets,
            frame_joints,
            from_roles,
            to_roles,
            torch.tensor(rigidity, dtype=landmarks.dtype),
        )
        table = _joint_limits(model.parts_path, limits)
        if table is None:
            return out
        return dataclasses.replace(out, limits=edge_limits(out, skeleton, table))

    def poses(self, model: BodyModel, skeleton: Skeleton, fk: FKResult) -> Tensor:
        """Part poses of a skeleton posture: ``(..., P, 7)`` (proximal landmark, frame)."""
        landmarks = model.landmarks(model.skeleton_points(skeleton, fk))
        origin = landmarks[..., self.from_roles, :]
        quat = rotation_matrix_to_quaternion(
            fk.rotations[..., self.frame_joints, :, :].contiguous()
        )
        return torch.cat([origin, quat.to(origin)], -1)

    def landmarks(self, poses: Tensor) -> Tensor:
        """Both end landmarks of every part from part poses: ``(..., P, 7)`` ->
        ``(..., P, 2, 3)`` (the capsules' segments)."""
        return self.shapes.segments(poses, torch.arange(self.num_parts, device=poses.device))


def _joint_limits(parts_path: Path, limits) -> dict | None:
    """Per-joint limits (degrees) from an argument or the parts file's ``limits`` entry."""
    if limits is None:
        limits = (yaml.safe_load(Path(parts_path).read_text()) or {}).get("limits")
        if isinstance(limits, str) and Path(limits).suffix:
            limits = Path(parts_path).parent / limits  # relative to the parts file
    if limits is None or isinstance(limits, dict):
        return limits
    return load_limits(limits)


def topological_order(parents: Tensor) -> Tensor:
    """``(P,)`` long: parts ordered by their depth in the tree ``parents`` (-1 for the
    root), root first, every parent before its children, on ``parents``' device (the depths
    are counted on the host)."""
    depth = torch.zeros(len(parents), dtype=torch.long, device="cpu")
    for p in range(len(parents)):
        q = int(parents[p])
        while q >= 0:
            depth[p] += 1
            q = int(parents[q])
    return torch.sort(depth, stable=True).indices.to(parents.device)


def _chain(skeleton: Skeleton, model: BodyModel, part: dict) -> list[int]:
    """Skeleton joints from the part's proximal landmark's joint to its distal one's
    (excluding the distal joint itself, which rotates what lies beyond it)."""
    first, _ = joint_of_point(model.mapping[part["from"]][0])
    last_name, offset = joint_of_point(model.mapping[part["to"]][0])
    start = skeleton.index(first)
    last = skeleton.index(last_name)
    chain = [last] if offset else []  # an End Site or a synthesized end moves with its joint
    j = int(skeleton.parents[last])
    while j >= 0 and last != start:
        chain.append(j)
        if j == start:
            break
        j = int(skeleton.parents[j])
    if start not in chain:
        chain.append(start)  # the landmarks are not on one chain: the proximal joint's frame
    return chain


def joint_parts(skeleton: Skeleton, model: BodyModel) -> Tensor:
    """``(J,)`` long: the part (``model.part_names``' order) each joint moves with -- the part
    whose chain of joints (from its proximal landmark's joint towards its distal one's) holds
    the joint or, failing that, its nearest ancestor -- or -1 when none does.

    A bone (a joint's offset from its parent) and an End Site lie in the part of the joint
    they hang from: the thigh's length is the knee's offset, which hangs from the hip joint in
    the thigh's chain. So a part's length factor scales the offsets of the joints whose parent
    is in it (:meth:`motion.registration.types.Proportions.joint_scales`)."""
    spec = read_parts(model.parts_path)
    own = torch.full((skeleton.num_joints,), -1, dtype=torch.long, device="cpu")
    for p, name in enumerate(model.part_names):
        for j in _chain(skeleton, model, spec[name]):
            if own[j] < 0:  # the first part naming a joint keeps it
                own[j] = p
    out = own.clone()
    for j in range(skeleton.num_joints):  # parents come before their children
        parent = int(skeleton.parents[j])
        if out[j] < 0 and parent >= 0:
            out[j] = out[parent]
    return out


def _in_frame(rotations: Tensor, vectors: Tensor) -> Tensor:
    """World vectors in the frames: ``(..., 3, 3)``, ``(..., 3)`` -> ``(..., 3)`` (R^T v)."""
    return (rotations.transpose(-1, -2) @ vectors.unsqueeze(-1)).squeeze(-1)


def _spread(rotations: Tensor, vectors: Tensor) -> float:
    """Mean distance of vectors (T, n, 3), expressed in frames (T, 3, 3), from their mean."""
    local = _in_frame(rotations[:, None], vectors)
    return float((local - local.mean(0)).norm(dim=-1).mean())
