"""Initial transforms of the pair fits, before any refinement: the yaw starts (the
reference's up on the world's up, yaws evenly spaced, :func:`_yaw_rotations`), where the
body's centroid should be (triangulated from the silhouette centroids, depth from the
silhouette's pixel height, :func:`_targets`), the pose from the 2-D joints
(:func:`_keypoint_starts`), and the caller's warm starts (:func:`_as_pair_init`).

A start (``Init``) is a rotation ``(..., 3, 3)``, the student root's world rotation acting on
column vectors, and a translation ``(..., 3)``, the root's world position in metres. Shapes:
``R`` rows (video frames of the pairs), ``W`` reference frames per row, ``C`` cameras, ``K``
keypoints.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from motion.geometry import rotation_vector_to_matrix
from motion.pose import solve_pose, solve_pose_views
from motion.registration.approximate.scene import _Scene
from motion.registration.types import RegistrationError

Init = tuple[Tensor, Tensor]


def _targets(
    scene: _Scene, rows: Tensor, cols: Tensor, depth_factor: float = 1.0, side_shift: float = 0.0
) -> Tensor:
    """Where the body's centroid should be for pairs ``rows (R,)``, ``cols (R, W)``: the
    least-squares meeting point of the rays through the silhouette centroids, with each
    (perspective) camera's depth guessed from the silhouette's pixel height against the
    body's height. Where a silhouette touches the image's top or bottom edge, that depth is
    multiplied by ``depth_factor`` (the height seen is a lower bound of the body's) and, with
    one edge clipped, the centroid is hung from the edge in view: the body's pixel height
    below its top row (or above its bottom row) times the centroid's place in ``B_t``.
    Where it touches one side edge, the centroid is moved toward that edge by
    ``side_shift`` times the body's pixel height. ``(R, W, 3)`` metres."""
    s = scene
    dt = s.landmarks.dtype
    r, w = cols.shape
    kinv = torch.linalg.inv(s.K)  # (C, 3, 3)
    clip = s.clipped[rows][:, None]  # (R, 1, C, 2) top, bottom
    clipped = clip.any(-1)  # (R, 1, C)
    height = s.height[rows][:, None]  # (R, 1, C) px
    if s.orthographic:
        body_px = s.K[:, 1, 1] * s.extent_b[cols][..., None]  # (R, W, C)
    else:
        body_px = torch.where(clipped, height / depth_factor, height).expand(r, w, -1)
    frac = s.centre_from_top[cols][..., None]  # (R, W, 1)
    v = s.centroid[rows][:, None, :, 1].expand(r, w, -1)  # (R, W, C)
    v = torch.where(clip[..., 1] & ~clip[..., 0], s.top_v[rows][:, None] + frac * body_px, v)
    v = torch.where(
        clip[..., 0] & ~clip[..., 1], s.bottom_v[rows][:, None] - (1 - frac) * body_px, v
    )
    u = s.centroid[rows][:, None, :, 0].expand(r, w, -1)
    if side_shift:
        side = s.side_clipped[rows][:, None].to(dt)  # (R, 1, C, 2) left, right
        u = u + side_shift * body_px * (side[..., 1] - side[..., 0])
    hom = torch.stack([u, v, torch.ones_like(u)], -1)  # (R, W, C, 3)
    ray_c = torch.einsum("cij,rwcj->rwci", kinv, hom)  # camera frame, z = 1
    if s.orthographic:
        origin_c = ray_c.clone()
        origin_c[..., 2] = 0.0
        origin = torch.einsum("cji,rwcj->rwci", s.R, origin_c - s.t)  # R^T (x - t)
        d = s.R[:, 2, :].expand_as(origin)
        lam0 = -(d * origin).sum(-1, keepdim=True)  # depth of the world origin
        mu = torch.full_like(lam0, 1e-3)
    else:
        origin = (-(s.R.transpose(1, 2) @ s.t[..., None])[..., 0]).expand(r, w, -1, -1)
        ray = torch.einsum("cji,rwcj->rwci", s.R, ray_c)
        length = ray.norm(dim=-1, keepdim=True)
        d = ray / length
        # depth: pixel height = f * body extent / z
        z = s.K[:, 1, 1] * s.extent_b[cols][..., None] / body_px  # (R, W, C)
        lam0 = z[..., None] * length
        mu = torch.full_like(length, s.settings.depth_prior)
    cam = s.cam_w[rows][:, None, :, None]  # (R, 1, C, 1)
    eye = torch.eye(3, dtype=dt, device=s.cam_w.device)
    ddt = d[..., :, None] * d[..., None, :]  # (R, W, C, 3, 3)
    proj = eye - ddt
    m = (cam[..., None] * (proj + mu[..., None] * ddt)).sum(2)  # (R, W, 3, 3)
    b_perp = (cam * (proj @ origin[..., None])[..., 0]).sum(2)  # (R, W, 3)
    along = (d * origin).sum(-1, keepdim=True)  # (R, W, C, 1)
    rhs = b_perp + (cam * mu * d * (along + lam0)).sum(2)
    return torch.linalg.solve(m + 1e-9 * eye, rhs)


def _yaw_rotations(scene: _Scene, count: int) -> Tensor:
    """``(count, 3, 3)``: the reference's up onto the world's up, yaws evenly spaced."""
    yaw = torch.arange(count, dtype=scene.up.dtype, device=scene.up.device) * (2 * math.pi / count)
    return rotation_vector_to_matrix(scene.up * yaw[:, None]) @ scene.align


def _keypoint_starts(scene: _Scene, rows: Tensor, cols: Tensor) -> Init | None:
    """Pose from the 2-D joints of pairs ``rows (R,)``, ``cols (R, W)``: perspective rigs by
    :func:`motion.pose.solve_pose_views` (all cameras, confidences as weights), orthographic
    ones by :func:`motion.pose.solve_pose` on the most confident camera. ``(R, W, 3, 3)``,
    ``(R, W, 3)`` metres, or ``None`` without keypoints (or with fewer than 6)."""
    s = scene
    if s.keypoints is None or s.kp_joints.numel() < 6:
        return None
    r, w = cols.shape
    x3 = s.joints[cols.reshape(-1)][:, s.kp_joints].to(torch.float64)  # (R W, K, 3)
    kp = s.keypoints[rows].to(torch.float64)[:, None].expand(-1, w, -1, -1, -1)
    kp = kp.reshape(r * w, *kp.shape[2:])  # (R W, C, K, 3)
    k64, r64, t64 = s.K.double(), s.R.double(), s.t.double()
    try:
        if s.orthographic:
            best = int(kp[..., 2].sum((0, 2)).argmax())
            res = solve_pose(x3, kp[:, best, :, :2], k64[best], orthographic=True)
            rot = r64[best].T @ res.R  # camera to world
            p = ((res.t - t64[best]) @ r64[best]).to(s.landmarks.dtype)
        else:
            res = solve_pose_views(x3, kp[..., :2], k64, r64, t64, weights=kp[..., 2])
            rot, p = res.R, res.t.to(s.landmarks.dtype)
    except ValueError:  # degenerate joints: no such start
        return None
    rot = rot.to(s.landmarks.dtype).reshape(r, w, 3, 3)
    return rot, p.reshape(r, w, 3)


def _as_pair_init(init: Init | None, rows: Tensor, cols: Tensor, dt) -> Init | None:
    """A warm start ``(R, W, 3, 3)``+``(R, W, 3)`` or per row ``(R, 3, 3)``+``(R, 3)``, checked
    and expanded to ``(R, W, ...)``."""
    if init is None:
        return None
    r, w = cols.shape
    if not (isinstance(init, tuple | list) and len(init) == 2):
        raise RegistrationError(
            f"init must be a (rotation, translation) pair of tensors; got {type(init).__name__}"
        )
    rot, p = (torch.as_tensor(x) for x in init)
    if rot.shape == (r, 3, 3) and p.shape == (r, 3):
        rot, p = rot[:, None].expand(r, w, 3, 3), p[:, None].expand(r, w, 3)
    if rot.shape != (r, w, 3, 3) or p.shape != (r, w, 3):
        raise RegistrationError(
            f"init must be rotation ({r}, {w}, 3, 3) and translation ({r}, {w}, 3), or per row "
            f"({r}, 3, 3) and ({r}, 3); got {tuple(rot.shape)} and {tuple(p.shape)}"
        )
    if not (torch.isfinite(rot).all() and torch.isfinite(p).all()):
        raise RegistrationError("init contains NaN or inf")
    return rot.to(dt), p.to(dt)
