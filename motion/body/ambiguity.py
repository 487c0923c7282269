"""How much of a 3-D error one view cannot see: the depth flips of an orthographic camera.

Seen by one orthographic camera, a part reflected about the plane through its proximal
joint parallel to the image (a *kinematic flip*: its far end and everything attached to it
move to the mirror depth, the parts beyond it following rigidly) projects to exactly the
same outline; only which part is in front where two overlap can tell the two apart. So a
posture can be right in the image and wrong in depth by whole limbs. :func:`resolve_depth_flips`
gives each part of an estimate the flip (or not) that brings it closest to the truth in
depth -- an oracle that changes nothing in the image -- so that the 3-D error left after it
is the part of the error the images could in principle have removed, and the difference
is what one view's depth ambiguity costs.

Shapes: ``T`` frames, ``P`` parts; landmarks ``(T, P, 2, 3)`` metres (each part's proximal
and distal end, as :meth:`motion.body.spec.BodySpec.landmarks`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from motion.body.spec import topological_order

__all__ = ["resolve_depth_flips"]


def resolve_depth_flips(
    parents: Tensor, landmarks: Tensor, truth: Tensor, depth_axis: Tensor
) -> Tensor:
    """The estimate with every part's depth flip chosen against the truth.

    Parts are visited root first; a part's flip negates the depth offsets (along
    ``depth_axis``) of its distal end and of its children's proximal ends from its own
    proximal end, and is kept where it brings those points closer to the truth's depth.
    Last, each frame is shifted along ``depth_axis`` onto the truth's mean depth (the other
    thing an orthographic view cannot see). The image coordinates (across ``depth_axis``)
    are never changed.

    Args:
        parents: ``(P,)`` long, -1 for the root.
        landmarks, truth: ``(T, P, 2, 3)`` the estimate's and the true part ends.
        depth_axis: ``(3,)`` the camera's viewing direction (unit, world frame).

    Returns:
        ``(T, P, 2, 3)`` the estimate, flipped part by part.
    """
    if landmarks.shape != truth.shape or landmarks.shape[-2:] != (2, 3):
        raise ValueError(
            f"landmarks and truth must both have shape (T, P, 2, 3); got "
            f"{tuple(landmarks.shape)} and {tuple(truth.shape)}"
        )
    p = landmarks.shape[1]
    if parents.shape != (p,):
        raise ValueError(f"parents must have shape ({p},); got {tuple(parents.shape)}")
    axis = depth_axis.to(landmarks) / depth_axis.norm()
    depth = landmarks @ axis  # (T, P, 2)
    true_depth = truth @ axis
    flat = landmarks - depth[..., None] * axis  # the image-plane part, kept
    new_depth = depth.clone()
    order = topological_order(parents).tolist()
    # decide the flips from the truth's root depth (the depth shift is settled last)
    new_depth[:, order[0], 0] = true_depth[:, order[0], 0]
    for j in order:
        kids = (parents == j).nonzero().flatten().tolist()
        # offsets from j's proximal end: its distal end, then each child's proximal end
        offsets = torch.stack([depth[:, j, 1]] + [depth[:, c, 0] for c in kids], 1)
        offsets = offsets - depth[:, j, :1]
        want = torch.stack([true_depth[:, j, 1]] + [true_depth[:, c, 0] for c in kids], 1)
        base = new_depth[:, j, :1]  # j's proximal end, already placed by its parent
        keep = (base + offsets - want).abs().sum(1)
        flip = (base - offsets - want).abs().sum(1)
        sign = torch.where(flip < keep, -1.0, 1.0).to(depth)[:, None]
        placed = base + sign * offsets
        new_depth[:, j, 1] = placed[:, 0]
        for i, c in enumerate(kids):
            new_depth[:, c, 0] = placed[:, i + 1]
    # nor does an orthographic view see where the body is along its axis
    new_depth = new_depth + (true_depth - new_depth).flatten(1).mean(1)[:, None, None]
    return flat + new_depth[..., None] * axis
