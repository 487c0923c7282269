"""What is fixed during a call of stage 1 (and of stage 0's body scale): :class:`_Scene`, the
precomputed inputs of every pair fit, and :func:`_build_scene`, which checks the inputs and
builds it -- the video's distance maps (paired, :func:`_pair_map`, built ``FRAME_CHUNK``
frames at a time), the fixed silhouette subsample, the reference's capsules at scale ``G``
for every frame, the world's up from the cameras; plus the checks of the pairs and of the
generator arguments.

Conventions (see :mod:`motion.registration.approximate`): metres, radians, pixels with centres
at integer ``(u, v)``, ``u`` right, ``v`` down; camera frames as OpenCV (x right, y down, z
forward); rotation matrices act on column vectors. Shapes: ``T'`` video frames, ``T``
reference frames, ``C`` cameras, ``P`` parts, ``J`` joints, ``K`` keypoints, ``H x W`` images;
``R`` rows (video frames of the pairs), ``W`` reference frames per row.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from motion.body.observation import SampleLayout
from motion.features import distance_to_edges
from motion.registration.approximate.settings import Stage1Settings
from motion.registration.types import (
    FRAME_CHUNK,
    Reference,
    RegistrationError,
    VideoFeatures,
    scaled_spec,
)


def _unit(v, device: torch.device) -> Tensor:
    v = torch.as_tensor(v, dtype=torch.float64, device=device)
    return v / v.norm()


@dataclass
class _Scene:
    """Precomputed inputs of the pair fits (settings dtype).

    Attributes:
        dout: distance (px) to the nearest silhouette pixel (0 inside) as a paired map
            (:func:`_pair_map`, ``T' C H W`` entries); ``None`` where
            ``settings.outside_weight`` is 0 (nothing reads it).
        edist: the same for the distance to the nearest observed edge (or ``None``).
        obs: ``(T', C, M, 2)`` subsampled silhouette pixels; obs_w ``(T', C, M)`` weights
            (summing to 1 per valid image, 0 for padding).
        height: ``(T', C)`` silhouette pixel height; cam_w ``(T', C)`` 1 where the camera
            sees a silhouette; centroid ``(T', C, 2)`` silhouette centroid (px); top_v,
            bottom_v ``(T', C)`` its first and last rows; clipped ``(T', C, 2)`` bool, it
            touches the image's top / bottom edge; side_clipped ``(T', C, 2)`` the left /
            right edge.
        keypoints: ``(T', C, K, 3)`` or ``None``; kp_joints ``(K,)`` long skeleton joints.
        landmarks: ``(T, P, 2, 3)`` capsule ends of ``B_t`` at scale G (metres);
            radii ``(P, 2)`` metres; joints ``(T, J, 3)``.
        centre_b: ``(T, 3)`` body centroid in ``B_t``; extent_b ``(T,)`` height along up;
            centre_from_top ``(T,)`` the centroid's depth below the body's top, a fraction
            of extent_b.
        K, R, t: ``(C, 3, 3)``, ``(C, 3, 3)``, ``(C, 3)`` cameras; orthographic; H, W.
        up, forward: ``(3,)`` world up (from the cameras) and yaw-0 facing direction.
        video_rate: Hz. track: ``(T', 3)`` the person's root position per video frame from
            rigid fits (NaN until needed, :func:`_track_at`); v_ref ``(T, 3)`` the reference
            root's velocity in its own frame (m/s), ``None`` without the heading prior.
        fits: pair fits so far (for :attr:`Stage1Result.pair_evaluations`); tracking: True
            while the track itself is being fitted (the heading prior is off then).
        settings: the call's :class:`Stage1Settings`; body_height: median height of ``B_t``
            along its up, metres (scales the translation smoothing).
        align: ``(3, 3)`` maps the reference's up/forward onto up/forward.
        interior, outline: canonical sample layouts, 6 rows each
            (:meth:`motion.body.observation.SampleLayout.canonical`), and their blends
            ``(3, S)`` (``(1-s)^2, (1-s) s, s^2``) and ``(2, S)`` (``1-s, s``); rows are
            stored as ``(S, 1)`` columns (the batch-last layout of :class:`_Batch`).
    """

    dout: Tensor | None
    edist: Tensor | None
    obs: Tensor
    obs_w: Tensor
    height: Tensor
    cam_w: Tensor
    centroid: Tensor
    top_v: Tensor
    bottom_v: Tensor
    clipped: Tensor
    side_clipped: Tensor
    keypoints: Tensor | None
    kp_joints: Tensor | None
    landmarks: Tensor
    radii: Tensor
    joints: Tensor
    centre_b: Tensor
    extent_b: Tensor
    centre_from_top: Tensor
    K: Tensor
    R: Tensor
    t: Tensor
    orthographic: bool
    H: int
    W: int
    up: Tensor
    forward: Tensor
    align: Tensor
    interior: tuple[Tensor, ...]
    outline: tuple[Tensor, ...]
    interior_blend: tuple[Tensor, Tensor]
    outline_blend: tuple[Tensor, Tensor]
    settings: Stage1Settings
    body_height: float
    video_rate: float = 1.0
    track: Tensor | None = None
    v_ref: Tensor | None = None
    fits: int = 0
    tracking: bool = False

    @property
    def num_cameras(self) -> int:
        return self.K.shape[0]

    @property
    def num_video(self) -> int:
        return self.obs.shape[0]

    @property
    def num_ref(self) -> int:
        return self.landmarks.shape[0]

    @property
    def device(self) -> torch.device:
        """Where the scene's tensors (and so every pair fit) live."""
        return self.landmarks.device


def _pair_map(maps: Tensor) -> Tensor:
    """A map ``(..., H, W)`` as one flat entry per pixel holding its value and its right
    neighbour's (the last column repeats itself), viewed as one wider number so that one
    gather reads both: float32 pairs as float64, float64 pairs as complex128."""
    pairs = torch.empty(
        *maps.shape, 2, dtype=maps.dtype, device=maps.device
    )  # written in place: no temporaries
    pairs[..., 0] = maps
    pairs[..., :-1, 1] = maps[..., 1:]
    pairs[..., -1, 1] = maps[..., -1]
    wide = torch.float64 if maps.dtype == torch.float32 else torch.complex128
    return pairs.view(-1, 2).view(wide).reshape(-1)


def _pair_maps(make: Callable[[slice], Tensor], frames: int) -> Tensor:
    """:func:`_pair_map` of ``(T', C, H, W)`` maps built ``FRAME_CHUNK`` frames at a time by
    ``make(frames slice) -> (n, C, H, W)`` (settings dtype) into one flat tensor: the same
    entries as ``_pair_map`` of all frames (its order is frame-major), without ever holding
    more than a chunk's intermediates."""
    out = None
    for lo in range(0, frames, FRAME_CHUNK):
        part = _pair_map(make(slice(lo, min(lo + FRAME_CHUNK, frames))))
        if out is None:
            per_frame = part.numel() // min(FRAME_CHUNK, frames)
            out = torch.empty(frames * per_frame, dtype=part.dtype, device=part.device)
        out[lo * per_frame : lo * per_frame + part.numel()] = part
    return out


def _check_inputs(reference: Reference, video: VideoFeatures, scale: float) -> None:
    if not isinstance(reference, Reference):
        raise RegistrationError(f"expected a Reference; got {type(reference).__name__}")
    if not isinstance(video, VideoFeatures):
        raise RegistrationError(f"expected VideoFeatures; got {type(video).__name__}")
    if (
        isinstance(scale, bool)
        or not isinstance(scale, int | float)
        or not (math.isfinite(scale) and scale > 0)
    ):
        raise RegistrationError(f"scale (G) must be a finite number > 0; got {scale!r}")
    sil = video.observation.silhouette
    _, tv, _c, h, w = sil.shape
    if tv == 0:
        raise RegistrationError(f"{video.name}: expected at least one video frame; got 0")
    if reference.num_frames == 0:
        raise RegistrationError(f"{reference.name}: expected at least one reference frame; got 0")
    if h < 2 or w < 2:
        raise RegistrationError(f"{video.name}: expected images of at least 2 x 2; got {w} x {h}")
    if not torch.isfinite(sil).all() or sil.min() < 0 or sil.max() > 1:
        raise RegistrationError(f"{video.name}: silhouettes must be finite and in [0, 1]")
    size = video.cameras.size.to(torch.float64)
    if (
        size.shape != (_c, 2)
        or (size != torch.tensor([w, h], dtype=torch.float64, device=size.device)).any()
    ):
        raise RegistrationError(
            f"{video.name}: camera image sizes {size.tolist()} do not match the {w} x {h} "
            "silhouettes"
        )


def _build_scene(
    reference: Reference,
    video: VideoFeatures,
    scale: float,
    settings: Stage1Settings,
    generator: torch.Generator,
) -> _Scene:
    """Check the inputs and precompute what every pair fit reads (:class:`_Scene`): the
    distance maps, the silhouette subsample (drawn from ``generator``), the reference's
    capsules at scale ``scale`` for every frame, the world's up from the cameras."""
    _check_inputs(reference, video, scale)
    dt = settings.dtype
    obs = video.observation
    sil = obs.silhouette[0].to(dt)  # (T', C, H, W)
    tv, c, h, w = sil.shape
    mask = sil > 0.5
    count = mask.sum((-1, -2))  # (T', C)
    empty = (count == 0).all(1)
    if empty.any():
        frames = empty.nonzero().flatten()[:5].tolist()
        raise RegistrationError(
            f"{video.name}: expected a silhouette in at least one camera of every frame; "
            f"{int(empty.sum())} frames have none (first: {frames})"
        )
    cam_w = (count > 0).to(dt)
    # silhouette statistics for the starts and the normalisation, and the reference's
    # geometry, before the distance maps: their intermediates (float maps of every frame,
    # forward kinematics of every reference frame) then never sit on top of those maps
    rows_any = mask.any(-1)  # (T', C, H)
    vv = torch.arange(h, dtype=dt, device=sil.device)
    top_v = torch.where(rows_any, vv, torch.full_like(vv, float(h))).amin(-1)
    bottom_v = torch.where(rows_any, vv, torch.full_like(vv, -1.0)).amax(-1)
    height = (bottom_v - top_v + 1).clamp_min(8.0)
    weight = sil * mask
    total = weight.sum((-1, -2)).clamp_min(1e-9)
    uu = torch.arange(w, dtype=dt, device=sil.device)
    centroid = torch.stack(
        [(weight.sum(-2) * uu).sum(-1) / total, (weight.sum(-1) * vv).sum(-1) / total], -1
    )
    clipped = torch.stack([mask[..., 0, :].any(-1), mask[..., -1, :].any(-1)], -1)
    side_clipped = torch.stack([mask[..., :, 0].any(-1), mask[..., :, -1].any(-1)], -1)
    del weight, rows_any
    # the reference's geometry at scale G, every frame
    frames = torch.arange(reference.num_frames, device=reference.rotations.device)
    spec = scaled_spec(reference.spec, scale)
    landmarks = spec.landmarks(reference.body_poses(frames, scale)).to(dt)  # (T, P, 2, 3)
    radii = spec.shapes.radii.to(dt)
    joints = reference.body_frames(frames, scale).positions.to(dt)
    far = float(h + w)

    # distance to the nearest silhouette pixel (0 inside); empty images are ignored (cam_w 0)
    def outside(sl: slice) -> Tensor:
        # OpenCV's exact transform on every device (kornia's, a GPU's default, errs ~13 %)
        d = distance_to_edges(mask[sl].reshape(-1, 1, h, w), backend="opencv")
        d = d.reshape(-1, c, h, w).to(dt)
        return torch.nan_to_num(d, posinf=far)

    dout = _pair_maps(outside, tv) if settings.outside_weight > 0 else None
    edist = None
    if obs.edge_distance is not None:
        e = obs.edge_distance[0].to(dt)  # no copy when the dtypes agree
        if torch.isnan(e).any() or (e < 0).any():
            raise RegistrationError(f"{video.name}: edge_distance must be >= 0 and not NaN")

        def to_edges(sl: slice) -> Tensor:
            return torch.nan_to_num(e[sl], posinf=far).clamp(max=far)

        edist = _pair_maps(to_edges, tv)
    # fixed random subsample of silhouette pixels per image (without replacement); the keys
    # are drawn a chunk of frames at a time: consecutive draws from one generator are the
    # same numbers (and leave it in the same state) as one draw of all of them
    m = settings.observed_points
    tops, idxs = [], []
    for lo in range(0, tv, FRAME_CHUNK):
        sl = slice(lo, min(lo + FRAME_CHUNK, tv))
        n = sl.stop - sl.start
        keys = torch.rand(
            n * c, h * w, generator=generator, dtype=torch.float64, device=mask.device
        )
        keys = keys.masked_fill_(~mask[sl].reshape(n * c, -1), -1.0)
        top, idx = keys.topk(min(m, h * w), dim=-1)
        tops.append(top)
        idxs.append(idx)
    del keys
    top, idx = torch.cat(tops), torch.cat(idxs)
    valid = (top >= 0).to(dt)
    pts = torch.stack([idx % w, idx // w], -1).to(dt).reshape(tv, c, -1, 2)
    obs_w = (valid / valid.sum(-1, keepdim=True).clamp_min(1)).reshape(tv, c, -1)
    # keypoints
    keypoints = kp_joints = None
    if obs.keypoints is not None and video.keypoint_joints is not None:
        names = reference.skeleton.names
        unknown = [n for n in video.keypoint_joints if n not in names]
        if unknown:
            raise RegistrationError(
                f"{video.name}: keypoint joints {unknown} are not joints of {reference.name} "
                f"(expected names from {names[:4]}...)"
            )
        keypoints = obs.keypoints[0].to(dt)
        if not torch.isfinite(keypoints).all():
            raise RegistrationError(f"{video.name}: keypoints contain NaN or inf")
        kp_joints = torch.tensor([names.index(n) for n in video.keypoint_joints], device=sil.device)
    up_b = _unit(settings.reference_up, sil.device).to(dt)
    seg_len = (landmarks[..., 1, :] - landmarks[..., 0, :]).norm(dim=-1)  # (T, P)
    area = (radii.sum(-1)) * seg_len + math.pi / 2 * radii.square().sum(-1)
    centre_b = (area[..., None] * landmarks.mean(-2)).sum(-2) / area.sum(-1, keepdim=True)
    height_along = landmarks @ up_b  # (T, P, 2)
    top_b = (height_along + radii).amax((-1, -2))
    extent_b = top_b - (height_along - radii).amin((-1, -2))
    centre_from_top = (top_b - centre_b @ up_b) / extent_b.clamp_min(1e-9)
    body_height = float(extent_b.median())
    # cameras: world up from the cameras' y axes, yaw 0 facing camera 0
    rig = video.cameras
    kk, rr, tt = rig.K.to(dt), rig.R.to(dt), rig.t.to(dt)
    up = -rr[:, 1, :].mean(0)
    if up.norm() < 1e-6:
        raise RegistrationError(
            f"{video.name}: the cameras' y axes cancel out; cannot tell the world's up"
        )
    up = up / up.norm()
    fwd = -rr[0, 2, :]
    fwd = fwd - (fwd @ up) * up
    if fwd.norm() < 1e-3:  # camera 0 looks straight down or up: face its x axis
        fwd = rr[0, 0, :] - (rr[0, 0, :] @ up) * up
    fwd = fwd / fwd.norm()
    f_b = _unit(settings.reference_forward, sil.device).to(dt)
    f_b = f_b - (f_b @ up_b) * up_b
    if f_b.norm() < 1e-6:
        raise RegistrationError(
            "Stage1Settings.reference_forward must not be parallel to reference_up; got "
            f"{settings.reference_forward} and {settings.reference_up}"
        )
    f_b = f_b / f_b.norm()
    world = torch.stack([torch.linalg.cross(up, fwd), up, fwd], 1)  # columns
    body = torch.stack([torch.linalg.cross(up_b, f_b), up_b, f_b], 1)
    interior, _ = SampleLayout(
        along=settings.interior_along,
        across=settings.interior_across,
        cap_points=settings.interior_cap,
    ).canonical(dt)
    _, outline = SampleLayout(
        side=settings.outline_side, arc=max(settings.outline_arc, 1)
    ).canonical(dt)
    if settings.outline_arc == 0:  # side lines only (they come first)
        outline = outline[:, : 2 * settings.outline_side]
    interior, outline = interior.to(sil.device), outline.to(sil.device)  # made on the host

    def blends(canon):  # (3, S) and (2, S)
        s_ax = canon[0]
        return torch.stack([(1 - s_ax) ** 2, (1 - s_ax) * s_ax, s_ax**2]), torch.stack(
            [1 - s_ax, s_ax]
        )

    scene = _Scene(
        dout,
        edist,
        pts,
        obs_w,
        height,
        cam_w,
        centroid,
        top_v,
        bottom_v,
        clipped,
        side_clipped,
        keypoints,
        kp_joints,
        landmarks,
        radii,
        joints,
        centre_b,
        extent_b,
        centre_from_top,
        kk,
        rr,
        tt,
        bool(rig.orthographic),
        h,
        w,
        up,
        fwd,
        world @ body.T,
        tuple(row[:, None] for row in interior),
        tuple(row[:, None] for row in outline),
        blends(interior),
        blends(outline),
        settings,
        body_height,
    )
    scene.video_rate = float(video.frame_rate)
    if settings.heading_weight > 0:
        scene.track = torch.full((tv, 3), math.nan, dtype=dt, device=sil.device)
        root = reference.root.to(dt)
        v_world = _central_velocity(root, reference.frame_rate, settings.heading_window)
        rot = reference.rotations[:, 0].to(dt)  # (T, 3, 3) root to world
        scene.v_ref = (rot.transpose(1, 2) @ v_world[..., None])[..., 0]
    return scene


def _central_velocity(x: Tensor, rate: float, window: float) -> Tensor:
    """Velocity of a track ``x (F, 3)`` sampled at ``rate`` Hz by central differences over
    ``window`` seconds (one-sided at the ends). ``(F, 3)`` per second."""
    f = x.shape[0]
    k = max(1, round(window * rate / 2))
    i = torch.arange(f, device=x.device)
    lo, hi = (i - k).clamp(min=0), (i + k).clamp(max=f - 1)
    span = (hi - lo).clamp(min=1).to(x.dtype) / rate
    return (x[hi] - x[lo]) / span[:, None]


def _check_pairs(scene: _Scene, rows, cols) -> tuple[Tensor, Tensor]:
    if not isinstance(rows, Tensor) or not isinstance(cols, Tensor):
        raise RegistrationError(
            f"rows and cols must be tensors; got {type(rows).__name__} and {type(cols).__name__}"
        )
    if rows.dim() != 1 or cols.dim() != 2 or cols.shape[0] != rows.shape[0]:
        raise RegistrationError(
            f"expected rows (R,) and cols (R, W); got {tuple(rows.shape)} and {tuple(cols.shape)}"
        )
    if rows.numel() == 0 or cols.numel() == 0:
        raise RegistrationError(
            f"expected at least one pair; got rows {tuple(rows.shape)} and cols {tuple(cols.shape)}"
        )
    if rows.dtype.is_floating_point or cols.dtype.is_floating_point or rows.dtype == torch.bool:
        raise RegistrationError(
            f"rows and cols must be integer frame indices; got {rows.dtype} and {cols.dtype}"
        )
    rows, cols = rows.long().to(scene.device), cols.long().to(scene.device)
    if int(rows.min()) < 0 or int(rows.max()) >= scene.num_video:
        raise RegistrationError(
            f"rows must be video frames in [0, {scene.num_video}); got "
            f"{int(rows.min())}..{int(rows.max())}"
        )
    if int(cols.min()) < 0 or int(cols.max()) >= scene.num_ref:
        raise RegistrationError(
            f"cols must be reference frames in [0, {scene.num_ref}); got "
            f"{int(cols.min())}..{int(cols.max())}"
        )
    return rows, cols


def _generator(generator: torch.Generator | None, video: VideoFeatures) -> torch.Generator:
    """``generator``, checked to draw where ``video``'s features are (``None``: seed 0
    there)."""
    device = video.observation.silhouette.device
    if generator is None:
        return torch.Generator(device=device).manual_seed(0)
    if not isinstance(generator, torch.Generator):
        raise RegistrationError(
            f"generator must be a torch.Generator or None; got {type(generator).__name__}"
        )
    if generator.device.type != device.type:
        raise RegistrationError(
            f"the generator draws on {generator.device} but the video's features are on "
            f"{device}: make it with torch.Generator(device=...) of theirs"
        )
    return generator
