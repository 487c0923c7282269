"""From part estimates to a skeleton posture: joint angles (articulation A) and the root (T).

Each part's frame is the global rotation of one skeleton joint (:attr:`BodySpec.frame_joints`),
so a part estimate fixes that joint's global rotation; walking the skeleton root first, its
local rotation is its parent's global rotation transposed times it. Joints that no part
drives (collar bones, the spine's links, fingers) keep the local rotations of a given
reference posture (the reference's at C(t') in registration, or a rest pose). The root
translation then puts the root part's proximal landmark where its estimate is. Exact for
postures of the model: a round trip through part poses gives back the driving joints' angles.

Shapes: ``T`` frames (any leading batch), ``J`` joints, ``P`` parts.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix
from torch import Tensor

from motion.body.spec import BodySpec
from motion.bodyparts import BodyModel
from motion.kinematics import FKResult, Skeleton, forward_kinematics

__all__ = ["Posture", "fit_posture"]


@dataclass
class Posture:
    """A skeleton posture. rotations: ``(..., J, 3, 3)`` local rotations; root: ``(..., 3)``
    metres (``forward_kinematics``'s root translation); fk: its forward kinematics."""

    rotations: Tensor
    root: Tensor
    fk: FKResult


def fit_posture(
    spec: BodySpec,
    skeleton: Skeleton,
    model: BodyModel,
    poses: Tensor,
    reference: Tensor,
) -> Posture:
    """The skeleton posture of part poses ``(..., P, 7)``, with ``reference`` ``(..., J, 3, 3)``
    local rotations for the joints that no part drives."""
    if poses.shape[-2:] != (spec.num_parts, 7):
        raise ValueError(
            f"poses must have shape (..., {spec.num_parts}, 7); got {tuple(poses.shape)}"
        )
    j = skeleton.num_joints
    if reference.shape[-3:] != (j, 3, 3):
        raise ValueError(
            f"reference must have shape (..., {j}, 3, 3); got {tuple(reference.shape)}"
        )
    dtype = reference.dtype
    part_rot = quaternion_to_rotation_matrix(
        poses[..., 3:7].to(dtype).contiguous()
    )  # (..., P, 3, 3)
    driven = {}
    for p, joint in enumerate(spec.frame_joints.tolist()):
        driven.setdefault(joint, p)
    lead = poses.shape[:-2]
    glob = [None] * j
    local = reference.expand(*lead, j, 3, 3).clone()
    for joint in range(j):  # parents come before children (Skeleton's invariant)
        parent = int(skeleton.parents[joint])
        if joint in driven:
            glob[joint] = part_rot[..., driven[joint], :, :]
            local[..., joint, :, :] = (
                glob[joint] if parent < 0 else glob[parent].transpose(-1, -2) @ glob[joint]
            )
        else:
            glob[joint] = (
                local[..., joint, :, :] if parent < 0 else glob[parent] @ local[..., joint, :, :]
            )
    zero = torch.zeros(*lead, 3, dtype=dtype, device=poses.device)
    at_origin = forward_kinematics(skeleton, local, zero)
    landmarks = model.landmarks(model.skeleton_points(skeleton, at_origin))
    root_part = int((spec.parents < 0).nonzero()[0])
    root = poses[..., root_part, :3].to(dtype) - landmarks[..., spec.from_roles[root_part], :]
    return Posture(local, root, forward_kinematics(skeleton, local, root))
