"""Rendering the body model: tapered capsules as silhouettes, part labels, outlines, intensity.

A part is a tapered capsule: the union of spheres swept along a segment with a radius that
varies linearly from ``r1`` to ``r2``. Its orthographic image is exactly the 2-D "uneven
capsule" with the same radii, whose signed distance has a closed form (used here); under
perspective the end radii are scaled by ``f / depth`` (an approximation that is exact as
the part's depth extent shrinks). Each pixel inside a part gets the depth of the part's
front surface there, so overlapping parts are ordered correctly (part-label maps).

Hypotheses are rendered in crops: :func:`render_part_hypotheses` draws K hypotheses of one
part inside a window around each, and composites them against the rest of the body drawn
once -- never the whole body K times.

Conventions: pixel centres at integer coordinates ``(u, v)``, ``u`` right, ``v`` down;
``(H, W)`` images; distances and radii in pixels; depth in metres (camera z). Shapes: ``P``
parts, ``K`` hypotheses, any leading batch ``(...)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from motion.cameras import CameraRig

__all__ = [
    "ProjectedParts",
    "capsule_area",
    "capsule_sdf",
    "label_map",
    "outline_points",
    "project_parts",
    "render_intensity",
    "render_part_hypotheses",
    "silhouette",
]


@dataclass
class ProjectedParts:
    """Parts in one or more images.

    Attributes:
        ends: ``(..., P, 2, 2)`` pixel positions of each part's two ends.
        radii: ``(..., P, 2)`` pixel radii at the ends.
        depth: ``(..., P, 2)`` camera depth (metres) of the ends.
    """

    ends: Tensor
    radii: Tensor
    depth: Tensor


def project_parts(rig: CameraRig, segments: Tensor, radii: Tensor) -> ProjectedParts:
    """Project capsules into every camera of a rig.

    Args:
        segments: ``(..., P, 2, 3)`` world end points (metres).
        radii: ``(P, 2)`` or ``(..., P, 2)`` metres.

    Returns:
        :class:`ProjectedParts` with shapes ``(..., C, P, 2, *)``.
    """
    lead = segments.shape[:-3]
    p = segments.shape[-3]
    uv, z = rig.project(segments.reshape(*lead, p * 2, 3))  # (..., C, 2P, 2), (..., C, 2P)
    c = rig.num_cameras
    uv = uv.reshape(*lead, c, p, 2, 2)
    z = z.reshape(*lead, c, p, 2)
    r = radii.to(segments).expand(*lead, p, 2).unsqueeze(-3)  # (..., 1, P, 2)
    focal = rig.K[:, 0, 0].to(segments)[:, None, None]  # (C, 1, 1)
    r_px = r * focal if rig.orthographic else r * focal / z.clamp_min(1e-6)
    return ProjectedParts(uv, r_px, z)


def capsule_sdf(points: Tensor, ends: Tensor, radii: Tensor) -> tuple[Tensor, Tensor]:
    """Signed distance (pixels) from points to 2-D uneven capsules, and the segment parameter.

    The capsule is the convex hull of the discs ``(ends[0], r1)`` and ``(ends[1], r2)``;
    negative inside. Where one disc contains the other, the capsule is the larger disc.

    Args:
        points: ``(..., N, 2)``.
        ends: ``(..., 2, 2)``. radii: ``(..., 2)``.

    Returns:
        sdf ``(..., N)`` and ``t`` ``(..., N)`` in [0, 1] (0 at the first end), the position
        along the axis of the nearest sphere centre, for depth interpolation.
    """
    a = ends[..., 0, :].unsqueeze(-2)
    axis = (ends[..., 1, :] - ends[..., 0, :]).unsqueeze(-2)
    h = axis.norm(dim=-1, keepdim=True).clamp_min(1e-9)  # (..., 1, 1)
    e_y = axis / h
    e_x = torch.stack([e_y[..., 1], -e_y[..., 0]], -1)
    rel = points - a
    px = (rel * e_x).sum(-1).abs()
    py = (rel * e_y).sum(-1)
    h = h.squeeze(-1)
    r1, r2 = radii[..., 0:1], radii[..., 1:2]
    b = ((r1 - r2) / h).clamp(-1.0, 1.0)
    a_ = torch.sqrt((1 - b * b).clamp_min(0.0))
    k = -b * px + a_ * py
    # clamp inside the roots: their gradient is infinite at 0, and torch.where would turn
    # the unused branch's inf into NaN
    d1 = torch.sqrt((px * px + py * py).clamp_min(1e-18)) - r1
    d2 = torch.sqrt((px * px + (py - h) ** 2).clamp_min(1e-18)) - r2
    side = a_ * px + b * py - r1
    sdf = torch.where(k < 0, d1, torch.where(k > a_ * h, d2, side))
    # one disc inside the other: the hull is the larger disc
    contained = (r1 - r2).abs() >= h
    sdf = torch.where(contained, torch.minimum(d1, d2), sdf)
    t = (py / h).clamp(0.0, 1.0)
    return sdf, t


def _grid(height: int, width: int, like: Tensor) -> Tensor:
    v, u = torch.meshgrid(
        torch.arange(height, dtype=like.dtype, device=like.device),
        torch.arange(width, dtype=like.dtype, device=like.device),
        indexing="ij",
    )
    return torch.stack([u, v], -1).reshape(-1, 2)  # (H*W, 2)


def _part_fields(parts: ProjectedParts, points: Tensor) -> tuple[Tensor, Tensor]:
    """sdf and front-surface depth of every part at ``points`` (N, 2): both (..., P, N)."""
    sdf, t = capsule_sdf(points, parts.ends, parts.radii)
    # depth of the part's axis at the pixel's position along it: parts are ordered by their
    # centre lines, which is what occlusion between limbs needs
    z = parts.depth[..., 0:1] + t * (parts.depth[..., 1:2] - parts.depth[..., 0:1])
    return sdf, z


def silhouette(
    parts: ProjectedParts, height: int, width: int, sharpness: float | None = None
) -> Tensor:
    """Body silhouette: hard ``(..., H, W)`` bool, or soft in (0, 1) when ``sharpness`` (pixels)
    is given: ``sigmoid(-sdf / sharpness)`` of the union (min over parts), differentiable."""
    points = _grid(height, width, parts.ends)
    sdf, _ = _part_fields(parts, points)
    union = sdf.amin(-2).reshape(*sdf.shape[:-2], height, width)
    if sharpness is None:
        return union <= 0
    return torch.sigmoid(-union / sharpness)


def label_map(parts: ProjectedParts, height: int, width: int) -> tuple[Tensor, Tensor]:
    """Which part is in front at each pixel.

    Returns:
        labels ``(..., H, W)`` long (-1 for background) and depth ``(..., H, W)`` (inf there).
    """
    points = _grid(height, width, parts.ends)
    sdf, z = _part_fields(parts, points)
    z = torch.where(sdf <= 0, z, torch.full_like(z, float("inf")))
    depth, labels = z.min(-2)
    labels = torch.where(torch.isfinite(depth), labels, torch.full_like(labels, -1))
    shape = (*labels.shape[:-1], height, width)
    return labels.reshape(shape), depth.reshape(shape)


def render_intensity(labels: Tensor, colours: Tensor, background: Tensor | float = 0.0) -> Tensor:
    """Colour a label map: ``(..., H, W)`` labels, ``(P, 3)`` colours in [0, 1] -> ``(..., 3, H, W)``."""
    bg = torch.as_tensor(background, dtype=colours.dtype, device=colours.device).expand(3)
    table = torch.cat([bg[None], colours], 0)  # index 0 = background
    img = table[(labels + 1).clamp_min(0)]
    return img.movedim(-1, -3)


def render_part_hypotheses(
    hypotheses: ProjectedParts, base_depth: Tensor, crop: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Render K hypotheses of one part against the rest of the body, drawn once.

    Each hypothesis is rasterised only inside a ``crop x crop`` window centred on its
    segment midpoint; a pixel is *visible* when the hypothesis covers it and is in front of
    ``base_depth`` (the rest of the body, from :func:`label_map` without this part).

    Args:
        hypotheses: parts with leading shape ``(K,)``: ends ``(K, 2, 2)``, radii ``(K, 2)``,
            depth ``(K, 2)`` (one camera).
        base_depth: ``(H, W)`` depth of the other parts (inf where none).
        crop: window side in pixels (make it cover the part's extent).

    Returns:
        covered ``(K, crop, crop)`` bool, visible ``(K, crop, crop)`` bool, and the window's
        top-left pixel ``(K, 2)`` long (u, v); pixels outside the image are not covered.
    """
    k = hypotheses.ends.shape[0]
    h, w = base_depth.shape
    centre = hypotheses.ends.mean(-2)  # (K, 2)
    origin = (centre - crop / 2).round().long()  # (K, 2) u, v
    local = _grid(crop, crop, hypotheses.ends)  # (crop*crop, 2)
    pix = origin.unsqueeze(1).to(local) + local.unsqueeze(0)  # (K, N, 2)
    sdf, t = capsule_sdf(pix, hypotheses.ends, hypotheses.radii)
    z = hypotheses.depth[:, 0:1] + t * (hypotheses.depth[:, 1:2] - hypotheses.depth[:, 0:1])
    u, v = pix[..., 0].long(), pix[..., 1].long()
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    covered = (sdf <= 0) & inside
    behind = base_depth[v.clamp(0, h - 1), u.clamp(0, w - 1)]
    visible = covered & (z < behind)
    return covered.reshape(k, crop, crop), visible.reshape(k, crop, crop), origin


def outline_points(
    parts: ProjectedParts, per_part: int = 32, labels: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Points evenly spaced along each part's outline (its 2-D capsule boundary: the arc
    around one end, a side line, the arc around the other end, the other side line),
    optionally keeping only those not hidden by another part.

    Args:
        parts: one image's parts, ends ``(P, 2, 2)``.
        per_part: points per part.
        labels: optional ``(H, W)`` label map; a point is kept when the pixel just inside it
            belongs to its own part.

    Returns:
        points ``(P, per_part, 2)`` pixels and visible ``(P, per_part)`` bool.
    """
    a, b_end = parts.ends[..., 0, :], parts.ends[..., 1, :]
    axis = b_end - a
    h = axis.norm(dim=-1, keepdim=True).clamp_min(1e-9)  # (P, 1)
    e_y = axis / h
    e_x = torch.stack([e_y[..., 1], -e_y[..., 0]], -1)
    r1, r2 = parts.radii[..., 0:1], parts.radii[..., 1:2]
    phi = torch.asin(((r1 - r2) / h).clamp(-1.0, 1.0))  # tangent lines' tilt
    side = h * torch.cos(phi)
    pieces = torch.cat(
        [r2 * (torch.pi - 2 * phi), side, r1 * (torch.pi + 2 * phi), side], -1
    )  # (P, 4)
    bounds = torch.cumsum(pieces, -1)
    s = (torch.arange(per_part, dtype=a.dtype, device=a.device) + 0.5) / per_part * bounds[..., 3:4]
    piece = (s.unsqueeze(-1) >= bounds.unsqueeze(-2)).sum(-1).clamp(max=3)  # (P, N)
    start = torch.cat([torch.zeros_like(bounds[..., :1]), bounds[..., :3]], -1)
    f = (s - start.gather(-1, piece)) / pieces.gather(-1, piece).clamp_min(1e-12)  # in [0, 1)

    def direction(theta):  # unit vector at local angle theta (0 = e_x, pi/2 = e_y)
        return torch.cos(theta).unsqueeze(-1) * e_x.unsqueeze(-2) + torch.sin(theta).unsqueeze(
            -1
        ) * e_y.unsqueeze(-2)

    n_right, n_left = direction(phi.expand_as(f)), direction((torch.pi - phi).expand_as(f))
    arc_b = b_end.unsqueeze(-2) + r2.unsqueeze(-1) * direction(phi + f * (torch.pi - 2 * phi))
    left = (b_end.unsqueeze(-2) + r2.unsqueeze(-1) * n_left) * (1 - f.unsqueeze(-1)) + (
        a.unsqueeze(-2) + r1.unsqueeze(-1) * n_left
    ) * f.unsqueeze(-1)
    arc_a = a.unsqueeze(-2) + r1.unsqueeze(-1) * direction(
        torch.pi - phi + f * (torch.pi + 2 * phi)
    )
    right = (a.unsqueeze(-2) + r1.unsqueeze(-1) * n_right) * (1 - f.unsqueeze(-1)) + (
        b_end.unsqueeze(-2) + r2.unsqueeze(-1) * n_right
    ) * f.unsqueeze(-1)
    candidates = torch.stack([arc_b, left, arc_a, right], -2)  # (P, N, 4, 2)
    pts = candidates.gather(-2, piece[..., None, None].expand(*piece.shape, 1, 2)).squeeze(-2)
    visible = torch.ones(pts.shape[:-1], dtype=torch.bool, device=pts.device)
    if labels is not None:
        hgt, wid = labels.shape
        along = ((pts - a.unsqueeze(-2)) * e_y.unsqueeze(-2)).sum(-1, keepdim=True)
        centre_line = a.unsqueeze(-2) + torch.minimum(
            along.clamp(min=0), h.unsqueeze(-1)
        ) * e_y.unsqueeze(-2)
        inward = torch.nn.functional.normalize(centre_line - pts, dim=-1)
        inner = pts + 1.5 * inward  # a pixel just inside the boundary
        u = inner[..., 0].round().long().clamp(0, wid - 1)
        v = inner[..., 1].round().long().clamp(0, hgt - 1)
        own = torch.arange(pts.shape[0], device=pts.device).unsqueeze(-1)
        visible = labels[v, u] == own
    return pts, visible


def capsule_area(r1: float, r2: float, length: float) -> float:
    """Exact area of the 2-D uneven capsule (convex hull of two discs at distance ``length``):
    ``r1^2 (pi/2 + phi) + r2^2 (pi/2 - phi) + (r1 + r2) length cos(phi)``,
    ``phi = asin((r1 - r2) / length)``."""
    phi = math.asin((r1 - r2) / length)
    return (
        r1**2 * (math.pi / 2 + phi)
        + r2**2 * (math.pi / 2 - phi)
        + (r1 + r2) * length * math.cos(phi)
    )
