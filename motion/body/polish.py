"""Gradient polish of part poses on a soft renderer (continuous local optimisation after the
particle search: the proposal's Section 3.1.4).

Particle BP finds the basin; its estimate is a particle, a pixel or so from the optimum. The
polish moves every part by a small rigid motion to minimise, by Adam, the squared difference
between a *soft* rendering of the body and the observation -- the silhouette
(``sigmoid(-sdf / sharpness)`` of the union of capsules) and, when an image is given, the
part-coloured image (each pixel's colour a soft depth-ordered blend of the parts covering
it) -- plus the joints' gaps (the connections' constraint) and a pull toward the start.

Units: metres, radians, pixels. Shapes: ``T`` frames, ``C`` cameras, ``P`` parts.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from motion.body.observation import Observation
from motion.body.spec import BodySpec
from motion.cameras import CameraRig
from motion.render import capsule_sdf, project_parts
from pgm.rotations import qexp, qmul, qrotate

__all__ = ["Polish", "polish"]


@dataclass(frozen=True)
class Polish:
    """Settings of :func:`polish`.

    Attributes:
        steps: Adam steps. lr: step size (metres and radians per step, roughly).
        sharpness: the soft silhouette's edge width, pixels.
        depth_softness: metres over which overlapping parts blend in the soft image.
        silhouette, image: weights of the two data terms (per pixel, mean over pixels).
        joints: weight of the joints' squared gaps (per metre squared).
        stay: weight of the squared motion away from the start (regularises parts the image
            does not constrain).
        frames_per_chunk: frames optimised together (independent frames; bounds memory).
    """

    steps: int = 60
    lr: float = 2e-3
    sharpness: float = 0.7
    depth_softness: float = 0.05
    silhouette: float = 1.0
    image: float = 1.0
    joints: float = 1e4
    stay: float = 10.0
    frames_per_chunk: int = 8  # frames optimised together (bounds the soft renders' memory)


def _soft_render(
    spec: BodySpec, rig: CameraRig, poses: Tensor, colours: Tensor | None, settings: Polish, size
) -> tuple[Tensor, Tensor | None]:
    """Soft silhouette ``(T, C, H, W)`` and soft part-coloured image ``(T, C, 3, H, W)``."""
    h, w = size
    seg = spec.landmarks(poses)  # (T, P, 2, 3)
    parts = project_parts(rig, seg, spec.shapes.radii.to(poses))  # (T, C, P, ...)
    v, u = torch.meshgrid(
        torch.arange(h, dtype=poses.dtype, device=poses.device),
        torch.arange(w, dtype=poses.dtype, device=poses.device),
        indexing="ij",
    )
    grid = torch.stack([u, v], -1).reshape(-1, 2)
    sdf, t = capsule_sdf(grid, parts.ends, parts.radii)  # (T, C, P, HW)
    cover = torch.sigmoid(-sdf / settings.sharpness)
    sil = 1 - torch.prod(1 - cover, dim=-2)  # soft union
    shape = (*sil.shape[:-1], h, w)
    if colours is None:
        return sil.reshape(shape), None
    z = parts.depth[..., 0:1] + t * (parts.depth[..., 1:2] - parts.depth[..., 0:1])
    logits = torch.log(cover.clamp_min(1e-12)) - z / settings.depth_softness
    weights = torch.softmax(logits, dim=-2)  # which part shows, among those covering
    colour = torch.einsum("tcpn,pk->tckn", weights, colours.to(poses))
    background = 0.5
    image = sil.unsqueeze(-2) * colour + (1 - sil.unsqueeze(-2)) * background
    return sil.reshape(shape), image.reshape(*shape[:-2], 3, h, w)


def polish(
    spec: BodySpec,
    rig: CameraRig,
    obs: Observation,
    poses: Tensor,
    colours: Tensor | None = None,
    settings: Polish | None = None,
) -> Tensor:
    """Polish part poses ``(T, P, 7)`` against ``obs`` (batch 1); returns ``(T, P, 7)``.

    ``colours``: ``(P, 3)`` part colours for the image term (``None``, or an observation
    without an image: silhouette only).
    """
    settings = settings or Polish()
    if obs.silhouette.shape[0] != 1:
        raise ValueError(f"polish takes an observation of batch 1; got {obs.silhouette.shape[0]}")
    if obs.silhouette.shape[1] != poses.shape[0]:
        raise ValueError(
            f"poses have {poses.shape[0]} frames; the observation {obs.silhouette.shape[1]}"
        )
    out = []
    for first in range(0, poses.shape[0], settings.frames_per_chunk):
        chunk = slice(first, first + settings.frames_per_chunk)
        part = Observation(
            obs.silhouette[:, chunk],
            image=None if obs.image is None else obs.image[:, chunk],
        )
        out.append(_polish_frames(spec, rig, part, poses[chunk], colours, settings))
    return torch.cat(out)


def _polish_frames(spec, rig, obs, poses, colours, settings) -> Tensor:
    target_sil = obs.silhouette[0].to(poses)
    target_img = None if (obs.image is None or colours is None) else obs.image[0].to(poses)
    start = poses.detach()
    dp = torch.zeros(
        *poses.shape[:-1], 3, dtype=poses.dtype, device=poses.device, requires_grad=True
    )
    dr = torch.zeros_like(dp, requires_grad=True)
    opt = torch.optim.Adam([dp, dr], lr=settings.lr)
    edges = spec.edges.to(poses.device)
    offsets = spec.offsets.to(poses)[edges[:, 1]]
    for _ in range(settings.steps):
        opt.zero_grad()
        current = torch.cat([start[..., :3] + dp, qmul(qexp(dr), start[..., 3:])], -1)
        sil, image = _soft_render(
            spec, rig, current, None if target_img is None else colours, settings, obs.size
        )
        loss = settings.silhouette * (sil - target_sil).square().sum((-1, -2)).mean()
        if image is not None:
            loss = loss + settings.image * (image - target_img).square().sum((-1, -2, -3)).mean()
        parent = current[:, edges[:, 0]]
        joint = parent[..., :3] + qrotate(parent[..., 3:], offsets.expand(len(current), -1, -1))
        gap = (joint - current[:, edges[:, 1], :3]).square().sum(-1).sum(-1).mean()
        stay = (dp.square().sum(-1) + dr.square().sum(-1)).sum(-1).mean()
        loss = loss + settings.joints * gap + settings.stay * stay
        loss.backward()
        opt.step()
    with torch.no_grad():
        return torch.cat([start[..., :3] + dp, qmul(qexp(dr), start[..., 3:])], -1)
