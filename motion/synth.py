"""Synthetic "student" sequences with ground truth, rendered from a reference BVH.

Every parameter lives in :class:`SynthConfig` (documented field by field). The generator
resamples the reference (120 Hz) to the video rate through a smooth non-linear monotone time
warp C, adds smooth articulation offsets A on chosen joints, moves the body along a global
path T (yaw and translation), scales the body (G), and renders every camera: silhouettes,
part labels, edges, intensity frames and 2-D joints (clean and noisy). A stretch of the
input can be replaced by later frames (the proposal's failure case), and another BVH can be
the student (then C has no ground truth).

Saved as ``sequence.npz`` (arrays) + ``sequence.json`` (config, shapes, units, camera
parameters). Units: metres, radians inside; the stored articulation A is in degrees.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from motion.bodyparts import BodyModel
from motion.bvh import read_bvh
from motion.cameras import CameraRig
from motion.draw import PART_COLOURS, write_video
from motion.features import edges
from motion.kinematics import (
    FKResult,
    Skeleton,
    euler_to_matrix,
    forward_kinematics,
    local_rotations,
)
from motion.render import ProjectedParts, label_map, project_parts

__all__ = ["Sequence", "SynthConfig", "load_sequence", "save_sequence", "synthesize", "time_warp"]


@dataclass
class SynthConfig:
    """Parameters of a synthetic sequence (all have defaults).

    Attributes:
        fps: video frame rate (the reference's rate is read from its file).
        warp: largest relative change of playback speed along the smooth non-linear time
            warp, in [0, 1) (0 = uniform resampling); C stays monotone.
        articulation: ``{joint name: max offset in degrees}``; each gets a smooth offset
            on all three axes, up to that amplitude (<= 30 recommended).
        yaw_deg: total rotation of the body about the vertical over the sequence.
        path_m: ``[x, y, z]`` translation added linearly over the sequence (metres).
        body_scale: G, multiplies bone lengths and part radii.
        cameras: number of static cameras, evenly spaced on a circle around the body.
        camera_distance_m, camera_height_m, focal_px: camera placement and intrinsics
            (distance ``None``: 2.5 m beyond the farthest the root gets from its mean).
        size: image ``[width, height]`` in pixels.
        noise_px: std of the Gaussian noise on the noisy 2-D joints.
        replace: ``[start, end]`` fractions of the video whose frames are replaced by the
            frames that follow them (the proposal's corruption), or ``None``.
        drop_reference_pose: drop frame 0 when it is a converter's reference pose.
        videos: also write one video per camera (intensity frames).
        seed: every random draw.
    """

    fps: float = 25.0
    warp: float = 0.3
    articulation: dict[str, float] = field(default_factory=dict)
    yaw_deg: float = 0.0
    path_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    body_scale: float = 1.0
    cameras: int = 1
    camera_distance_m: float | None = None
    camera_height_m: float = 1.0
    focal_px: float = 300.0
    size: list[int] = field(default_factory=lambda: [160, 120])
    noise_px: float = 1.0
    replace: list[float] | None = None
    drop_reference_pose: bool = True
    videos: bool = False
    seed: int = 0

    def validate(self) -> None:
        if not self.fps > 0:
            raise ValueError(f"fps must be > 0; got {self.fps}")
        if not 0 <= self.warp < 1:
            raise ValueError(f"warp must be in [0, 1) to keep C monotone; got {self.warp}")
        if self.cameras < 1:
            raise ValueError(f"cameras must be >= 1; got {self.cameras}")
        if len(self.size) != 2 or min(self.size) < 8:
            raise ValueError(f"size must be [width, height] >= 8; got {self.size}")
        if self.replace is not None and not (
            0 <= self.replace[0] < self.replace[1] <= 0.5 + self.replace[0]
        ):
            raise ValueError(
                f"replace must be [start, end] fractions with start < end; got {self.replace}"
            )
        if not self.body_scale > 0:
            raise ValueError(f"body_scale must be > 0; got {self.body_scale}")


@dataclass
class Sequence:
    """A synthetic sequence in memory (see :func:`synthesize` for the arrays' shapes)."""

    arrays: dict[str, np.ndarray]
    meta: dict


def time_warp(
    num_video: int, num_ref: int, strength: float, generator: torch.Generator
) -> torch.Tensor:
    """A smooth non-linear monotone correspondence ``C`` (``(T',)`` long) from ``num_video``
    frames onto ``[0, num_ref - 1]``, both ends fixed: ``w(u) = u + s sin(2 pi k u) / (2 pi k)``
    with a random ``k`` in [1, 2], so playback speed stays within ``1 +- strength``."""
    if not 0 <= strength < 1:
        raise ValueError(f"warp strength must be in [0, 1); got {strength}")
    u = torch.linspace(0, 1, num_video, dtype=torch.float64)
    bend = 1 + float(torch.rand(1, generator=generator))
    warp = u + strength * torch.sin(2 * math.pi * bend * u) / (2 * math.pi * bend)
    warp = (warp - warp[0]) / (warp[-1] - warp[0]).clamp_min(1e-12)
    return torch.cummax((warp * (num_ref - 1)).round().long(), 0).values


def _rig(cfg: SynthConfig, centre: torch.Tensor, distance: float) -> CameraRig:
    """Cameras on a circle around ``centre`` (world Y up), looking at it horizontally."""
    w, h = cfg.size
    ks, rs, ts = [], [], []
    for c in range(cfg.cameras):
        a = 2 * math.pi * c / cfg.cameras
        eye = centre + torch.tensor(
            [distance * math.sin(a), 0.0, distance * math.cos(a)], dtype=torch.float64
        )
        eye[1] = cfg.camera_height_m
        fwd = torch.nn.functional.normalize(centre - eye, dim=0)
        right = torch.nn.functional.normalize(
            torch.linalg.cross(fwd, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)), dim=0
        )
        down = torch.linalg.cross(fwd, right)
        r = torch.stack([right, down, fwd])  # rows: camera axes in world coordinates
        rs.append(r)
        ts.append(-r @ eye)
        ks.append(
            torch.tensor(
                [[cfg.focal_px, 0, w / 2], [0, cfg.focal_px, h / 2], [0, 0, 1]], dtype=torch.float64
            )
        )
    n = cfg.cameras
    return CameraRig(
        torch.stack(ks),
        torch.stack(rs),
        torch.stack(ts),
        torch.zeros(n, 5, dtype=torch.float64),
        torch.tensor([[w, h]] * n, dtype=torch.float64),
        [f"cam{c + 1}" for c in range(n)],
    )


def synthesize(
    reference: str | Path, config: SynthConfig | None = None, student: str | Path | None = None
) -> Sequence:
    """Generate a synthetic sequence.

    Returns:
        :class:`Sequence` whose arrays are: ``C_true`` (T',) long reference frames (-1 if
        the student is another performer); ``replaced`` (T',) bool; ``A_deg`` (T', J, 3);
        ``T_yaw_rad`` (T',), ``T_translation_m`` (T', 3); ``joints3d`` (T', J, 3) metres;
        ``joints2d`` (C, T', J, 2) px and ``joints2d_noisy``; ``silhouettes`` (C, T', H, W)
        bool; ``labels`` (C, T', H, W) int8 (-1 background); ``edges`` (C, T', H, W) bool;
        ``frames`` (C, T', H, W, 3) uint8; camera ``K`` (C, 3, 3), ``R`` (C, 3, 3), ``t`` (C, 3).
    """
    cfg = config or SynthConfig()
    cfg.validate()
    g = torch.Generator().manual_seed(cfg.seed)
    ref = read_bvh(reference)
    source = read_bvh(student) if student is not None else ref
    motion = source.motion_frames() if cfg.drop_reference_pose else source.motion
    skel = Skeleton.from_bvh(source)
    num_ref = motion.shape[0]
    num_video = int((num_ref - 1) * cfg.fps / source.frame_rate) + 1

    # C: smooth non-linear monotone warp from video frames to source frames
    u = torch.linspace(0, 1, num_video, dtype=torch.float64)
    c_true = time_warp(num_video, num_ref, cfg.warp, g)
    shown = c_true.clone()
    replaced = torch.zeros(num_video, dtype=torch.bool)
    if cfg.replace is not None:
        lo, hi = (int(f * num_video) for f in cfg.replace)
        length = hi - lo
        if hi + length > num_video:
            raise ValueError(
                f"replace {cfg.replace} needs {hi + length} frames; the video has {num_video}"
            )
        shown[lo:hi] = c_true[hi : hi + length]
        replaced[lo:hi] = True

    rot, root = local_rotations(skel, torch.from_numpy(motion[shown.numpy()]), source.channels)
    # A: smooth articulation offsets on chosen joints
    j = skel.num_joints
    a_deg = torch.zeros(num_video, j, 3, dtype=torch.float64)
    for name, amplitude in cfg.articulation.items():
        idx = skel.index(name)
        phase = torch.rand(3, generator=g, dtype=torch.float64) * 2 * math.pi
        freq = 0.5 + torch.rand(3, generator=g, dtype=torch.float64)
        a_deg[:, idx] = amplitude * torch.sin(2 * math.pi * freq * u[:, None] + phase)
        order = skel.rotation_orders[idx] or "ZYX"
        rot[:, idx] = rot[:, idx] @ euler_to_matrix(torch.deg2rad(a_deg[:, idx]), order)
    # G: body size
    offsets = skel.offsets * cfg.body_scale
    fk = forward_kinematics(skel, rot, root * cfg.body_scale, offsets)
    # T: yaw about the vertical through the first root position, plus a linear path
    yaw = torch.deg2rad(torch.tensor(cfg.yaw_deg, dtype=torch.float64)) * u
    trans = u[:, None] * torch.tensor(cfg.path_m, dtype=torch.float64)
    pivot = fk.positions[0, 0].clone()
    pivot[1] = 0.0
    cy, sy = torch.cos(yaw), torch.sin(yaw)
    r_yaw = torch.zeros(num_video, 3, 3, dtype=torch.float64)
    r_yaw[:, 0, 0], r_yaw[:, 0, 2], r_yaw[:, 1, 1], r_yaw[:, 2, 0], r_yaw[:, 2, 2] = (
        cy,
        sy,
        1.0,
        -sy,
        cy,
    )
    pos = (
        (r_yaw[:, None] @ (fk.positions - pivot).unsqueeze(-1)).squeeze(-1) + pivot + trans[:, None]
    )
    glob_rot = r_yaw[:, None] @ fk.rotations
    fk = FKResult(pos, glob_rot)

    model = BodyModel.from_skeleton(skel)
    seg = model.segments(model.skeleton_points(skel, fk))  # (T', P, 2, 3)
    centre = pos[..., 0, :].mean(0)
    distance = cfg.camera_distance_m
    if distance is None:
        distance = 2.5 + float((pos[..., 0, :] - centre)[..., [0, 2]].norm(dim=-1).max())
    rig = _rig(cfg, centre, distance)
    w, h = cfg.size
    joints2d, _ = rig.project(pos)  # (T', C, J, 2)
    joints2d = joints2d.transpose(0, 1)  # (C, T', J, 2)
    noisy = joints2d + cfg.noise_px * torch.randn(joints2d.shape, generator=g, dtype=torch.float64)

    parts = project_parts(rig, seg, model.radii * cfg.body_scale)  # (T', C, P, 2, *)
    labels = torch.empty(cfg.cameras, num_video, h, w, dtype=torch.int8)
    for s in range(0, num_video, 8):  # chunks keep the (frames, C, P, H*W) fields small
        sl = slice(s, min(s + 8, num_video))
        chunk = ProjectedParts(parts.ends[sl], parts.radii[sl], parts.depth[sl])
        lab, _ = label_map(chunk, h, w)
        labels[:, sl] = lab.transpose(0, 1).to(torch.int8)
    sil = labels >= 0
    shade = torch.from_numpy(PART_COLOURS.astype(np.float32) / 255.0)
    bg = torch.tensor([0.85, 0.85, 0.8])
    table = torch.cat([bg[None], shade])
    frames = table[(labels.long() + 1)]  # (C, T', H, W, 3)
    grey = frames.mean(-1).reshape(-1, 1, h, w)
    edge = edges(grey, 0.1, 0.3).reshape(cfg.cameras, num_video, h, w)

    arrays = {
        "C_true": (c_true if student is None else torch.full_like(c_true, -1)).numpy(),
        "C_shown": shown.numpy(),
        "replaced": replaced.numpy(),
        "A_deg": a_deg.numpy(),
        "T_yaw_rad": yaw.numpy(),
        "T_translation_m": trans.numpy(),
        "joints3d": pos.numpy(),
        "joints2d": joints2d.numpy(),
        "joints2d_noisy": noisy.numpy(),
        "silhouettes": sil.numpy(),
        "labels": labels.numpy(),
        "edges": edge.numpy(),
        "frames": (frames.numpy() * 255).round().astype(np.uint8),
        "K": rig.K.numpy(),
        "R": rig.R.numpy(),
        "t": rig.t.numpy(),
    }
    meta = {
        "format": "motionreg synthetic sequence v1",
        "reference": str(reference),
        "student": None if student is None else str(student),
        "config": asdict(cfg),
        "reference_rate_hz": source.frame_rate,
        "video_rate_hz": cfg.fps,
        "num_video_frames": num_video,
        "num_reference_frames": num_ref,
        "joint_names": skel.names,
        "part_names": model.part_names,
        "cameras": rig.names,
        "units": {
            "length": "metres",
            "angles": "A in degrees, T_yaw in radians",
            "pixels": "u right, v down",
        },
        "metres_per_file_unit": skel.metres_per_unit,
        "shapes": {k: list(v.shape) for k, v in arrays.items()},
    }
    return Sequence(arrays, meta)


def save_sequence(seq: Sequence, out_dir: str | Path) -> Path:
    """Write ``sequence.npz`` + ``sequence.json`` (and videos if configured) into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / "sequence.npz", **seq.arrays)
    (out / "sequence.json").write_text(json.dumps(seq.meta, indent=2))
    if seq.meta["config"]["videos"]:
        for c, name in enumerate(seq.meta["cameras"]):
            write_video(out / f"{name}.avi", seq.arrays["frames"][c], seq.meta["video_rate_hz"])
    return out


def load_sequence(out_dir: str | Path) -> Sequence:
    """Read a sequence written by :func:`save_sequence`."""
    out = Path(out_dir)
    with np.load(out / "sequence.npz") as data:
        arrays = {k: data[k] for k in data.files}
    return Sequence(arrays, json.loads((out / "sequence.json").read_text()))
