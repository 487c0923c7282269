"""Occlusion-aware observation factors: part hypotheses scored against image features.

The proposal's ``phi_j(x_j, X_-j, z_j)`` (Eqs. 28-29): each hypothesis of part j is seen
together with the other parts' current estimates ``X_-j``, and only the pixels j can own --
covered by it and not behind another part -- count for it. Nothing is rasterised per
hypothesis. Each part's 2-D capsule carries a fixed set of sample points in its own canonical
coordinates (interior points with their area, outline points with their length; a
:class:`SampleLayout`), which are projected with the hypothesis and *gathered* from maps:
the observed silhouette, the distance to observed edges, the image, and -- for occlusion --
the depth of the rest of the body, rendered once per iteration as the two nearest surfaces
of every pixel (the rest without part j is the nearest surface unless that is j itself, then
the second). The cost is O(points) per hypothesis, not O(pixels).

What a hypothesis scores is the sum over cameras of its :class:`Cue` s (each a small class
with one scoring method over the shared :class:`PartSamples`), combined as data with
weights: ``BodyObservation(..., cues=[Silhouette(), Edges()])``.

Conventions: pixel centres at integer ``(u, v)``, ``u`` right, ``v`` down (as
:mod:`motion.render`); a part's depth at a point is that of its axis there (as the label
maps). A part's state is its rigid pose ``(x, y, z, qw, qx, qy, qz)`` (metres, a unit
quaternion as :mod:`pgm.rotations`); its capsule runs from the pose's origin to ``R axis``.
Shapes: ``B`` batch, ``T`` frames, ``C`` cameras, ``P`` parts per frame, ``N`` nodes of a
unary group, ``K`` hypotheses, ``S`` sample points, ``H x W`` images.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from motion.cameras import CameraRig
from motion.render import ProjectedParts, capsule_sdf, project_parts
from pgm import AnnealingStep, Constant, Schedule, UnaryFactor
from pgm.rotations import qrotate

__all__ = [
    "BodyObservation",
    "Cue",
    "Edges",
    "Intensity",
    "Joints2D",
    "NonPenetration",
    "Observation",
    "PartSamples",
    "PartShapes",
    "RestLayers",
    "SampleLayout",
    "Samples",
    "Silhouette",
    "body_layers",
    "poses_from_segments",
    "segment_distance",
]


# -- geometry of parts ---------------------------------------------------------------------
@dataclass(frozen=True)
class PartShapes:
    """Each part's capsule in its own frame: from the origin to ``axis``.

    Attributes:
        axis: ``(P, 3)`` metres, the distal end in the part's frame (the proximal end is
            the origin).
        radii: ``(P, 2)`` metres at the proximal and distal end.
    """

    axis: Tensor
    radii: Tensor

    def __post_init__(self):
        if self.axis.dim() != 2 or self.axis.shape[-1] != 3:
            raise ValueError(f"axis must have shape (P, 3); got {tuple(self.axis.shape)}")
        if self.radii.shape != (self.axis.shape[0], 2):
            raise ValueError(
                f"radii must have shape ({self.axis.shape[0]}, 2); got {tuple(self.radii.shape)}"
            )
        if not (torch.isfinite(self.axis).all() and (self.radii > 0).all()):
            raise ValueError("part axes must be finite and radii > 0")

    @property
    def num_parts(self) -> int:
        return self.axis.shape[0]

    @classmethod
    def from_segments(cls, segments: Tensor, radii: Tensor) -> PartShapes:
        """Capsules of the lengths of ``segments`` ``(P, 2, 3)`` along each part's local z
        (the convention of :func:`poses_from_segments`); radii ``(P, 2)`` metres."""
        length = (segments[:, 1] - segments[:, 0]).norm(dim=-1)
        axis = torch.zeros(len(length), 3, dtype=segments.dtype, device=segments.device)
        axis[:, 2] = length
        return cls(axis, radii.to(segments))

    def segments(self, poses: Tensor, parts: Tensor, trailing: int = 0) -> Tensor:
        """World end points of parts ``parts`` at ``poses``.

        Shapes: poses ``(..., N, M_1..M_trailing, 7)`` (the node axis of ``parts`` ``(N,)``
        followed by ``trailing`` more axes, e.g. hypotheses) -> ``(..., 2, 3)`` (proximal,
        distal; metres).
        """
        axis = self.axis.to(poses)[parts.to(poses.device)]  # (N, 3)
        axis = axis.reshape(axis.shape[0], *([1] * trailing), 3).expand(*poses.shape[:-1], 3)
        origin = poses[..., :3]
        return torch.stack([origin, origin + qrotate(poses[..., 3:7], axis)], -2)


def poses_from_segments(segments: Tensor) -> Tensor:
    """Part poses whose local z runs along each segment: origin at the proximal end and
    the shortest rotation taking z to the segment's direction (the twist about the axis,
    which a capsule does not show, is the minimal one). Shapes: ``(..., P, 2, 3)`` ->
    ``(..., P, 7)``."""
    d = torch.nn.functional.normalize(segments[..., 1, :] - segments[..., 0, :], dim=-1)
    w = 1.0 + d[..., 2]
    q = torch.stack([w, -d[..., 1], d[..., 0], torch.zeros_like(w)], -1)
    flipped = w < 1e-9  # pointing along -z: a half turn about x
    half = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=q.dtype, device=q.device).expand_as(q)
    q = torch.nn.functional.normalize(torch.where(flipped[..., None], half, q), dim=-1)
    return torch.cat([segments[..., 0, :], q], -1)


def _node_axis_view(t: Tensor, ndim: int) -> Tensor:
    """A per-node tensor ``(N,)`` viewed for ``(B, N, ...)`` broadcasting over ``ndim`` axes."""
    return t.reshape(1, t.shape[0], *([1] * (ndim - 2)))


# -- sample points ---------------------------------------------------------------------------
@dataclass(frozen=True)
class SampleLayout:
    """Where the sample points of a 2-D capsule sit, in canonical coordinates.

    Interior: ``along x across`` points on the body between the ends (each standing for an
    equal share of the trapezoid's area) and ``cap_points`` on each end's half-disc (equal
    area shares); outline: ``side`` points per side line and ``arc`` per end arc, each
    standing for its share of the length. The defaults give 48 interior and 24 outline points
    (a 25 x 8 px limb: ~6 px^2 per interior point).
    """

    along: int = 8
    across: int = 4
    cap_points: int = 8
    side: int = 8
    arc: int = 4

    def canonical(self, dtype=torch.float32) -> tuple[Tensor, Tensor]:
        """``(6, S_interior)`` and ``(6, S_outline)`` rows ``s, s_r, alpha, beta, c_L, c_A``:
        point ``a + s (b - a) + r(s_r) (alpha e + beta n)`` with ``r(s_r)`` the radius there,
        ``e`` the unit axis and ``n`` its normal; weight ``c_L L r + c_A r^2`` (interior, px^2)
        or ``c_L L + c_A r`` (outline, px)."""

        def mid(n):
            return (torch.arange(n, dtype=torch.float64, device="cpu") + 0.5) / n

        cols = []
        s = mid(self.along).repeat_interleave(self.across)
        w = (2 * mid(self.across) - 1).repeat(self.along)
        z = torch.zeros_like(s)
        cols.append(torch.stack([s, s, z, w, z + 2 / (self.along * self.across), z]))
        # caps: a half-disc outward of each end, equal-area rings x sectors
        rings = max(1, round(math.sqrt(self.cap_points / 2)))
        sectors = max(1, self.cap_points // rings)
        rho = mid(rings).sqrt().repeat_interleave(sectors)
        theta = (mid(sectors) - 0.5).repeat(rings) * math.pi
        n = rho.numel()
        zc = torch.zeros(n, dtype=torch.float64, device="cpu")
        area = zc + (math.pi / 2) / n
        for end, sign in ((0.0, -1.0), (1.0, 1.0)):
            cols.append(
                torch.stack(
                    [zc + end, zc + end, sign * rho * theta.cos(), rho * theta.sin(), zc, area]
                )
            )
        interior = torch.cat(cols, 1)
        s = mid(self.side)
        zs = torch.zeros_like(s)
        lines = [torch.stack([s, s, zs, zs + side, zs + 1 / self.side, zs]) for side in (-1, 1)]
        theta = (mid(self.arc) - 0.5) * math.pi
        za = torch.zeros_like(theta)
        arcs = [
            torch.stack(
                [za + end, za + end, sign * theta.cos(), theta.sin(), za, za + math.pi / self.arc]
            )
            for end, sign in ((0.0, -1.0), (1.0, 1.0))
        ]
        outline = torch.cat([*lines, *arcs], 1)
        return interior.to(dtype), outline.to(dtype)


def _place(canon: Tensor, parts: ProjectedParts, area: bool) -> tuple[Tensor, Tensor, Tensor]:
    """Points, weights and depths of canonical samples on projected capsules.

    Shapes: canon ``(6, S)``; parts with leading ``(...)`` -> ``(..., S, 2)``, ``(..., S)``,
    ``(..., S)``.
    """
    s, s_r, alpha, beta, c_len, c_rad = canon.to(parts.ends).unbind(0)
    a, b = parts.ends[..., 0, :], parts.ends[..., 1, :]
    d = b - a
    length = d.norm(dim=-1, keepdim=True)  # (..., 1)
    e = d / length.clamp_min(1e-6)
    n = torch.stack([-e[..., 1], e[..., 0]], -1)
    r1, r2 = parts.radii[..., 0:1], parts.radii[..., 1:2]
    r = r1 + s_r * (r2 - r1)  # (..., S)
    offset = (alpha * r).unsqueeze(-1) * e.unsqueeze(-2) + (beta * r).unsqueeze(-1) * n.unsqueeze(
        -2
    )
    points = a.unsqueeze(-2) + s.unsqueeze(-1) * d.unsqueeze(-2) + offset
    weight = c_len * length * r + c_rad * r * r if area else c_len * length + c_rad * r
    z1, z2 = parts.depth[..., 0:1], parts.depth[..., 1:2]
    return points, weight, z1 + s * (z2 - z1)


# -- the rest of the body, rendered once per iteration ---------------------------------------
@dataclass
class RestLayers:
    """The two nearest part surfaces at every pixel.

    Attributes:
        label, second_label: ``(B, T, C, H, W)`` long, the nearest and the second nearest
            part (-1 for none).
        near, second: ``(B, T, C, H, W)`` depth (metres) of the nearest and the second
            nearest part surface (inf where there is none).
    """

    label: Tensor
    near: Tensor
    second: Tensor
    second_label: Tensor

    @classmethod
    def empty(cls, shape: Sequence[int], like: Tensor) -> RestLayers:
        """No other parts anywhere (each part is rendered alone: the occlusion-unaware
        ablation). ``shape`` is ``(B, T, C, H, W)``."""
        inf = torch.full(tuple(shape), math.inf, dtype=like.dtype, device=like.device)
        label = torch.full(tuple(shape), -1, dtype=torch.long, device=like.device)
        return cls(label, inf, inf, label)


#: metres per part index added to the depths only to order them in :func:`body_layers`:
#: ties within it go to the lower index. Far above float32 rounding at camera depths
#: (~5e-7 m at 5 m), far below any part's radius (15 parts: 0.14 mm at most).
DEPTH_TIE_BREAK = 1e-5
#: pixels where :func:`body_layers` puts a part the cameras cannot image: off every image
_NOWHERE = -1e6


def body_layers(parts: ProjectedParts, height: int, width: int, rows: int = 32) -> RestLayers:
    """Render the nearest two surfaces of all parts at every pixel.

    Parts are projected capsules with leading shape ``(B, T, C, P)``. Only the pixels of
    each image's body box (every part's extent, one common size for the batch) are
    evaluated -- ~1/5 of a 160 x 120 image for a whole body -- in bands of ``rows`` box rows,
    so that the ``(..., P, pixels)`` distance field stays small; the rest is background.
    Returns :class:`RestLayers` ``(B, T, C, H, W)``.
    """
    lead = parts.ends.shape[:-3]
    p = parts.ends.shape[-3]
    n = math.prod(lead)
    dev, dtype = parts.ends.device, parts.ends.dtype
    ends = parts.ends.reshape(n, p, 2, 2)
    radii = parts.radii.expand(*lead, p, 2).reshape(n, p, 2)
    depth = parts.depth.reshape(n, p, 2)
    # a part the cameras cannot image (a NaN pose, a point at the camera's centre) covers
    # nothing: far off the image, no width, infinitely deep
    imaged = (
        torch.isfinite(ends).all(-1).all(-1)
        & torch.isfinite(radii).all(-1)
        & torch.isfinite(depth).all(-1)
    )[..., None]  # (n, P, 1)
    ends = torch.where(imaged[..., None], ends, torch.full_like(ends, _NOWHERE))
    radii = torch.where(imaged, radii, torch.zeros_like(radii))
    depth = torch.where(imaged, depth, torch.full_like(depth, math.inf))
    reach = radii.amax(-1)[..., None]  # (n, P, 1)
    top_left = (ends.amin(-2) - reach).amin(-2).floor()  # (n, 2) u, v
    bottom_right = (ends.amax(-2) + reach).amax(-2).ceil()
    limit = torch.tensor([width - 1, height - 1], dtype=dtype, device=dev)
    top_left = top_left.clamp(min=0)
    bottom_right = torch.minimum(bottom_right, limit)
    size = (bottom_right - top_left + 1).clamp(min=1).amax(0)  # (2,) box width, height
    box_w, box_h = int(size[0]), int(size[1])
    box = torch.tensor([box_w, box_h], dtype=dtype, device=dev)
    origin = torch.minimum(top_left, limit + 1 - box).clamp(min=0)  # boxes inside the image
    label = torch.full((n, height * width), -1, dtype=torch.long, device=dev)
    second_label = label.clone()
    near = torch.full((n, height * width), math.inf, dtype=dtype, device=dev)
    second = near.clone()
    u = torch.arange(box_w, dtype=dtype, device=dev)
    tie = DEPTH_TIE_BREAK * torch.arange(p, dtype=dtype, device=dev)[:, None]  # (P, 1)
    for top in range(0, box_h, rows):
        v = torch.arange(top, min(top + rows, box_h), dtype=dtype, device=dev)
        local = torch.stack(torch.meshgrid(v, u, indexing="ij")[::-1], -1).reshape(-1, 2)
        pixels = origin[:, None, :] + local[None]  # (n, m, 2)
        sdf, t = capsule_sdf(pixels[:, None], ends, radii)  # (n, P, m)
        z = depth[..., 0:1] + t * (depth[..., 1:2] - depth[..., 0:1])
        z = torch.where(sdf <= 0, z, torch.full_like(z, math.inf))
        if p >= 2:
            # adjacent parts meet at a joint at one depth: there the nearest is chosen by
            # part index, not by rounding (CPU and CUDA rounded such ties apart, which gave
            # the Intensity cue another covered colour); the depths kept are the true ones
            idx = torch.topk(z + tie, 2, dim=-2, largest=False).indices
            top2 = z.gather(-2, idx)
            first, nxt = top2[:, 0], top2[:, 1]
            idx_next = idx[:, 1]
        else:
            first, idx = z.min(-2, keepdim=True)
            first, nxt = first[:, 0], torch.full_like(first[:, 0], math.inf)
            idx_next = torch.zeros_like(idx[:, 0])
        flat = (pixels[..., 1] * width + pixels[..., 0]).long()  # (n, m)
        near.scatter_(1, flat, first)
        second.scatter_(1, flat, nxt)
        label.scatter_(1, flat, torch.where(torch.isfinite(first), idx[:, 0], -1))
        second_label.scatter_(1, flat, torch.where(torch.isfinite(nxt), idx_next, -1))
    shape = (*lead, height, width)
    return RestLayers(
        label.reshape(shape),
        near.reshape(shape),
        second.reshape(shape),
        second_label.reshape(shape),
    )


# -- observations ----------------------------------------------------------------------------
@dataclass
class Observation:
    """Image features of T frames seen by C cameras (every map ``(B or 1, T, C, H, W)``).

    Attributes:
        silhouette: the person's silhouette, float in [0, 1] (soft masks allowed).
        edge_distance: pixels to the nearest observed edge (``None``: no edge cue).
        image: ``(B or 1, T, C, 3, H, W)`` colour in [0, 1] (``None``: no intensity cue).
        keypoints: ``(B or 1, T, C, J, 3)`` detected 2-D joints ``u, v, confidence``
            (confidence 0: missing), or ``None``.
    """

    silhouette: Tensor
    edge_distance: Tensor | None = None
    image: Tensor | None = None
    keypoints: Tensor | None = None

    def __post_init__(self):
        if self.silhouette.dim() != 5:
            raise ValueError(
                f"silhouette must have shape (B, T, C, H, W); got {tuple(self.silhouette.shape)}"
            )
        lead = self.silhouette.shape
        if self.edge_distance is not None and self.edge_distance.shape != lead:
            raise ValueError(
                f"edge_distance must have the silhouette's shape {tuple(lead)}; got "
                f"{tuple(self.edge_distance.shape)}"
            )
        if self.image is not None and self.image.shape != (*lead[:3], 3, *lead[3:]):
            raise ValueError(
                f"image must have shape {(*lead[:3], 3, *lead[3:])}; got {tuple(self.image.shape)}"
            )
        if self.keypoints is not None and (
            self.keypoints.dim() != 5 or self.keypoints.shape[:3] != lead[:3]
        ):
            raise ValueError(
                f"keypoints must have shape {(*lead[:3], 'J', 3)}; got {tuple(self.keypoints.shape)}"
            )

    @property
    def size(self) -> tuple[int, int]:
        """``(H, W)``."""
        return tuple(self.silhouette.shape[-2:])


@dataclass
class PartSamples:
    """One kind of sample points (interior or outline) of every hypothesis in every camera,
    and what the renderer found there. Point values are ``(B, N, C, K, S)``.

    Attributes:
        points: ``(..., S, 2)`` pixels. weight: px^2 (interior) or px (outline).
        depth: the part's depth at each point (metres).
        inside: the point lies in the image.
        rest_depth: depth of the rest of the body there (inf: uncovered).
        near_label: the nearest part of the whole current body there (-1: none); with
            ``second_labels`` (the flattened second-nearest label map) it gives
            :attr:`rest_label`, gathered only when a cue asks.
        flat: index of each point's pixel in the flattened ``(B, T, C, H, W)`` maps.
    """

    points: Tensor
    weight: Tensor
    depth: Tensor
    inside: Tensor
    rest_depth: Tensor
    near_label: Tensor
    second_labels: Tensor
    flat: Tensor
    batch_maps: int  # B of the maps the index was made for (1: shared by the batch)
    image_base: Tensor  # index of each point's image's first pixel in the flattened maps
    parts: Tensor  # (N,) part of each node

    @property
    def rest_label(self) -> Tensor:
        """The part of the rest of the body in front at each point (-1: uncovered)."""
        mine = self.near_label == _node_axis_view(self.parts, self.near_label.dim())
        return torch.where(mine, self.second_labels[self.flat], self.near_label)

    @property
    def own(self) -> Tensor:
        """Points the hypothesis owns: in the image and in front of the rest of the body."""
        return self.inside & (self.depth < self.rest_depth)

    @property
    def rest_covered(self) -> Tensor:
        return torch.isfinite(self.rest_depth)

    def gather(self, maps: Tensor, outside: float = 0.0, smooth: bool = False) -> Tensor:
        """Values of ``(B or 1, T, C, H, W)`` maps at the points (``outside`` where a point
        leaves the image): the nearest pixel's, or with ``smooth`` bilinearly interpolated
        (continuous in the pose: sub-pixel moves change the score).
        ``(B or 1, T, C, ch, H, W)`` maps give ``(..., S, ch)``."""
        if maps.dim() == 6:
            chans = [self.gather(maps[:, :, :, i], outside, smooth) for i in range(maps.shape[3])]
            return torch.stack(chans, -1)
        flat = maps.reshape(-1)
        if not smooth:
            vals = flat[self._index(maps)]
        else:
            h, w = maps.shape[-2:]
            base = self.image_base if maps.shape[0] == self.batch_maps else self._shared(maps)
            u = self.points[..., 0].clamp(0, w - 1)
            v = self.points[..., 1].clamp(0, h - 1)
            u0 = u.floor().clamp(max=max(w - 2, 0))
            v0 = v.floor().clamp(max=max(h - 2, 0))
            fu, fv = u - u0, v - v0
            i = base + v0.long() * w + u0.long()
            right, down = (1 if w > 1 else 0), (w if h > 1 else 0)
            top = flat[i] * (1 - fu) + flat[i + right] * fu
            bottom = flat[i + down] * (1 - fu) + flat[i + down + right] * fu
            vals = top * (1 - fv) + bottom * fv
        return torch.where(self.inside, vals, torch.full_like(vals, outside))

    def _shared(self, maps: Tensor) -> Tensor:
        if maps.shape[0] != 1:
            raise ValueError(f"maps have batch {maps.shape[0]}; expected 1 or {self.batch_maps}")
        return self.image_base % maps[0].numel()

    def _index(self, maps: Tensor) -> Tensor:
        if maps.shape[0] == self.batch_maps:
            return self.flat
        if maps.shape[0] == 1:  # a map shared by the batch: drop the batch offset
            return self.flat % maps[0].numel()
        raise ValueError(f"maps have batch {maps.shape[0]}; expected 1 or {self.batch_maps}")


@dataclass
class Samples:
    """Everything the cues may score, shared by all of them (one projection per call).

    Attributes:
        interior, outline: :class:`PartSamples`.
        ends: ``(B, N, C, K, 2, 2)`` projected part ends (pixels).
        segments: ``(B, N, K, 2, 3)`` world end points of the hypotheses (metres).
        rest_segments: ``(B, T, P, 2, 3)`` world end points of every part's estimate.
        parts: ``(N,)`` part index of each node; frames: ``(N,)`` its frame.
        radii: ``(P, 2)`` part radii (metres).
    """

    interior: PartSamples
    outline: PartSamples
    ends: Tensor
    segments: Tensor
    rest_segments: Tensor
    parts: Tensor
    frames: Tensor
    radii: Tensor


# -- cues ------------------------------------------------------------------------------------
class Cue:
    """One term of an observation factor. Subclasses implement :meth:`score`.

    A cue reads :class:`Samples` (the hypotheses' sample points and what the renderer found
    under them) and the :class:`Observation`; it returns log-potentials per camera, which the
    factor sums. Weights are part of the cue (its constructor), so cues combine as data.
    """

    def score(self, samples: Samples, obs: Observation) -> Tensor:
        """Shapes: -> ``(B, N, C, K)`` log-potentials (nats), one column per camera."""
        raise NotImplementedError(f"{type(self).__name__} must implement score")


@dataclass
class Silhouette(Cue):
    """Silhouette in both directions, in nats per pixel.

    ``-outside * |pixels j owns outside the silhouette|`` (model -> observation) plus
    ``+uncovered * |silhouette pixels j covers that the rest of the body leaves uncovered|``
    (observation -> model: a limb hidden inside the torso explains nothing). Points outside
    the image count as background.
    """

    outside: float = 0.1
    uncovered: float = 0.1
    smooth: bool = False  # bilinear reads of the silhouette (use a soft one: sub-pixel)

    def score(self, samples, obs):
        inner = samples.interior
        sil = inner.gather(obs.silhouette, smooth=self.smooth)
        w = inner.weight
        spill = (w * inner.own * (1 - sil)).sum(-1)
        explained = (w * inner.inside * sil * ~inner.rest_covered).sum(-1)
        return self.uncovered * explained - self.outside * spill


@dataclass
class Edges(Cue):
    """Chamfer: the part's visible outline against the distance to observed edges.

    ``-weight * sum over outline length of min(d, truncate)^2 / truncate^2`` (nats per pixel
    of outline); a hidden stretch of outline costs what a stretch ``truncate / 2`` away costs
    (no reward for hiding).
    """

    weight: float = 0.2
    truncate: float = 8.0
    smooth: bool = False  # bilinear reads of the distance map

    def score(self, samples, obs):
        if obs.edge_distance is None:
            raise ValueError("the Edges cue needs Observation.edge_distance")
        line = samples.outline
        d = line.gather(obs.edge_distance, outside=self.truncate, smooth=self.smooth)
        d = d.clamp(max=self.truncate)
        cost = (d / self.truncate).square()
        cost = torch.where(line.own, cost, torch.full_like(cost, 0.25))
        return -self.weight * (line.weight * cost).sum(-1)


@dataclass
class Intensity(Cue):
    """Per-part appearance, in nats per pixel: where part j is in front, the image should
    show its colour, ``cost_j = |I - colour_j|^2 / (2 sigma^2)``.

    With ``replaces_rest`` (default) the score is what placing j changes in the whole
    body's colour likelihood: on each pixel j owns, the part of the rest it covers up (if
    any) no longer has to explain that pixel, ``-weight * sum over owned area of (cost_j -
    cost_rest)`` -- so an arm gains by lying in front of the torso where the image shows the
    arm's colour (without this term, hiding behind the torso would cost nothing). Without
    it, ``-weight * sum over owned area of cost_j``. ``colours``: ``(P, 3)`` in [0, 1].
    """

    colours: Tensor
    weight: float = 0.05
    sigma: float = 0.1
    replaces_rest: bool = True

    def score(self, samples, obs):
        if obs.image is None:
            raise ValueError("the Intensity cue needs Observation.image")
        inner = samples.interior
        seen = inner.gather(obs.image)  # (B, N, C, K, S, 3)
        colours = self.colours.to(seen)
        colour = colours[samples.parts.to(seen.device)]  # (N, 3)
        cost = (seen - colour[None, :, None, None, None, :]).square().sum(-1)
        if self.replaces_rest:
            label = inner.rest_label
            covered = label >= 0
            rest = colours[label.clamp_min(0)]  # (B, N, C, K, S, 3)
            cost = cost - covered * (seen - rest).square().sum(-1)
        return -self.weight / (2 * self.sigma**2) * (inner.weight * inner.own * cost).sum(-1)


@dataclass
class Joints2D(Cue):
    """Detected 2-D joints against the part's projected ends, robust to outliers:
    ``-weight * sum conf * log(1 + |uv - keypoint|^2 / sigma^2)`` (Cauchy; sigma in pixels).

    ``part_keypoints``: ``(P, 2)`` long, the keypoint index of each part's proximal and
    distal end (-1: none).
    """

    part_keypoints: Tensor
    weight: float = 1.0
    sigma: float = 4.0

    def score(self, samples, obs):
        if obs.keypoints is None:
            raise ValueError("the Joints2D cue needs Observation.keypoints")
        dev = samples.ends.device
        idx = self.part_keypoints.to(dev)[samples.parts.to(dev)]  # (N, 2)
        kp = obs.keypoints.to(samples.ends)[:, samples.frames.to(dev)]  # (B', N, C, J, 3)
        b, n, c = kp.shape[:3]
        which = idx.clamp_min(0)[None, :, None, :, None].expand(b, n, c, 2, 3)
        chosen = kp.gather(3, which).unsqueeze(3)  # (B', N, C, 1, 2, 3)
        conf = chosen[..., 2] * (idx >= 0)[None, :, None, None, :]
        d2 = (samples.ends - chosen[..., :2]).square().sum(-1)  # (B, N, C, K, 2)
        return -self.weight * (conf * torch.log1p(d2 / self.sigma**2)).sum(-1)


@dataclass
class NonPenetration(Cue):
    """Soft non-penetration against the other parts' estimates in the same frame:
    ``-weight * sum_k max(0, r_j + r_k - dist_jk)^2 / depth^2`` over the parts ``k`` that
    may not touch ``j`` (``allowed[j, k]`` False; adjacent parts are allowed). Counted once,
    not per camera (the first camera's column; the others are 0)."""

    allowed: Tensor
    weight: float = 1.0
    depth: float = 0.02

    def score(self, samples, obs):
        seg = samples.segments  # (B, N, K, 2, 3)
        rest = samples.rest_segments[:, samples.frames.to(seg.device)]  # (B, N, P, 2, 3)
        dist = segment_distance(
            seg[:, :, :, None, 0],
            seg[:, :, :, None, 1],
            rest[:, :, None, :, 0],
            rest[:, :, None, :, 1],
        )  # (B, N, K, P)
        radii = samples.radii.to(seg).mean(-1)  # (P,)
        parts = samples.parts.to(seg.device)
        reach = radii[parts][None, :, None, None] + radii[None, None, None, :]
        forbidden = ~self.allowed.to(seg.device)[parts]  # (N, P)
        depth = (reach - dist).clamp_min(0) * forbidden[None, :, None, :]
        total = -self.weight * (depth / self.depth).square().sum(-1)  # (B, N, K)
        b, n, k = total.shape
        out = total.new_zeros(b, n, samples.ends.shape[2], k)
        out[:, :, 0] = total
        return out


def segment_distance(p1: Tensor, q1: Tensor, p2: Tensor, q2: Tensor) -> Tensor:
    """Shortest distance between 3-D segments ``[p1, q1]`` and ``[p2, q2]`` (broadcast).

    Shapes: ``(..., 3)`` each -> ``(...)``. The closest-point parameters are found in closed
    form and clamped to the segments (Ericson, Real-Time Collision Detection, 5.1.9).
    """
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = (d1 * d1).sum(-1).clamp_min(1e-12)
    e = (d2 * d2).sum(-1).clamp_min(1e-12)
    f = (d2 * r).sum(-1)
    c = (d1 * r).sum(-1)
    b = (d1 * d2).sum(-1)
    denom = (a * e - b * b).clamp_min(1e-12)
    s = ((b * f - c * e) / denom).clamp(0, 1)
    t = (b * s + f) / e
    s = torch.where(t < 0, (-c / a).clamp(0, 1), torch.where(t > 1, ((b - c) / a).clamp(0, 1), s))
    t = t.clamp(0, 1)
    closest = (p1 + s.unsqueeze(-1) * d1) - (p2 + t.unsqueeze(-1) * d2)
    return closest.norm(dim=-1)


# -- the factor ------------------------------------------------------------------------------
@dataclass
class BodyObservation(UnaryFactor):
    """``phi_j``: every hypothesis of every part of a body graph scored against images.

    The graph's nodes are numbered ``t * P + p`` (part p of frame t, as
    :class:`pgm.SpatioTemporalTemplate`); ``obs`` holds the T frames (batch B, or 1 shared).
    Each call renders the rest of the body once from the current estimates (two depth
    layers), projects every hypothesis' sample points into every camera, and sums the
    cues over cameras.

    Args:
        shapes: the parts' capsules (:class:`PartShapes`, P parts).
        rig: the cameras (C of them; orthographic or pinhole).
        obs: :class:`Observation` of T frames.
        cues: the scoring terms (default: :class:`Silhouette` only).
        occlusion: score against the rest of the body (``False``: each part rendered
            alone, the ablation).
        layout: the sample points (:class:`SampleLayout`).
        schedule: multiplier of the log-potential per iteration (annealing; default 1).
    """

    shapes: PartShapes
    rig: CameraRig
    obs: Observation
    cues: Sequence[Cue] = field(default_factory=lambda: [Silhouette()])
    occlusion: bool = True
    layout: SampleLayout = field(default_factory=SampleLayout)
    schedule: Schedule = field(default_factory=Constant)
    multiplier: float = 1.0

    def __post_init__(self):
        if self.rig.num_cameras != self.obs.silhouette.shape[2]:
            raise ValueError(
                f"the rig has {self.rig.num_cameras} cameras but the observation "
                f"{self.obs.silhouette.shape[2]}"
            )
        if not self.cues:
            raise ValueError("an observation needs at least one cue")
        for cue in self.cues:
            if not isinstance(cue, Cue):
                raise TypeError(f"cues must be Cue instances; got {type(cue).__name__}")
        self._canon = self.layout.canonical()

    def annealed(self, step: AnnealingStep) -> BodyObservation:
        multiplier = self.schedule(step.iteration)
        if multiplier == self.multiplier:
            return self
        return dataclasses.replace(self, multiplier=multiplier)

    @property
    def num_parts(self) -> int:
        return self.shapes.num_parts

    def log_potential(self, x: Tensor, nodes: Tensor, estimates: Tensor) -> Tensor:
        samples = self.samples(x, nodes, estimates)
        total = sum(cue.score(samples, self.obs) for cue in self.cues)
        total = self.multiplier * total.sum(2)
        # every cue is finite on a part the cameras can image; a hypothesis they cannot (a
        # NaN pose, an end at a camera's centre) is impossible, not an error
        return torch.where(torch.isfinite(total), total, torch.full_like(total, -math.inf))

    def samples(self, x: Tensor, nodes: Tensor, estimates: Tensor) -> Samples:
        """The shared rendering products of one call (see :class:`Samples`).

        Shapes: x ``(B, N, K, 7)``, nodes ``(N,)``, estimates ``(B, V, D)`` whose first
        ``T * P`` nodes are the body's (nodes of other kinds, e.g. a correspondence chain
        coupled to the body, may follow them).
        """
        b, n, k, _ = x.shape
        p = self.num_parts
        t_obs = self.obs.silhouette.shape[1]
        if estimates.shape[1] < t_obs * p or estimates.shape[-1] < 7:
            raise ValueError(
                f"the graph has {estimates.shape[1]} nodes; the observation has {t_obs} frames "
                f"of {p} parts ({t_obs * p} SE(3) nodes first)"
            )
        nodes = nodes.to(x.device)
        frames, parts = nodes // p, nodes % p
        rest = estimates[:, : t_obs * p, :7].reshape(b, t_obs, p, 7)
        rest_segments = self.shapes.segments(
            rest, torch.arange(p, device=rest.device)
        )  # (B, T, P, 2, 3)
        h, w = self.obs.size
        if self.occlusion:
            layers = body_layers(project_parts(self.rig, rest_segments, self.shapes.radii), h, w)
        else:
            layers = RestLayers.empty((b, t_obs, self.rig.num_cameras, h, w), x)
        segments = self.shapes.segments(x[..., :7], parts, trailing=1)  # (B, N, K, 2, 3)
        radii = self.shapes.radii.to(x)[parts][None, :, None]  # (1, N, 1, 2)
        # the hypotheses take the parts' axis of project_parts: (B, N, C, K, ...)
        projected = project_parts(self.rig, segments, radii.expand(b, n, k, 2))
        interior = self._part_samples(self._canon[0], projected, layers, frames, parts, True)
        outline = self._part_samples(self._canon[1], projected, layers, frames, parts, False)
        return Samples(
            interior,
            outline,
            projected.ends,
            segments,
            rest_segments,
            parts,
            frames,
            self.shapes.radii,
        )

    def _part_samples(self, canon, projected, layers, frames, parts, area) -> PartSamples:
        points, weight, depth = _place(canon, projected, area)  # (B, N, K, C, S, ...)
        h, w = self.obs.size
        b, t = layers.label.shape[:2]
        c = self.rig.num_cameras
        # a point the camera cannot image (NaN) is outside, not a pixel index
        u = torch.nan_to_num(points[..., 0].round(), nan=-1.0)
        v = torch.nan_to_num(points[..., 1].round(), nan=-1.0)
        inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        pix = v.clamp(0, h - 1).long() * w + u.clamp(0, w - 1).long()
        dev = points.device
        bi = torch.arange(b, device=dev).reshape(b, 1, 1, 1, 1)
        fi = frames.reshape(1, -1, 1, 1, 1)
        ci = torch.arange(c, device=dev).reshape(1, 1, c, 1, 1)
        base = ((bi * t + fi) * c + ci) * (h * w)
        flat = base + pix
        label = layers.label.reshape(-1)[flat]
        own_label = label == _node_axis_view(parts, label.dim())
        rest_depth = torch.where(
            own_label, layers.second.reshape(-1)[flat], layers.near.reshape(-1)[flat]
        )
        return PartSamples(
            points,
            weight,
            depth,
            inside,
            rest_depth,
            label,
            layers.second_label.reshape(-1),
            flat,
            b,
            base.expand_as(flat),
            parts,
        )
