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
from kornia.geometry.conversions import (
    quaternion_to_rotation_matrix,
    rotation_matrix_to_quaternion,
)
from torch import Tensor

from motion.body.spec import BodySpec
from motion.bodyparts import BodyModel
from motion.kinematics import FKResult, Skeleton, forward_kinematics

__all__ = ["Posture", "fit_part_rotations", "fit_posture", "rigid_fit"]


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


def fit_part_rotations(
    spec: BodySpec,
    poses: Tensor,
    reference: Tensor,
    prior_weight: float | Tensor = 1e-4,
    root_rotation: Tensor | None = None,
) -> Tensor:
    """Each part's rotation refitted to what images show of it, the rest from a reference.

    A capsule looks the same however it is turned about its own axis, so particle BP leaves
    a limb's twist to chance. Here each part's rotation is the least-squares rotation
    (Wahba's problem, solved by SVD) taking its vectors in its own frame -- the capsule axis
    and the joints of its children (:attr:`BodySpec.offsets`) -- onto where the estimates
    put them (its far landmark, its children's near landmarks), plus a weak pull
    (``prior_weight``, m^2: a vector of 1 cm; a limb's vectors weigh ~0.1 m^2, so the pull
    bends a real swing by ~0.1 %) toward the rotation the reference's joint angle would
    give under the already fitted parent. Where the vectors pin the rotation (a pelvis, from its
    hip joints) the pull is negligible; where they leave one axis free (a limb's twist) the
    reference decides it: the smallest articulation that explains the images. Parents are
    fitted before children, one depth level at a time. ``prior_weight`` may also be a
    tensor ``(..., P)``: one pull per part (e.g. weaker for a joint that differs from the
    reference by much).

    Shapes: ``poses`` ``(..., P, 7)`` estimates; ``reference`` ``(..., P, 7)`` part poses
    of the reference posture (only their relative rotations are used). Returns ``(..., P,
    7)``: positions unchanged, frames refitted. ``root_rotation`` ``(..., 3, 3)``: the root
    part's rotation, given (e.g. the whole body's rigid fit) instead of fitted.
    """
    if poses.shape[-2:] != (spec.num_parts, 7) or reference.shape[-2:] != poses.shape[-2:]:
        raise ValueError(
            f"poses and reference must have shape (..., {spec.num_parts}, 7); got "
            f"{tuple(poses.shape)} and {tuple(reference.shape)}"
        )
    dtype = poses.dtype
    if isinstance(prior_weight, Tensor):
        if prior_weight.shape[-1:] != (spec.num_parts,):
            raise ValueError(
                f"prior_weight must be a float or (..., {spec.num_parts}); got "
                f"{tuple(prior_weight.shape)}"
            )
        pull = prior_weight.to(dtype)[..., None, None]  # (..., P, 1, 1)
    else:
        pull = torch.full((spec.num_parts, 1, 1), float(prior_weight), dtype=dtype)
    est_rot = quaternion_to_rotation_matrix(poses[..., 3:7].contiguous())
    ref_rot = quaternion_to_rotation_matrix(reference[..., 3:7].to(dtype).contiguous())
    ends = spec.landmarks(poses)  # (..., P, 2, 3)
    axis = spec.shapes.axis.to(dtype)
    offsets = spec.offsets.to(dtype)
    fitted = est_rot.clone()
    eye = torch.eye(3, dtype=dtype, device=poses.device)
    depth = torch.zeros(spec.num_parts, dtype=torch.long, device="cpu")
    for p in spec.topological_order().tolist()[1:]:
        depth[p] = depth[int(spec.parents[p])] + 1
    for level in range(int(depth.max()) + 1):
        for p in (depth == level).nonzero().flatten().tolist():  # a level's few parts
            parent = int(spec.parents[p])
            if parent < 0 and root_rotation is not None:
                fitted[..., p, :, :] = root_rotation.to(dtype)
                continue
            if parent < 0:
                prior = est_rot[..., p, :, :]
            else:
                relative = ref_rot[..., parent, :, :].transpose(-1, -2) @ ref_rot[..., p, :, :]
                prior = fitted[..., parent, :, :] @ relative
            seen = ends[..., p, 1, :] - ends[..., p, 0, :]
            b = seen[..., :, None] * axis[p][None, :] + pull[..., p, :, :] * prior
            for child in (spec.parents == p).nonzero().flatten().tolist():
                seen = poses[..., child, :3] - poses[..., p, :3]
                b = b + seen[..., :, None] * offsets[child][None, :]
            fitted[..., p, :, :] = _nearest_rotation(b, eye)
    quat = rotation_matrix_to_quaternion(fitted.contiguous())
    return torch.cat([poses[..., :3], quat.to(dtype)], -1)


def _nearest_rotation(b: Tensor, eye: Tensor) -> Tensor:
    """``argmax_R trace(R^T B)`` over rotations (Wahba / Kabsch): ``(..., 3, 3)``."""
    u, _, vh = torch.linalg.svd(b)
    d = torch.det(u @ vh)
    fix = eye.expand_as(b).clone()
    fix[..., 2, 2] = d
    return u @ fix @ vh


def rigid_fit(
    source: Tensor, target: Tensor, weights: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """The rotation and translation taking points ``source`` onto ``target`` in (weighted)
    least squares (Kabsch): ``(..., N, 3)`` each, ``weights`` ``(..., N)`` >= 0 (``None``:
    all 1; broadcast against the points' batch) -> ``R (..., 3, 3)``, ``t (..., 3)`` with
    ``target ~ R source + t``, minimising ``sum_i w_i ||R s_i + t - x_i||^2``."""
    if source.shape != target.shape or source.shape[-1] != 3:
        raise ValueError(
            f"source and target must have the same shape (..., N, 3); got "
            f"{tuple(source.shape)} and {tuple(target.shape)}"
        )
    if weights is None:
        weights = torch.ones(source.shape[-2], dtype=source.dtype, device=source.device)
    weights = weights.to(source)[..., None]  # (..., N, 1)
    if weights.shape[-2] != source.shape[-2] or bool((weights < 0).any()):
        raise ValueError(
            f"weights must be >= 0 with one per point ({source.shape[-2]}); got shape "
            f"{tuple(weights.shape[:-1])}"
        )
    total = weights.sum(-2)  # (..., 1)
    if bool((total <= 0).any()):
        raise ValueError("every point set needs a positive total weight")
    mu_s = (weights * source).sum(-2) / total
    mu_t = (weights * target).sum(-2) / total
    b = (weights * (target - mu_t[..., None, :])).transpose(-1, -2) @ (source - mu_s[..., None, :])
    eye = torch.eye(3, dtype=source.dtype, device=source.device)
    r = _nearest_rotation(b, eye)
    return r, mu_t - (r @ mu_s[..., :, None]).squeeze(-1)
