"""Body proportions (the proposal's G, per bone) from 2-D joints seen by calibrated cameras.

Given the posture of every frame (local joint rotations, e.g. a registration's), a joint's
position is linear in the bone lengths: ``X_j(t) = r(t) + sum_k s_k G_parent(k)(t) o_k`` over
the bones ``k`` on the chain from the root to ``j`` (``o_k`` the reference's offset, ``s_k``
its scale, ``G`` global rotations, ``r`` the root). A calibrated pinhole camera's
observation ``x`` (normalised, undistorted image coordinates) of ``X`` is the pair of linear
equations ``x (R_3 X + t_3) = R_12 X + t_12``; an orthographic camera's is ``x = R_12 X +
t_12``. So the scales and the root of every frame are one linear least-squares problem
(:func:`bone_scales`), weighted by the detections' confidences, and re-weighted by the
depths of the previous solution so that it minimises image distances, not algebraic ones.

Bones are scaled in **segments**: all bones that lead (down the tree) to the same first
observed joint share one scale (thigh: the bones between the hip's and the knee's keypoints;
the trunk: bones leading to several observed joints); bones no observed joint lies below keep
scale 1. With one perspective camera the whole body's size trades against its depth, so one
segment (``anchor``) is held at 1 and the others are relative to it.

Shapes: ``T`` frames, ``J`` joints, ``C`` cameras, ``K`` keypoints, ``S`` segments.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch import Tensor

from motion.cameras import CameraRig
from motion.kinematics import Skeleton, forward_kinematics

__all__ = ["BoneScales", "ProportionsError", "bone_scales", "segments"]


class ProportionsError(ValueError):
    """Inputs from which the proportions cannot be estimated (the message says why)."""


@dataclass(frozen=True)
class BoneScales:
    """Estimated proportions.

    Attributes:
        segments: ``S`` segment names (the observed joint each one ends at, or ``"+"``-joined
            names for a shared segment such as the trunk).
        segment_scales: ``(S,)`` each segment's bone-length factor (1: the reference's).
        joint_scales: ``(J,)`` the factor of each joint's offset (1 where unobservable).
        anchor: the segment held at 1 (one perspective camera), else ``None``.
        residual_px: ``(C,)`` RMS reprojection error of the fitted joints per camera, pixels.
    """

    segments: list[str]
    segment_scales: Tensor
    joint_scales: Tensor
    anchor: str | None
    residual_px: Tensor

    def offsets(self, skeleton: Skeleton) -> Tensor:
        """``(J, 3)`` the skeleton's offsets with these proportions, metres."""
        return skeleton.offsets * self.joint_scales[:, None].to(skeleton.offsets)


def segments(skeleton: Skeleton, observed: list[int]) -> tuple[list[str], Tensor]:
    """Each joint's segment: ``(names, (J,) long)`` with -1 for the root and for bones that
    no observed joint lies below (or whose offset is zero). A bone ``k`` (the offset from
    its parent to joint ``k``) belongs to the segment of the first observed joints at or below
    ``k``: one such joint names the segment; several (the trunk) share a segment named by
    all of them."""
    parents = skeleton.parents.tolist()
    observed_set = set(observed)
    children: dict[int, list[int]] = {}
    for j, p in enumerate(parents):
        children.setdefault(p, []).append(j)

    def first_observed(k: int) -> frozenset[int]:
        if k in observed_set:
            return frozenset([k])
        found: frozenset[int] = frozenset()
        for c in children.get(k, []):
            found |= first_observed(c)
        return found

    names: list[str] = []
    index: dict[frozenset[int], int] = {}
    out = torch.full((skeleton.num_joints,), -1, dtype=torch.long)
    for k, p in enumerate(parents):
        if p < 0 or float(skeleton.offsets[k].norm()) == 0.0:
            continue
        ends = first_observed(k)
        if not ends:
            continue
        if ends not in index:
            index[ends] = len(names)
            names.append("+".join(skeleton.names[j] for j in sorted(ends)))
        out[k] = index[ends]
    return names, out


def _normalised(rig: CameraRig, uv: Tensor) -> Tensor:
    """``(C, N, 2)`` pixels -> undistorted normalised coordinates (orthographic: metres)."""
    out = []
    for c in range(rig.num_cameras):
        k = rig.K[c].double().numpy()
        pts = uv[c].double().numpy().reshape(-1, 1, 2)
        if rig.orthographic:
            xy = (pts[:, 0] - k[:2, 2]) / np.diag(k)[:2]
        else:
            xy = cv2.undistortPoints(pts, k, rig.dist[c].double().numpy()).reshape(-1, 2)
        out.append(torch.from_numpy(np.ascontiguousarray(xy)))
    return torch.stack(out)


def bone_scales(
    skeleton: Skeleton,
    rotations: Tensor,
    rig: CameraRig,
    keypoints: Tensor,
    keypoint_joints: list[str | None],
    anchor: str | None = None,
    reweight: int = 3,
) -> BoneScales:
    """The bone-length factors that best explain 2-D joints under known postures.

    Args:
        skeleton: the reference's joint tree (its offsets are what is scaled).
        rotations: ``(T, J, 3, 3)`` local rotations, the root's global (per frame; the
            root's position is estimated with the scales).
        rig: ``C`` calibrated cameras.
        keypoints: ``(T, C, K, 3)`` pixels and confidence (0: not detected).
        keypoint_joints: for each of the ``K`` columns the skeleton joint it is (``None``:
            not a joint; left out, as are columns never detected: the segments are those of
            the joints seen).
        anchor: with one perspective camera, the segment held at 1 (default: the one with
            the most confident observations at its end).
        reweight: re-solves with each equation divided by the previous solution's depth
            (pixel-distance least squares); 0: algebraic least squares only.

    Returns:
        :class:`BoneScales`.

    Raises:
        ProportionsError: shapes that disagree, no observed joint, an unknown anchor, or too
            few observations for the unknowns.
    """
    t, j = rotations.shape[:2]
    if rotations.shape != (t, skeleton.num_joints, 3, 3):
        raise ProportionsError(
            f"rotations must be (T, {skeleton.num_joints}, 3, 3); got {tuple(rotations.shape)}"
        )
    if keypoints.shape[:2] != (t, rig.num_cameras) or keypoints.shape[-1] != 3:
        raise ProportionsError(
            f"keypoints must be ({t}, {rig.num_cameras}, K, 3); got {tuple(keypoints.shape)}"
        )
    if len(keypoint_joints) != keypoints.shape[2]:
        raise ProportionsError(
            f"{len(keypoint_joints)} keypoint joint names for {keypoints.shape[2]} columns"
        )
    detected = (keypoints[..., 2] > 0).any(0).any(0)  # (K,) a column ever seen
    cols = [i for i, n in enumerate(keypoint_joints) if n is not None and bool(detected[i])]
    joints = [skeleton.index(keypoint_joints[i]) for i in cols]
    if not joints:
        raise ProportionsError("no keypoint column names a detected joint of the skeleton")
    names, seg = segments(skeleton, joints)
    if not names:
        raise ProportionsError("no bone lies above an observed joint")
    rot = rotations.double()
    fk = forward_kinematics(skeleton, rot, torch.zeros(t, 3, dtype=torch.float64))
    # bone k's world vector G_parent(k) o_k, (T, J, 3)
    parents = skeleton.parents
    parent_rot = fk.rotations[:, parents.clamp_min(0)]
    bone = torch.einsum("tjab,jb->tja", parent_rot, skeleton.offsets.double())
    bone[:, parents < 0] = 0.0
    s = len(names)
    # V[t, j, g]: the sum of bone vectors of segment g on j's chain; fixed[t, j]: the rest
    chain = torch.zeros(j, j, dtype=torch.float64)  # chain[j, k] = 1 if k on root..j
    for q in range(j):
        k = q
        while k >= 0:
            chain[q, k] = 1.0
            k = int(parents[k])
    member = torch.zeros(j, s, dtype=torch.float64)
    member[seg >= 0, seg[seg >= 0]] = 1.0
    v = torch.einsum("qk,tka,kg->tqga", chain, bone, member)[:, joints]  # (T, O, S, 3)
    fixed = torch.einsum("qk,tka->tqa", chain * (seg < 0).double(), bone)[:, joints]  # (T, O, 3)
    obs = keypoints[:, :, cols].double()  # (T, C, O, 3)
    conf = obs[..., 2].clamp_min(0)
    if float((conf > 0).sum()) * 2 < 3 * t + s:
        raise ProportionsError(
            f"{int((conf > 0).sum())} detections cannot fix {3 * t + s} unknowns "
            "(the root of each frame and the segment scales)"
        )
    xy = _normalised(rig, obs[..., :2].permute(1, 0, 2, 3).reshape(rig.num_cameras, -1, 2))
    xy = xy.reshape(rig.num_cameras, t, len(joints), 2).permute(1, 0, 2, 3)  # (T, C, O, 2)
    r, tr = rig.R.double(), rig.t.double()
    # each equation: a . X + b = 0 with X = root + fixed + V s
    if rig.orthographic:
        a = r[None, :, None, :2, :].expand(t, -1, len(joints), -1, -1)  # (T, C, O, 2, 3)
        b = tr[None, :, None, :2] - xy
    else:
        a = r[None, :, None, :2, :] - xy[..., None] * r[None, :, None, 2:3, :]
        b = tr[None, :, None, :2] - xy * tr[None, :, None, 2:3]
    b = b + torch.einsum("tcoea,toa->tcoe", a, fixed)
    a_scale = torch.einsum("tcoea,tosa->tcoes", a, v)  # (T, C, O, 2, S)
    a_root = torch.zeros(t, rig.num_cameras, len(joints), 2, t, 3, dtype=torch.float64)
    a_root[torch.arange(t), :, :, :, torch.arange(t)] = a
    design = torch.cat([a_root.reshape(t, rig.num_cameras, len(joints), 2, 3 * t), a_scale], -1)
    design = design.reshape(-1, 3 * t + s)
    rhs = -b.reshape(-1)
    weight = conf[..., None].expand(-1, -1, -1, 2).reshape(-1).sqrt()
    anchor_index = None
    if not rig.orthographic and rig.num_cameras == 1:
        per_segment = torch.zeros(s, dtype=torch.float64)
        for o, q in enumerate(joints):
            k = q  # the segment ending at this observed joint
            if seg[k] >= 0:
                per_segment[seg[k]] += conf[:, :, o].sum()
        if anchor is None:
            anchor_index = int(per_segment.argmax())
        elif anchor not in names:
            raise ProportionsError(f"anchor must be one of {names}; got {anchor!r}")
        else:
            anchor_index = names.index(anchor)
    keep = torch.ones(3 * t + s, dtype=torch.bool)
    if anchor_index is not None:
        keep[3 * t + anchor_index] = False
        rhs = rhs - design[:, 3 * t + anchor_index]
    depth_w = torch.ones_like(weight)
    for _ in range(reweight + 1):
        w = weight / depth_w
        sol = torch.linalg.lstsq(design[:, keep] * w[:, None], rhs * w, driver="gelsd").solution
        full = torch.ones(3 * t + s, dtype=torch.float64)
        full[keep] = sol
        x = full[: 3 * t].reshape(t, 1, 3) + fixed + torch.einsum("tosa,s->toa", v, full[3 * t :])
        if rig.orthographic:
            break
        z = torch.einsum("ca,toa->tco", r[:, 2], x) + tr[None, :, None, 2]
        depth_w = z[..., None].expand(-1, -1, -1, 2).reshape(-1).abs().clamp_min(1e-3)
    scales = full[3 * t :]
    joint_scales = torch.ones(j, dtype=torch.float64)
    joint_scales[seg >= 0] = scales[seg[seg >= 0]]
    uv, _ = rig.project(x.reshape(t, len(joints), 3).to(rig.K.dtype))  # (T, C, O, 2)
    err = (uv.double() - obs[..., :2]).norm(dim=-1)
    seen = conf > 0
    residual = torch.stack(
        [
            err[:, c][seen[:, c]].square().mean().sqrt()
            if seen[:, c].any()
            else torch.tensor(float("nan"), dtype=torch.float64)
            for c in range(rig.num_cameras)
        ]
    )
    return BoneScales(
        names,
        scales,
        joint_scales,
        names[anchor_index] if anchor_index is not None else None,
        residual,
    )
