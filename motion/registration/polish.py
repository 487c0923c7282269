"""Stage 2b: the registered posture polished on the skeleton, against the images.

Particle BP (stages 2-3) estimates each body part as a free rigid body; the posture fit
(:mod:`motion.body.fit`) then hangs the reference's skeleton on those estimates, pulling
every joint toward the reference's rotation at C(t'). What comes out is a posture of the
right kind, off by the particles' sampling error. This stage moves the skeleton itself --
each driven joint's rotation, the root's rotation and position, all frames together -- by
gradient descent (Adam) on

* **the silhouettes, both ways, at sampled points** (O(points), not O(pixels): DESIGN.md
  section 7): points on every capsule's projected outline pay their squared distance
  (pixels) outside the observed silhouette (read by bilinear interpolation from its distance
  map to its pixels' centres), and sampled pixels of the observed silhouette pay their
  squared distance outside the body (the nearest capsule's signed distance,
  :func:`motion.render.capsule_sdf`); each camera's term is the mean over its points, in
  nats per squared ``silhouette_px``. With ``rasterised`` the outline pays only beyond a
  pixel from the outer pixels' centres (a pixel is drawn when its centre is inside the
  body, so the true outline may lie up to there) and sampled pixels of the ring just
  outside the silhouette pay their squared distance inside the body: the true posture of
  a rendered student then costs nothing;
* **the 2-D joints**, where given: a Cauchy term ``log(1 + r^2 / s^2)`` of each joint's
  reprojection error ``r`` in each camera, weighted by the detector's confidence;
* **the articulation prior** ``E_A``: each driven joint's rotation angle away from the
  reference's at C(t'), Gaussian with a broad spread (a student differs from the reference
  in every joint by ten or twenty degrees, not in a few by much);
* **smoothness**: the change of every joint's correction, and of the root's, from one video
  frame to the next.

C and G stay as given; the frames are solved in chunks, each chunk's first frame tied to the
previous chunk's last.

Before the frames, when turned on (``proportion_steps``) and the video has 2-D joints, the
**student's proportions** (the
proposal's G per bone: :class:`~motion.registration.types.Proportions`) are fitted: one
length factor per body part (left and right sharing one), shared by every frame, on up to
``proportion_frames`` frames spread over the video together with their postures, under a
log-normal prior about 1 (the same terms, without smoothness between frames that are not
neighbours). The frames are then polished on the student's proportions.

Before the polish, when turned on (``joints_first_steps``) and the video has 2-D joints, a
**descent on the 2-D joints alone** (the same terms without the silhouettes, a wider prior
and looser smoothness) moves the posture toward the joints' from further away than the
polish reaches: the silhouettes hold a limb wherever it lies inside the outline, so started
at the reference's posture the polish keeps most of it.

Conventions: metres, radians, pixels; column vectors, right-handed world (DESIGN.md section
3). Shapes: ``T'`` video frames, ``J`` joints, ``C`` cameras, ``P`` parts, ``N`` points.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from motion.body.spec import BodySpec
from motion.cameras import CameraRig
from motion.features import distance_to_edges
from motion.geometry import rotation_vector_to_matrix
from motion.kinematics import FKResult
from motion.registration.types import (
    Proportions,
    Reference,
    RegistrationError,
    VideoFeatures,
    paired_part,
    scaled_spec,
)
from motion.render import capsule_sdf, project_parts
from motion.settings import SettingError, Settings, setting

__all__ = ["PolishResult", "PosturePolishSettings", "part_groups", "polish_posture"]


class PosturePolishSettingsError(SettingError, RegistrationError):
    """A posture polish setting outside its type or range."""


@dataclass(frozen=True)
class PosturePolishSettings(Settings):
    """Settings of :func:`polish_posture` (every field checked at construction)."""

    setting_error = PosturePolishSettingsError

    steps: int = setting(50, "Adam steps of the posture polish (0: no polish)", ge=0, le=100000)
    lr: float = setting(
        0.02, "Adam's step size: radians (and metres for the root) per step, about", gt=0, le=1
    )
    silhouette: float = setting(
        1.0,
        "weight of each camera's silhouette term (nats per squared silhouette_px of mean "
        "distance outside; 0 leaves the silhouettes out)",
        ge=0,
    )
    silhouette_px: float = setting(
        0.5, "pixels, the spread of the outline's distance from the silhouette's", gt=0
    )
    silhouette_samples: int = setting(
        128, "pixels of each observed silhouette sampled for the body's cover of it", ge=1
    )
    outline_points: int = setting(
        8, "points on each side of a capsule's projected outline (and 2 on each cap)", ge=2
    )
    keypoints: float = setting(
        1.0,
        "weight of the 2-D joints' Cauchy term, nats per joint and camera at confidence 1 "
        "(0 leaves them out)",
        ge=0,
    )
    keypoint_px: float = setting(4.0, "pixels, the 2-D joints' Cauchy scale", gt=0)
    articulation_deg: float = setting(
        20.0,
        "degrees, s of the articulation prior 2 (1 - cos a) / s^2 on each joint's rotation a "
        "about the reference's at C (near 0 a Gaussian of spread s / sqrt(2)); 40 measured "
        "better on rendered students and worse on the real Pose2Sim trial "
        "(docs/decisions/002-posture-polish.md)",
        gt=0,
        le=180,
    )
    smooth_deg: float = setting(
        3.0, "degrees, the spread of a joint's correction's change from frame to frame", gt=0
    )
    smooth_m: float = setting(
        0.01, "metres, the spread of the root's correction's change from frame to frame", gt=0
    )
    frames_per_chunk: int = setting(64, "video frames solved together", ge=2)
    proportion_steps: int = setting(
        0,
        "Adam steps of the proportions' fit: each body part's length on top of G, shared by "
        "every frame, fitted to the 2-D joints on frames spread over the video before the "
        "frames are polished (0, or no 2-D joints: the reference's proportions). Off by "
        "default: a detector's joints sit where its own convention puts them, and lengths "
        "fitted to them measure that convention (docs/decisions/003-proportions.md); turn it "
        "on for joints that are the skeleton's (markers, a matched detector); 100 is enough",
        ge=0,
        le=100000,
    )
    proportion_frames: int = setting(
        32, "video frames (spread evenly over those where the person is seen) it fits on", ge=1
    )
    proportion_pct: float = setting(
        8.0,
        "percent, the spread of the prior on each part's length factor about 1 (log-normal: "
        "what the images cannot tell stays the reference's)",
        gt=0,
        le=100,
    )
    symmetric: bool = setting(
        True, "left and right parts (names ending _l and _r) share one length factor"
    )
    rasterised: bool = setting(
        False,
        "read the silhouettes as a rasteriser draws them: the body's outline free within a "
        "pixel of the silhouette's outer pixel centres, and the ring of pixels just outside "
        "it paying where the body covers them, so the true posture of a rendered student "
        "costs nothing; off: the outline read to the pixel centres, which shrinks the body "
        "about half a pixel but measured better on the real Pose2Sim trial, whose masks are "
        "no rasteriser's (docs/decisions/002-posture-polish.md)",
    )
    joints_first_steps: int = setting(
        0,
        "Adam steps of a descent on the 2-D joints alone (the silhouettes left out), before "
        "the polish and after the proportions' fit, from the posture given: a wider search "
        "than the polish, whose silhouettes hold a posture near where it starts (0, or no "
        "2-D joints: none). For joints that are the skeleton's, seen by two or more cameras "
        "(docs/experiments.md, 'Where the articulation's error on another performer comes "
        "from'); 300 is enough",
        ge=0,
        le=100000,
    )
    joints_first_lr: float = setting(
        0.05, "the joints-first descent's Adam step size (radians, metres, per step)", gt=0, le=1
    )
    joints_first_articulation_deg: float = setting(
        30.0,
        "degrees, the joints-first descent's articulation prior (as articulation_deg)",
        gt=0,
        le=180,
    )
    joints_first_smooth_deg: float = setting(
        30.0, "degrees, the joints-first descent's frame-to-frame smoothness (as smooth_deg)", gt=0
    )
    seed: int = setting(0, "seed of the silhouette pixels' sampling", ge=0)

    def joints_first(self) -> PosturePolishSettings:
        """The settings of the joints-first descent: these, on the 2-D joints alone."""
        return dataclasses.replace(
            self,
            silhouette=0.0,
            steps=self.joints_first_steps,
            lr=self.joints_first_lr,
            articulation_deg=self.joints_first_articulation_deg,
            smooth_deg=self.joints_first_smooth_deg,
        )


@dataclass
class PolishResult:
    """The polished posture: local ``rotations`` ``(T', J, 3, 3)`` float64 (the root's is
    T's), root ``translation`` ``(T', 3)`` metres, the loss before and after
    (``loss_start``, ``loss_end``: nats, summed over the chunks), and the student's
    ``proportions`` (not measured when ``proportion_steps`` is 0)."""

    rotations: Tensor
    translation: Tensor
    loss_start: float
    loss_end: float
    proportions: Proportions


@dataclass
class _Targets:
    """What the images say, for one chunk: the silhouette's distance map ``(n, C, H, W)``
    (pixels to the nearest silhouette pixel's centre, 0 inside; ``rasterised``: less one
    pixel, 0 within it), sampled silhouette pixels ``(n, C, N, 2)`` (u, v) with a mask
    ``(n, C, N)`` of the real ones, sampled pixels of the ring just outside it (``ring``,
    ``ring_mask``: the pixels next to a silhouette pixel, 8-connected; ``None`` unless
    ``rasterised``), each view's weight ``(n, C)`` (0: an empty
    silhouette), and the 2-D joints ``(n, C, K, 3)`` or ``None``."""

    outside: Tensor
    samples: Tensor
    sample_mask: Tensor
    ring: Tensor | None
    ring_mask: Tensor | None
    view: Tensor
    keypoints: Tensor | None


def _silhouette_targets(
    silhouette: Tensor, samples: int, generator: torch.Generator, rasterised: bool
) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor | None, Tensor]:
    """Distance maps, sampled silhouette pixels and their mask, sampled ring pixels and
    their mask (``None`` unless ``rasterised``), and each view's weight of silhouettes
    ``(n, C, H, W)`` in [0, 1] (see :class:`_Targets` and
    :attr:`PosturePolishSettings.rasterised`)."""
    n, c, h, w = silhouette.shape
    inside = silhouette > 0.5
    view = inside.flatten(2).any(-1)  # (n, C)
    # OpenCV's exact transform on every device (kornia's, a GPU's default, errs ~13 %)
    outside = distance_to_edges(inside.reshape(n * c, 1, h, w), backend="opencv")
    outside = outside.reshape(n, c, h, w)
    if rasterised:
        # a pixel is in the silhouette when its centre is inside the body, so the true
        # outline lies anywhere between the outer pixels' centres and the next pixels' (up
        # to a pixel beyond the former): it pays from there on. Read to the centres
        # themselves, the true outline pays ~0.5 px everywhere and the body shrinks into them
        # (started at the truth, the silhouettes alone moved it to IoU 0.96). Within that
        # band the ring's pixels say where it ends: their centres must lie outside the body
        outside = (outside - 1.0).clamp_min(0)
    outside = torch.where(view[..., None, None], outside, torch.zeros_like(outside))
    uv, mask = _sample_pixels(inside, samples, generator)
    ring_uv = ring_mask = None
    if rasterised:
        near = F.max_pool2d(inside.reshape(n * c, 1, h, w).float(), 3, 1, 1)
        ring = (near.reshape(n, c, h, w) > 0) & ~inside
        ring_uv, ring_mask = _sample_pixels(ring, samples, generator)
    return outside, uv, mask, ring_uv, ring_mask, view.float()


def _sample_pixels(
    pixels: Tensor, samples: int, generator: torch.Generator
) -> tuple[Tensor, Tensor]:
    """``samples`` pixels ``(n, C, N, 2)`` (u, v) drawn uniformly (with replacement) from each
    view's ``pixels`` ``(n, C, H, W)`` bool, and a mask ``(n, C, N)`` of the views that have
    any (the others' draws are anywhere and masked out)."""
    n, c, h, w = pixels.shape
    flat = pixels.reshape(n * c, h * w).float()
    weights = torch.where(flat.sum(-1, keepdim=True) > 0, flat, torch.ones_like(flat))
    index = torch.multinomial(weights, samples, replacement=True, generator=generator)
    uv = torch.stack([index % w, index // w], -1).float().reshape(n, c, samples, 2)
    mask = pixels.flatten(2).any(-1)[..., None].expand(n, c, samples)
    return uv, mask


def _sample_map(maps: Tensor, uv: Tensor) -> Tensor:
    """Bilinear read of ``maps`` ``(n, C, H, W)`` at pixels ``uv`` ``(n, C, N, 2)`` (pixel
    centres at integers; outside the image: the border's value) -> ``(n, C, N)``."""
    n, c, h, w = maps.shape
    grid = torch.stack([uv[..., 0] / max(w - 1, 1), uv[..., 1] / max(h - 1, 1)], -1) * 2 - 1
    out = F.grid_sample(
        maps.reshape(n * c, 1, h, w),
        grid.reshape(n * c, 1, -1, 2).to(maps),
        mode="bilinear",
        padding_mode="border",
        align_corners=True,
    )
    return out.reshape(n, c, -1)


def capsule_outline(ends: Tensor, radii: Tensor, per_side: int) -> Tensor:
    """Points on the outline of 2-D capsules: ``per_side`` points on each straight side
    (the discs' common tangents, approximated by the normals at the axis) and 2 on each cap
    (along the axis beyond each end).

    Args:
        ends: ``(..., 2, 2)`` pixels, the axis's two end points.
        radii: ``(..., 2)`` pixels at the two ends.
        per_side: points per side (>= 2).

    Returns:
        ``(..., 2 per_side + 4, 2)`` pixels.
    """
    a, b = ends[..., 0, :], ends[..., 1, :]
    axis = b - a
    unit = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    normal = torch.stack([-unit[..., 1], unit[..., 0]], -1)
    t = torch.linspace(0, 1, per_side, dtype=ends.dtype, device=ends.device)[:, None]
    centre = a[..., None, :] + t * axis[..., None, :]  # (..., S, 2)
    r = (radii[..., 0:1] + t[:, 0] * (radii[..., 1:2] - radii[..., 0:1]))[..., None]
    sides = [centre + r * normal[..., None, :], centre - r * normal[..., None, :]]
    caps = [
        a - radii[..., 0:1] * unit,
        b + radii[..., 1:2] * unit,
        a + radii[..., 0:1] * (normal - unit) / math.sqrt(2),
        b + radii[..., 1:2] * (unit - normal) / math.sqrt(2),
    ]
    return torch.cat([*sides, torch.stack(caps, -2)], -2)


class _Posture:
    """The skeleton's posture as a function of the corrections being optimised."""

    def __init__(self, reference: Reference, scale: float, start: Tensor, driven: list[int]):
        self.reference = reference
        self.scale = scale
        self.start = start.double()  # (n, J, 3, 3)
        self.mask = torch.zeros(start.shape[1], 1, dtype=torch.float64, device=start.device)
        self.mask[driven] = 1.0

    def rotations(self, joints: Tensor, root: Tensor) -> Tensor:
        """Local rotations ``(n, J, 3, 3)``: each driven joint's start turned by its
        correction ``joints`` ``(n, J, 3)`` (rotation vectors, in the joint's frame), the
        root's start turned by ``root`` ``(n, 3)`` in the world."""
        local = self.start @ rotation_vector_to_matrix(joints * self.mask)
        top = rotation_vector_to_matrix(root) @ self.start[:, 0]
        return torch.cat([top[:, None], local[:, 1:]], 1)

    def frames(self, rotations: Tensor, joint_scales: Tensor | None = None) -> FKResult:
        """The posture's forward kinematics in the root's frame (scaled by G, and each
        offset by ``joint_scales`` ``(J,)`` when given)."""
        return self.reference.posture_frames(rotations, self.scale, joint_scales)

    def world_joints(
        self, rotations: Tensor, translation: Tensor, fk: FKResult | None = None
    ) -> Tensor:
        """``(n, J, 3)`` metres: every joint in the world (``fk``: :meth:`frames` of
        ``rotations``, when already computed)."""
        fk = self.frames(rotations) if fk is None else fk
        rotated = (rotations[:, None, 0] @ fk.positions[..., None]).squeeze(-1)
        return rotated + translation[:, None]

    def segments(
        self, spec: BodySpec, rotations: Tensor, translation: Tensor, fk: FKResult | None = None
    ) -> Tensor:
        """``(n, P, 2, 3)`` metres: every capsule's axis in the world (``spec``: the body at
        this size and these proportions; ``fk`` as in :meth:`world_joints`)."""
        ref = self.reference
        fk = self.frames(rotations) if fk is None else fk
        poses = spec.poses(ref.model, ref.skeleton, fk)
        ends = spec.landmarks(poses)  # (n, P, 2, 3) in the root's frame, scaled
        root = rotations[:, 0][:, None, None]
        return (root @ ends[..., None]).squeeze(-1) + translation[:, None, None]


@dataclass
class _Problem:
    """What one descent of :func:`_losses` works on: the posture, the body (``spec`` at G,
    the ``proportions``' parts and bones), the images' ``targets``, the skeleton joint of
    each keypoint column, the reference's rotations of the driven joints at C ``(n, D, 3,
    3)``, and the root's start ``(n, 3)`` metres."""

    posture: _Posture
    spec: BodySpec
    proportions: Proportions
    rig: CameraRig
    targets: _Targets
    keypoint_joints: Tensor | None
    reference_rotations: Tensor
    driven: list[int]
    translation: Tensor


def _losses(
    problem: _Problem,
    joints: Tensor,
    root: Tensor,
    shift: Tensor,
    part_scales: Tensor | None,
    anchor: tuple[Tensor, Tensor, Tensor] | None,
    smooth: bool,
    s: PosturePolishSettings,
) -> dict[str, Tensor]:
    """Each term of the polish's loss (nats) at corrections ``joints`` ``(n, J, 3)``,
    ``root`` ``(n, 3)``, ``shift`` ``(n, 3)`` metres and the parts' length factors
    ``part_scales`` ``(P,)`` (``None``: the problem's proportions); ``smooth``: the frames
    are consecutive (else no smoothness term)."""
    posture, targets = problem.posture, problem.targets
    if part_scales is None:
        part_scales = problem.proportions.part_scales
    rotations = posture.rotations(joints, root)
    # once per step, for the silhouettes and the joints
    fk = posture.frames(rotations, problem.proportions.joint_scales(part_scales))
    # the silhouettes move the posture, never the proportions: where a clothed body's outline
    # lies says nothing of where its joints are (a coat lengthens no trunk)
    seen_scales, seen_fk = part_scales, fk
    if part_scales.requires_grad:
        seen_scales = part_scales.detach()
        seen_fk = posture.frames(rotations, problem.proportions.joint_scales(seen_scales))
    spec = scaled_spec(problem.spec, 1.0, seen_scales)
    moved = problem.translation + shift
    terms: dict[str, Tensor] = {}
    if s.silhouette > 0:
        # float32 from here: the signed distances of every sampled pixel to every capsule
        # are the polish's bulk (float64 took twice as long for the same result)
        segments = posture.segments(spec, rotations, moved, seen_fk).float()
        parts = project_parts(problem.rig, segments, spec.shapes.radii.to(segments))
        # the body's outline, outside the silhouette
        outline = capsule_outline(parts.ends, parts.radii, s.outline_points)  # (n,C,P,S,2)
        n, c = outline.shape[:2]
        out = _sample_map(targets.outside, outline.reshape(n, c, -1, 2)).square().mean(-1)
        # the silhouette's pixels outside the body, and the ring's pixels inside it
        sdf, _ = capsule_sdf(targets.samples[:, :, None], parts.ends, parts.radii)
        uncovered = sdf.amin(-2).clamp_min(0).square()  # (n, C, N)
        cover = (uncovered * targets.sample_mask).sum(-1) / targets.sample_mask.sum(-1).clamp_min(1)
        if targets.ring is not None:
            sdf, _ = capsule_sdf(targets.ring[:, :, None], parts.ends, parts.radii)
            spilt = (-sdf.amin(-2)).clamp_min(0).square()  # (n, C, N)
            ring = targets.ring_mask
            cover = cover + (spilt * ring).sum(-1) / ring.sum(-1).clamp_min(1)
        per_view = (out + cover) / (2 * s.silhouette_px**2)
        terms["silhouette"] = s.silhouette * (per_view * targets.view).sum().double()
    kp_joints = problem.keypoint_joints
    if s.keypoints > 0 and targets.keypoints is not None and kp_joints is not None:
        world = posture.world_joints(rotations, moved, fk)[:, kp_joints]  # (n, K, 3)
        uv, depth = problem.rig.project(world)  # (n, C, K, 2), (n, C, K)
        kp = targets.keypoints.to(uv)
        confidence = torch.where(depth > 0, kp[..., 2], torch.zeros_like(kp[..., 2]))
        r2 = (uv - kp[..., :2]).square().sum(-1)
        terms["keypoints"] = s.keypoints * (confidence * torch.log1p(r2 / s.keypoint_px**2)).sum()
    articulation = problem.reference_rotations.transpose(-1, -2) @ rotations[:, problem.driven]
    trace = articulation.diagonal(dim1=-2, dim2=-1).sum(-1)
    # acos's gradient is infinite at 0: the prior reads (3 - trace) / s^2 = 2 (1 - cos a) / s^2
    # ~ a^2 / s^2 instead, a Gaussian of spread s / sqrt(2) in the angle a
    terms["articulation"] = ((3 - trace) / math.radians(s.articulation_deg) ** 2).sum()
    if not smooth:
        return terms
    if anchor is not None:  # the previous chunk's last frame, fixed
        joints = torch.cat([anchor[0], joints])
        root = torch.cat([anchor[1], root])
        shift = torch.cat([anchor[2], shift])
    turn = (joints[1:] - joints[:-1]) * posture.mask
    smoothness = turn.square().sum() + (root[1:] - root[:-1]).square().sum()
    terms["smoothness"] = smoothness / (2 * math.radians(s.smooth_deg) ** 2) + (
        shift[1:] - shift[:-1]
    ).square().sum() / (2 * s.smooth_m**2)
    return terms


def _descend(
    loss: Callable[[], Tensor], variables: list[Tensor], steps: int, lr: float
) -> tuple[float, float, list[Tensor] | None]:
    """Adam on ``variables`` for ``steps`` steps of ``loss()``: ``(first loss, best loss,
    the variables at the best)`` (``None`` when no loss was finite). Adam jitters about an
    optimum by about ``lr``, so the best iterate is kept, not the last."""
    optimiser = torch.optim.Adam(variables, lr=lr)
    first, best = math.nan, (math.inf, None)
    for step in range(steps + 1):  # the last pass only scores the last step
        optimiser.zero_grad()
        value = loss()
        if not torch.isfinite(value):
            break
        if step == 0:
            first = float(value.detach())
        if float(value.detach()) < best[0]:
            best = (float(value.detach()), [x.detach().clone() for x in variables])
        if step < steps:
            value.backward()
            optimiser.step()
    return first, best[0], best[1]


def part_groups(names: list[str], symmetric: bool) -> tuple[list[str], Tensor]:
    """The groups of parts that share a length factor: ``(group names, (P,) long group of
    each part)``. ``symmetric``: a part named ``X_l`` and one named ``X_r`` form group ``X``;
    otherwise (and for every other part) a part is its own group."""
    groups: list[str] = []
    index = []
    for name in names:
        key = (paired_part(name) if symmetric else None) or name
        if key not in groups:
            groups.append(key)
        index.append(groups.index(key))
    return groups, torch.tensor(index, device="cpu")


def _spread_frames(seen: Tensor, most: int) -> Tensor:
    """Up to ``most`` indices of the ``True`` entries of ``seen`` ``(T',)``, spread evenly
    (first and last included)."""
    frames = seen.nonzero().flatten()
    if len(frames) <= most:
        return frames
    picks = torch.linspace(0, len(frames) - 1, most, device=seen.device).round().long().unique()
    return frames[picks]


def polish_posture(
    reference: Reference,
    video: VideoFeatures,
    c: Tensor,
    rotations: Tensor,
    translation: Tensor,
    scale: float,
    settings: PosturePolishSettings | None = None,
    progress: Callable[[Iterable, str, int], Iterator] | None = None,
) -> PolishResult:
    """Polish a registered posture against the video (see the module's docstring).

    Args:
        reference: the reference motion (skeleton, body model, C's postures).
        video: the features: silhouettes and, where given, 2-D joints (``keypoint_joints``
            names the skeleton joint of each column).
        c: ``(T',)`` long, C.
        rotations: ``(T', J, 3, 3)`` local rotations to start from (the root's is T's).
        translation: ``(T', 3)`` metres, the root's position.
        scale: the body scale G.
        settings: :class:`PosturePolishSettings`.
        progress: ``progress(items, description, total)`` wrapping the loop over chunks of
            frames (e.g. a tqdm bar); ``None``: silent.

    Returns:
        :class:`PolishResult`.
    """
    s = settings or PosturePolishSettings()
    t, j = rotations.shape[:2]
    if c.shape != (t,) or translation.shape != (t, 3) or video.num_frames != t:
        raise RegistrationError(
            f"expected C ({t},), translation ({t}, 3) and {t} video frames; got "
            f"{tuple(c.shape)}, {tuple(translation.shape)}, {video.num_frames}"
        )
    proportions = Proportions.of(reference)
    start = PolishResult(rotations.double(), translation.double(), 0.0, 0.0, proportions)
    if s.steps == 0 and s.proportion_steps == 0 and s.joints_first_steps == 0:
        return start
    driven = sorted(set(reference.spec.frame_joints.tolist()) - {0})
    columns, keypoint_joints = _keypoint_columns(reference, video)
    # draws where the silhouettes are (torch.multinomial takes a generator of their device)
    generator = torch.Generator(device=video.observation.silhouette.device).manual_seed(s.seed)

    def problem(frames: Tensor | slice, rot: Tensor, trans: Tensor, body: Proportions):
        obs = video.observation
        targets = _silhouette_targets(
            obs.silhouette[0, frames].float(), s.silhouette_samples, generator, s.rasterised
        )
        keypoints = None
        if columns is not None:
            keypoints = obs.keypoints[0, frames][:, :, columns].double()
        return _Problem(
            _Posture(reference, scale, rot, driven),
            scaled_spec(reference.spec, scale),
            body,
            video.cameras,
            _Targets(*targets, keypoints),
            keypoint_joints,
            reference.rotations[c[frames]][:, driven].double(),
            driven,
            trans,
        )

    # the proportions rest on the 2-D joints: a silhouette does not show where along a limb
    # its joint lies (a longer thigh under a shorter shin draws the same straight leg), and
    # measured without them the part lengths drift within their prior (decision 003)
    if s.proportion_steps and columns is not None:
        frames = _spread_frames(video.seen(), s.proportion_frames)
        fitted = _fit_proportions(
            problem(frames, start.rotations[frames], start.translation[frames], proportions), s
        )
        proportions = Proportions.of(reference, fitted)
    out_rot, out_trans = start.rotations.clone(), start.translation.clone()
    wrap = progress or (lambda items, description, total: items)

    def descend_chunks(settings: PosturePolishSettings, label: str) -> tuple[float, float]:
        """``settings``' descent over the chunks of frames, in place on ``out_rot`` and
        ``out_trans``: the loss before and after, summed over the chunks."""
        before = after = 0.0
        anchor = None
        firsts = range(0, t, settings.frames_per_chunk) if settings.steps else range(0)
        for first in wrap(firsts, label, len(firsts)):
            chunk = slice(first, min(t, first + settings.frames_per_chunk))
            task = problem(chunk, out_rot[chunk], out_trans[chunk], proportions)
            n = chunk.stop - chunk.start
            dev = out_rot.device
            joints = torch.zeros(n, j, 3, dtype=torch.float64, device=dev, requires_grad=True)
            root = torch.zeros(n, 3, dtype=torch.float64, device=dev, requires_grad=True)
            shift = torch.zeros(n, 3, dtype=torch.float64, device=dev, requires_grad=True)

            def loss(task=task, joints=joints, root=root, shift=shift, anchor=anchor):
                terms = _losses(task, joints, root, shift, None, anchor, True, settings)
                return sum(terms.values())

            first_loss, best_loss, best = _descend(
                loss, [joints, root, shift], settings.steps, settings.lr
            )
            if best is None:  # nothing finite to descend: the chunk keeps its start
                anchor = None
                continue
            best_joints, best_root, best_shift = best
            with torch.no_grad():
                out_rot[chunk] = task.posture.rotations(best_joints, best_root)
                out_trans[chunk] = task.translation + best_shift
                anchor = (best_joints[-1:], best_root[-1:], best_shift[-1:])
            before += first_loss
            after += best_loss
        return before, after

    # the silhouettes hold a posture near its start (a limb inside the outline stays where it
    # fits); the 2-D joints alone pull it toward theirs from further away
    if s.joints_first_steps and columns is not None:
        descend_chunks(s.joints_first(), "polish on the 2-D joints (T, A)")
    before, after = descend_chunks(s, "polish (T, A)")
    return PolishResult(out_rot, out_trans, before, after, proportions)


def _keypoint_columns(
    reference: Reference, video: VideoFeatures
) -> tuple[Tensor | None, Tensor | None]:
    """The keypoint columns that name a joint of the reference's skeleton and those joints
    (others, if any, are another body model's landmarks): ``(columns, joints)`` long, or
    ``(None, None)`` when there are none."""
    if video.observation.keypoints is None or video.keypoint_joints is None:
        return None, None
    names = reference.skeleton.names
    pairs = [(i, names.index(n)) for i, n in enumerate(video.keypoint_joints) if n in names]
    if not pairs:
        return None, None
    dev = video.observation.keypoints.device
    return (
        torch.tensor([i for i, _ in pairs], device=dev),
        torch.tensor([j for _, j in pairs], device=dev),
    )


def _fit_proportions(task: _Problem, s: PosturePolishSettings) -> Tensor:
    """``(P,)`` the parts' length factors fitted on ``task``'s frames (not consecutive: no
    smoothness) together with their postures, under a log-normal prior of spread
    ``proportion_pct`` about 1; groups (:func:`part_groups`) share a factor."""
    names = task.proportions.part_names
    _, group = part_groups(names, s.symmetric)
    n, j = task.posture.start.shape[:2]
    dev = task.posture.start.device
    group = group.to(dev)
    joints = torch.zeros(n, j, 3, dtype=torch.float64, device=dev, requires_grad=True)
    root = torch.zeros(n, 3, dtype=torch.float64, device=dev, requires_grad=True)
    shift = torch.zeros(n, 3, dtype=torch.float64, device=dev, requires_grad=True)
    log_scale = torch.zeros(
        int(group.max()) + 1, dtype=torch.float64, device=dev, requires_grad=True
    )
    spread = math.log1p(s.proportion_pct / 100)

    def loss() -> Tensor:
        terms = _losses(task, joints, root, shift, log_scale.exp()[group], None, False, s)
        return sum(terms.values()) + log_scale.square().sum() / (2 * spread**2)

    _, _, best = _descend(loss, [joints, root, shift, log_scale], s.proportion_steps, s.lr)
    if best is None:  # nothing finite: the reference's proportions
        return torch.ones(len(names), dtype=torch.float64, device=dev)
    return best[3].exp()[group]
