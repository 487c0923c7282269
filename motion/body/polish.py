"""Gradient polish of part poses on a soft renderer (continuous local optimisation after the
particle search: the proposal's Section 3.1.4).

Particle BP finds the basin; its estimate is a particle, a pixel or so from the optimum. The
polish moves every part by a small rigid motion to minimise, by Adam, the squared difference
between a *soft* rendering of the body and the observation -- the silhouette
(``sigmoid(-sdf / sharpness)`` of the union of capsules, whose signed distance is the
nearest capsule's) and, when an image is given, the
part-coloured image (each pixel's colour a soft depth-ordered blend of the parts covering
it) -- plus the joints' gaps (the connections' constraint) and a pull toward the start.

Units: metres, radians, pixels. Shapes: ``T`` frames, ``C`` cameras, ``P`` parts.
"""

from __future__ import annotations

import math
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
        silhouette, image: weights of the two data terms (per pixel, mean over pixels).
        joints: weight of the joints' squared gaps (per metre squared).
        stay: weight of the squared motion away from the start (regularises parts the image
            does not constrain).
        frames_per_chunk: frames optimised together (independent frames; bounds memory).
        margin_px: pixels around the observed figure and the start's outline that are
            rendered (the rest of the image cannot change the loss: a polish moves parts a
            pixel or two).
    """

    steps: int = 60
    lr: float = 2e-3
    sharpness: float = 0.7
    silhouette: float = 1.0
    image: float = 1.0
    joints: float = 1e4
    stay: float = 10.0
    frames_per_chunk: int = 8  # frames optimised together (bounds the soft renders' memory)
    margin_px: int = 6


def _soft_render(
    spec: BodySpec,
    rig: CameraRig,
    poses: Tensor,
    colours: Tensor | None,
    settings: Polish,
    window: tuple[int, int, int, int],
) -> tuple[Tensor, Tensor | None]:
    """Soft silhouette ``(T, C, h, w)`` and soft part-coloured image ``(T, C, 3, h, w)`` of
    the pixels ``window = (top, left, h, w)``."""
    top, left, h, w = window
    seg = spec.landmarks(poses)  # (T, P, 2, 3)
    parts = project_parts(rig, seg, spec.shapes.radii.to(poses))  # (T, C, P, ...)
    v, u = torch.meshgrid(
        torch.arange(top, top + h, dtype=poses.dtype, device=poses.device),
        torch.arange(left, left + w, dtype=poses.dtype, device=poses.device),
        indexing="ij",
    )
    grid = torch.stack([u, v], -1).reshape(-1, 2)
    sdf, t = capsule_sdf(grid, parts.ends, parts.radii)  # (T, C, P, hw)
    # The union's edge is where the nearest part's signed distance is 0: soften that, not
    # the parts one by one -- a soft union 1 - prod(1 - cover) reads above 1/2 outside
    # where parts overlap (at every joint), and the polish then pulls the parts apart
    # (the fit started at the truth drifted further from it than with this;
    # docs/decisions/004-tuning-evidence.md).
    sil = torch.sigmoid(-sdf.amin(dim=-2) / settings.sharpness)
    shape = (*sil.shape[:-1], h, w)
    if colours is None:
        return sil.reshape(shape), None
    # Each pixel's colour: the parts over it composited front to back, each showing its
    # cover times what the parts in front leave through, normalised over the parts -- so at
    # a front part's edge (cover 1/2) the colours blend half and half, as a pixel whose
    # centre is on that edge is as likely one as the other. (A softmax over depth let a
    # near part's colour spread past its edge, and the fit started at the truth drifted
    # further from it than with this; docs/decisions/004-tuning-evidence.md.)
    cover = torch.sigmoid(-sdf / settings.sharpness)
    z = parts.depth[..., 0:1] + t * (parts.depth[..., 1:2] - parts.depth[..., 0:1])
    order = z.detach().argsort(dim=-2)  # nearest first, per pixel
    front = cover.gather(-2, order)
    ahead = torch.cat([torch.ones_like(front[..., :1, :]), 1 - front[..., :-1, :]], dim=-2)
    through = torch.cumprod(ahead, dim=-2)  # what the parts in front let through
    weights = torch.zeros_like(front).scatter(-2, order, front * through)  # parts' order
    weights = weights / weights.sum(-2, keepdim=True).clamp_min(1e-12)
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


def _window(
    spec: BodySpec, rig: CameraRig, poses: Tensor, silhouette: Tensor, margin: int
) -> tuple[int, int, int, int]:
    """``(top, left, h, w)``: the pixels of the observed silhouettes ``(T, C, H, W)`` and of
    the capsules at ``poses`` ``(T, P, 7)``, in any frame and camera, ``margin`` around."""
    H, W = silhouette.shape[-2:]
    parts = project_parts(rig, spec.landmarks(poses), spec.shapes.radii.to(poses))
    reach = parts.radii.unsqueeze(-1)  # (T, C, P, 2, 1)
    low = (parts.ends - reach).flatten(0, -2).amin(0)  # (u, v)
    high = (parts.ends + reach).flatten(0, -2).amax(0)
    seen = silhouette.flatten(0, -3).amax(0)  # (H, W): observed in any frame and camera
    rows, cols = seen.amax(-1).nonzero(), seen.amax(-2).nonzero()
    if len(rows):
        low = torch.minimum(low, torch.stack([cols.min(), rows.min()]).to(low))
        high = torch.maximum(high, torch.stack([cols.max(), rows.max()]).to(high))
    left = int(max(0, min(W - 1, math.floor(low[0].item()) - margin)))
    top = int(max(0, min(H - 1, math.floor(low[1].item()) - margin)))
    right = int(max(left + 1, min(W, math.ceil(high[0].item()) + margin + 1)))
    bottom = int(max(top + 1, min(H, math.ceil(high[1].item()) + margin + 1)))
    return top, left, bottom - top, right - left


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
    window = _window(spec, rig, start, target_sil, settings.margin_px)
    top, left, h, w = window
    target_sil = target_sil[..., top : top + h, left : left + w]
    if target_img is not None:
        target_img = target_img[..., top : top + h, left : left + w]
    for _ in range(settings.steps):
        opt.zero_grad()
        current = torch.cat([start[..., :3] + dp, qmul(qexp(dr), start[..., 3:])], -1)
        sil, image = _soft_render(
            spec, rig, current, None if target_img is None else colours, settings, window
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
