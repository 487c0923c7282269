"""Synthetic "student" sequences with ground truth, rendered from a reference BVH.

Every parameter lives in :class:`SynthConfig` (type, range and meaning declared per field). The generator
resamples the reference (120 Hz) to the video rate through a smooth non-linear monotone time
warp C, adds smooth articulation offsets A on chosen joints, moves the body along a global
path T (yaw and translation), scales the body (G), and renders every camera: silhouettes,
part labels, edges, intensity frames and 2-D joints (clean and noisy). A stretch of the
input can be replaced by later frames (the proposal's failure case), and another BVH can be
the student (then C has no ground truth).

Saved as ``sequence.npz`` (arrays) + ``sequence.json`` (config, shapes, units, camera
parameters); with ``videos=true`` also one ``.avi`` per camera and the cameras as a Pose2Sim
``calibration.toml``, so that the folder is a complete input to ``motion register``.
Units: metres, radians inside; the stored articulation A is in degrees.
"""

from __future__ import annotations

import difflib
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np
import torch

from motion.bodyparts import BodyModel
from motion.bvh import read_bvh
from motion.cameras import CameraRig, save_pose2sim_calibration
from motion.draw import PART_COLOURS, write_video
from motion.features import BACKGROUND_SUFFIX, edges
from motion.geometry import euler_to_matrix, rotation_about_y
from motion.kinematics import FKResult, Skeleton, forward_kinematics, local_rotations
from motion.render import ProjectedParts, label_map, project_parts
from motion.settings import SettingError, Settings, echo, from_text, setting, show

__all__ = [
    "BACKGROUND_RGB",
    "BACKGROUND_SUFFIX",
    "CALIBRATION_FILE",
    "Sequence",
    "SynthConfig",
    "SynthConfigError",
    "load_sequence",
    "save_sequence",
    "sequence_files",
    "synthesize",
    "time_warp",
]


#: the scene's colour behind the body (RGB in [0, 1])
BACKGROUND_RGB = (0.85, 0.85, 0.8)
#: with the videos, each camera's empty scene (a clean plate, as one films before the person
#: walks in) is written as ``<camera><BACKGROUND_SUFFIX>`` (:data:`motion.features.
#: BACKGROUND_SUFFIX`, where ``motion register`` looks for it)
#: video frames coloured (and their edges found) at once: each image is its own, so only the
#: uint8 frames of the whole video are kept, never float colour fields of every frame
COLOUR_CHUNK = 64


class SynthConfigError(SettingError):
    """A synthetic-sequence setting outside its type or range, or one the reference cannot
    satisfy (an unknown joint, too short a video for the replaced stretch)."""


@dataclass
class SynthConfig(Settings):
    """Parameters of a synthetic sequence: every field has a default, a declared range and a
    meaning (``python -m motion synth --help`` lists them). Checked at construction and by
    :meth:`validate`; a bad value raises :class:`SynthConfigError` naming the field, what it
    must be and what it was."""

    setting_error: ClassVar[type[SettingError]] = SynthConfigError

    fps: float = setting(
        25.0, "video frame rate in Hz (the reference's rate is read from its file)", gt=0, le=1000
    )
    warp: float = setting(
        0.3,
        "largest relative change of playback speed along the smooth non-linear time warp "
        "(0: uniform resampling); C stays monotone",
        ge=0,
        lt=1,
    )
    articulation: dict[str, float] = setting(
        {},
        "joint name -> largest offset in degrees: each named joint gets a smooth offset on all "
        "three axes, up to that amplitude (30 or less recommended)",
        ge=0,
        le=180,
        example="LeftLeg:20,RightArm:30",
    )
    yaw_deg: float = setting(0.0, "total rotation of the body about the vertical, degrees")
    path_m: list[float] = setting(
        [0.0, 0.0, 0.0],
        "x,y,z translation in metres added linearly over the sequence",
        length=3,
        example="0.5,0,0",
    )
    body_scale: float = setting(
        1.0, "body size G: multiplies bone lengths and part radii", gt=0, le=10
    )
    cameras: int = setting(
        1, "number of static cameras, evenly spaced on a circle around the body", ge=1, le=64
    )
    camera_distance_m: float | None = setting(
        None,
        "camera distance from the body's mean root position in metres (none: 2.5 m beyond "
        "the farthest the root gets from its mean)",
        gt=0,
    )
    camera_height_m: float = setting(1.0, "camera height above the floor, metres")
    focal_px: float = setting(300.0, "focal length in pixels", gt=0)
    size: list[int] = setting(
        [160, 120],
        "image width x height in pixels",
        length=2,
        ge=8,
        le=4096,
        sep="x,",
        example="320x240",
    )
    noise_px: float = setting(
        1.0, "standard deviation of the Gaussian noise on the noisy 2-D joints, pixels", ge=0
    )
    replace: list[float] | None = setting(
        None,
        "start,end fractions of the video whose frames are replaced by the (end - start) "
        "that follow them, the proposal's corruption (needs end + (end - start) <= 1); none: "
        "no corruption",
        length=2,
        ge=0,
        le=1,
        example="0.4,0.5",
    )
    drop_reference_pose: bool = setting(
        True, "drop frame 0 when it is a converter's reference pose"
    )
    videos: bool = setting(False, "also write one video per camera (intensity frames, .avi)")
    seed: int = setting(0, "seed of every random draw", ge=0, le=2**32 - 1)

    def validate(self) -> None:
        """Check every field (types and ranges), then the replaced stretch's bounds."""
        super().validate()
        if self.replace is not None:
            start, end = self.replace
            if not start < end or end + (end - start) > 1:
                raise SynthConfigError(
                    f"SynthConfig: replace must be start,end with start < end and "
                    f"end + (end - start) <= 1 (the replacing frames follow the stretch); "
                    f"got {show(self.replace)}"
                )

    @classmethod
    def from_assignments(cls, items: list[str], where: str = "synth") -> SynthConfig:
        """``["fps=30", "size=320x240", ...]`` -> a checked config (see
        :func:`motion.settings.from_text` for the syntax). Unknown keys, repeated keys and
        bad values raise :class:`SynthConfigError` naming the setting."""
        values: dict[str, object] = {}
        for item in items:
            key, eq, text = item.partition("=")
            key = key.strip()
            if not eq or not key:
                raise SynthConfigError(
                    f"{where}: expected a setting as key=value (e.g. fps=30); got {item!r}"
                )
            if key in values:
                raise SynthConfigError(f"{where}: {echo(key)} is given twice")
            values[key] = from_text(cls, key, text, where, error=SynthConfigError)
        try:
            return cls(**values)
        except SynthConfigError as err:  # a check across fields: say where it came from
            raise SynthConfigError(str(err).replace("SynthConfig:", f"{where}:", 1)) from None


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
    reference: str | Path,
    config: SynthConfig | None = None,
    student: str | Path | None = None,
    frames: int | None = None,
    images: bool = True,
) -> Sequence:
    """Generate a synthetic sequence.

    Args:
        reference: the reference BVH; config: :class:`SynthConfig` (defaults otherwise);
            student: another performer's BVH (then no true C).
        frames: keep only the first ``frames`` video frames (``None``: all): every per-frame
            array is cut to them and only they are rendered, while what the frames share --
            the time warp, the articulation, the random draws, the cameras placed around the
            whole motion -- is the whole video's, so they are exactly its first frames.
        images: ``False`` renders nothing: the sequence has no ``silhouettes``, ``labels``,
            ``edges`` or ``frames`` (its poses and joints only, for a truth at little cost).

    Returns:
        :class:`Sequence` whose arrays are: ``C_true`` (T',) long reference frames (-1 if
        the student is another performer); ``replaced`` (T',) bool; ``A_deg`` (T', J, 3);
        ``T_yaw_rad`` (T',), ``T_translation_m`` (T', 3); ``joints3d`` (T', J, 3) metres;
        ``joints2d`` (C, T', J, 2) px and ``joints2d_noisy``; ``silhouettes`` (C, T', H, W)
        bool; ``labels`` (C, T', H, W) int8 (-1 background); ``edges`` (C, T', H, W) bool;
        ``frames`` (C, T', H, W, 3) uint8; camera ``K`` (C, 3, 3), ``R`` (C, 3, 3), ``t`` (C, 3).

    Raises:
        SynthConfigError: a setting the reference cannot satisfy (an articulated joint it
            does not have, a replaced stretch without frames, joints behind a camera, images
            beyond :data:`MAX_IMAGE_BYTES`); file errors come from :func:`motion.bvh.read_bvh`.
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
    kept = num_video if frames is None else max(1, min(frames, num_video))
    drawn = kept if images else 0  # the frames whose images are rendered
    _check_against(cfg, skel, drawn, student if student is not None else reference)

    # C: smooth non-linear monotone warp from video frames to source frames
    u = torch.linspace(0, 1, num_video, dtype=torch.float64)
    c_true = time_warp(num_video, num_ref, cfg.warp, g)
    shown = c_true.clone()
    replaced = torch.zeros(num_video, dtype=torch.bool)
    if cfg.replace is not None:
        lo, hi = (int(f * num_video) for f in cfg.replace)
        length = hi - lo
        if length == 0:
            raise SynthConfigError(
                f"replace={_text(cfg.replace)} covers no frame of the {num_video}-frame video; "
                "expected a stretch of at least one frame (raise fps or widen replace)"
            )
        if hi + length > num_video:
            raise SynthConfigError(
                f"replace={_text(cfg.replace)} replaces frames {lo}-{hi - 1} by frames "
                f"{hi}-{hi + length - 1}; expected them inside the {num_video}-frame video "
                "(move or narrow replace)"
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
    r_yaw = rotation_about_y(yaw)  # (T', 3, 3)
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
    joints2d, depth = rig.project(pos)  # (T', C, J, 2), (T', C, J)
    _check_in_front(depth, skel.names, rig.names, distance)
    joints2d = joints2d.transpose(0, 1)  # (C, T', J, 2)
    noisy = joints2d + cfg.noise_px * torch.randn(joints2d.shape, generator=g, dtype=torch.float64)

    first = slice(0, kept)
    arrays = {
        "C_true": (c_true if student is None else torch.full_like(c_true, -1))[first].numpy(),
        "C_shown": shown[first].numpy(),
        "replaced": replaced[first].numpy(),
        "A_deg": a_deg[first].numpy(),
        "T_yaw_rad": yaw[first].numpy(),
        "T_translation_m": trans[first].numpy(),
        "joints3d": pos[first].numpy(),
        "joints2d": joints2d[:, first].numpy(),
        "joints2d_noisy": noisy[:, first].numpy(),
    }
    if images:
        parts = project_parts(rig, seg[first], model.radii * cfg.body_scale)  # (n, C, P, 2, *)
        arrays.update(_images(cfg, parts))
    arrays.update({"K": rig.K.numpy(), "R": rig.R.numpy(), "t": rig.t.numpy()})
    meta = {
        "format": "motionreg synthetic sequence v1",
        "reference": str(reference),
        "student": None if student is None else str(student),
        "config": asdict(cfg),
        "reference_rate_hz": source.frame_rate,
        "video_rate_hz": cfg.fps,
        "num_video_frames": kept,
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


def _images(cfg: SynthConfig, parts: ProjectedParts) -> dict[str, np.ndarray]:
    """The rendered ``silhouettes``, ``labels``, ``edges`` and colour ``frames`` of the
    projected body ``parts`` (``(T', C, P, ...)``), each ``(C, T', H, W[, 3])``."""
    w, h = cfg.size
    num_video = parts.ends.shape[0]
    labels = torch.empty(cfg.cameras, num_video, h, w, dtype=torch.int8)
    for s in range(0, num_video, 8):  # chunks keep the (frames, C, P, H*W) fields small
        sl = slice(s, min(s + 8, num_video))
        chunk = ProjectedParts(parts.ends[sl], parts.radii[sl], parts.depth[sl])
        lab, _ = label_map(chunk, h, w)
        labels[:, sl] = lab.transpose(0, 1).to(torch.int8)
    shade = torch.from_numpy(PART_COLOURS.astype(np.float32) / 255.0)
    bg = torch.tensor(BACKGROUND_RGB)
    table = torch.cat([bg[None], shade])
    # colour frames and their edges a chunk of frames at a time (COLOUR_CHUNK)
    frames = np.empty((cfg.cameras, num_video, h, w, 3), dtype=np.uint8)
    edge = torch.empty(cfg.cameras, num_video, h, w, dtype=torch.bool)
    for s in range(0, num_video, COLOUR_CHUNK):
        sl = slice(s, min(s + COLOUR_CHUNK, num_video))
        rgb = table[(labels[:, sl].long() + 1)]  # (C, n, H, W, 3)
        grey = rgb.mean(-1).reshape(-1, 1, h, w)
        edge[:, sl] = edges(grey, 0.1, 0.3).reshape(cfg.cameras, -1, h, w)
        frames[:, sl] = (rgb.numpy() * 255).round().astype(np.uint8)
    return {
        "silhouettes": (labels >= 0).numpy(),
        "labels": labels.numpy(),
        "edges": edge.numpy(),
        "frames": frames,
    }


#: Largest memory the rendered images of one sequence may take (about 24 bytes per pixel of
#: every camera's every frame, intermediate fields included); beyond it synthesize refuses.
MAX_IMAGE_BYTES = 8 << 30


def _text(values: list[float]) -> str:
    return ",".join(f"{v:g}" for v in values)


def _check_against(cfg: SynthConfig, skel: Skeleton, num_video: int, source) -> None:
    """Settings the source motion must satisfy: articulated joints exist; the images of
    ``num_video`` frames fit."""
    for name in cfg.articulation:
        if name not in skel.names:
            close = difflib.get_close_matches(name, skel.names, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise SynthConfigError(
                f"articulation: {source} has no joint {name!r}{hint}; its joints: "
                f"{', '.join(skel.names)}"
            )
    w, h = cfg.size
    need = 24 * cfg.cameras * num_video * w * h
    if need > MAX_IMAGE_BYTES:
        raise SynthConfigError(
            f"cameras={cfg.cameras} x {num_video} frames x size={w}x{h} would need about "
            f"{need / 2**30:.1f} GiB of images; expected at most {MAX_IMAGE_BYTES / 2**30:.0f} "
            "GiB (lower size, cameras or fps)"
        )


def _check_in_front(depth: torch.Tensor, joints: list[str], cameras: list[str], distance) -> None:
    """Every joint must be in front of every camera (depth ``(T', C, J)`` metres)."""
    if bool((depth > 1e-3).all()):
        return
    t, c, j = (int(i) for i in torch.nonzero(depth <= 1e-3)[0])
    raise SynthConfigError(
        f"camera_distance_m={distance:.3g}: joint {joints[j]} is at depth "
        f"{float(depth[t, c, j]):.2f} m from camera {cameras[c]} in video frame {t}; expected "
        "every joint in front of every camera (raise camera_distance_m, or lower body_scale)"
    )


#: the cameras of a sequence written with its videos (Pose2Sim TOML, see
#: :func:`motion.cameras.save_pose2sim_calibration`)
CALIBRATION_FILE = "calibration.toml"


def sequence_files(meta: dict, out_dir: str | Path) -> list[Path]:
    """The files :func:`save_sequence` writes for a sequence with metadata ``meta``."""
    out = Path(out_dir)
    files = [out / "sequence.npz", out / "sequence.json"]
    if meta["config"]["videos"]:
        files += [out / f"{name}.avi" for name in meta["cameras"]]
        files += [out / f"{name}{BACKGROUND_SUFFIX}" for name in meta["cameras"]]
        files.append(out / CALIBRATION_FILE)
    return files


def _sequence_rig(seq: Sequence) -> CameraRig:
    """The rig the sequence was rendered with (float64), from its ``K``, ``R``, ``t``."""
    k = torch.from_numpy(seq.arrays["K"]).to(torch.float64)
    c = k.shape[0]
    w, h = seq.meta["config"]["size"]
    return CameraRig(
        k,
        torch.from_numpy(seq.arrays["R"]).to(torch.float64),
        torch.from_numpy(seq.arrays["t"]).to(torch.float64),
        torch.zeros(c, 5, dtype=torch.float64),
        torch.tensor([[w, h]] * c, dtype=torch.float64),
        list(seq.meta["cameras"]),
    )


def save_sequence(seq: Sequence, out_dir: str | Path) -> Path:
    """Write ``sequence.npz`` + ``sequence.json`` (and, if configured, one ``.avi`` per camera
    and the cameras as :data:`CALIBRATION_FILE`) into ``out_dir`` (:func:`sequence_files`
    lists them); returns ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / "sequence.npz", **seq.arrays)
    (out / "sequence.json").write_text(json.dumps(seq.meta, indent=2))
    if seq.meta["config"]["videos"]:
        plate = cv2.cvtColor(np.ascontiguousarray(seq.arrays["frames"][0, 0]), cv2.COLOR_RGB2BGR)
        plate[...] = np.round(np.array(BACKGROUND_RGB[::-1]) * 255).astype(np.uint8)
        for c, name in enumerate(seq.meta["cameras"]):
            write_video(out / f"{name}.avi", seq.arrays["frames"][c], seq.meta["video_rate_hz"])
            if not cv2.imwrite(str(out / f"{name}{BACKGROUND_SUFFIX}"), plate):
                raise OSError(f"{out / (name + BACKGROUND_SUFFIX)}: OpenCV cannot write it")
        save_pose2sim_calibration(_sequence_rig(seq), out / CALIBRATION_FILE)
    return out


def load_sequence(out_dir: str | Path) -> Sequence:
    """Read a sequence written by :func:`save_sequence`."""
    out = Path(out_dir)
    with np.load(out / "sequence.npz") as data:
        arrays = {k: data[k] for k in data.files}
    return Sequence(arrays, json.loads((out / "sequence.json").read_text()))
