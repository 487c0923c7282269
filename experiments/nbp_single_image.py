"""Posture refinement from images by particle BP (the proposal's Section 6.2.1, Figs. 14-15).

The proposal's protocol: frames of a BVH motion rendered from fixed cameras (orthographic as
in the proposal, perspective as an option) -- silhouette, part-coloured intensity image, its
Canny edges and their distance transform, exactly as ``motion.features`` computes them on a
video -- and, per frame, a start posture: the truth with uniform noise of +-``noise_deg`` on
every angle of every part's joint (the root's orientation and position kept). Particle BP
over the body graph of ``motion.body`` (15 SE(3) parts, annealed connections, the
occlusion-aware observation factor with the chosen cues) refines it
(:func:`motion.body.solve.solve_posture`), as ``starts`` independent searches (one batch) of
which each frame keeps the one whose rendering explains the images best
(:mod:`motion.body.select`); errors are the proposal's E_2D and E_3D (Eqs.
36-37): mean landmark distance over the figure's height, in camera 0's image and in 3-D.
``e3d_depth_oracle_mean`` is E_3D once every part's depth flip in camera 0 and the body's
depth are set right (:mod:`motion.body.ambiguity`): the error one orthographic view could in
principle remove. Writes per-frame errors, Figs. 14-15-style curves and a contact sheet of
truth / start / result overlays.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np
import torch
from torch import Tensor

from experiments.config import ConfigError, ExperimentConfig
from experiments.progress import note
from experiments.stick_time import BUNDLED
from motion.body.ambiguity import resolve_depth_flips
from motion.body.graph import Connections, Temporal, body_graph
from motion.body.observation import (
    BodyObservation,
    Edges,
    Intensity,
    Joints2D,
    Observation,
    PartShapes,
    Silhouette,
)
from motion.body.solve import Images, PostureSettings, anneal_schedule, solve_posture
from motion.body.spec import BodySpec
from motion.bodyparts import BodyModel
from motion.bvh import read_bvh
from motion.cameras import CameraRig
from motion.draw import PART_COLOURS, contact_sheet, draw_parts
from motion.features import distance_to_edges, edges
from motion.kinematics import Skeleton, euler_to_matrix, forward_kinematics, local_rotations
from motion.render import label_map, project_parts, render_intensity, silhouette
from motion.settings import setting

CUES = ("silhouette", "edges", "intensity", "joints")
KEYPOINT_NOISE_PX = 2.0  # std of the simulated detector's 2-D joints (the joints cue)
CAMERAS = ("orthographic", "perspective")
#: metrics that are timings (timings.json)
TIMINGS = ("sec_per_frame",)
H, W = 120, 160  # the synthetic default resolution (motion.synth)
PX_PER_M = 57.0  # orthographic scale: a 1.75 m figure ~100 px tall
FOCAL = 300.0  # perspective focal length, pixels (motion.synth's default)


@dataclass
class NbpSingleImageConfig(ExperimentConfig):
    """Fields of ``experiments/configs/nbp_single_image.yaml``."""

    NAME = "nbp_single_image"
    TINY_DOC = (
        "a quick run: frames=2, particles=30, iterations=2, restarts=1 (values given on the "
        "command line win)"
    )
    TINY: ClassVar[dict] = {
        "frames": 2,
        "particles": 30,
        "iterations": 2,
        "restarts": 1,
        "starts": 1,
    }

    bvh: str = setting(BUNDLED, "BVH file whose frames are rendered", path="file")
    frames: int = setting(80, "frames taken evenly from the BVH", ge=1, le=10000)
    noise_deg: float = setting(
        30.0, "uniform start noise on every joint angle, degrees", ge=0, le=90
    )
    particles: int = setting(150, "particles per part", ge=2, le=5000)
    iterations: int = setting(6, "iterations per annealing run", ge=1, le=100)
    restarts: int = setting(2, "annealing runs (the proposal: 6 iterations, twice)", ge=1, le=20)
    starts: int = setting(
        4,
        "independent searches (a batch of particle BP runs with different draws); per frame "
        "the one whose rendering explains the images best is kept",
        ge=1,
        le=64,
    )
    cameras: int = setting(1, "cameras on a circle around the figure", ge=1, le=16)
    camera: str = setting("orthographic", "camera model", choices=CAMERAS)
    azimuth_deg: float = setting(
        90.0, "camera 0's direction around the vertical, degrees", ge=-360, le=360
    )
    cues: list[str] = setting(
        ["silhouette", "edges", "intensity"], "observation cues", choices=CUES, min_length=1
    )
    intensity_weight: float = setting(
        0.05, "nats per pixel of the intensity cue (colour distance / 2 sigma^2)", gt=0, le=100
    )
    intensity_two_way: bool = setting(
        True,
        "the intensity cue scores a part's colour cost less that of the rest it covers up "
        "(False: its own cost only, so hiding behind another part is free)",
    )
    limits: str = setting(
        "",
        "joint-angle limits on the kinematic edges: a bundled limits name (cmu_cgspeed, "
        "cmu_daz) or a limits file; empty: none",
    )
    polish: bool = setting(False, "gradient polish of the BP estimate on the soft renderer")
    annealing: bool = setting(True, "anneal the connections and the proposal kernels")
    smooth: bool = setting(False, "bilinear reads of the silhouette and edge maps")
    kernel_end: float = setting(
        0.05, "the proposal kernels' final multiplier (start: 2 cm, 0.5 rad)", gt=0, le=1
    )
    occlusion: bool = setting(True, "score parts against the rest of the body (False: alone)")
    temporal: bool = setting(
        False, "temporal edges between frames (the frames are consecutive then)"
    )
    proposal: str = setting(
        "mixture",
        "particle proposal (mixture: neighbours propose through the connections; own: BPMC)",
        choices=("mixture", "own"),
    )


def _ring(cfg: NbpSingleImageConfig, dtype=torch.float32) -> CameraRig:
    """Cameras on a horizontal half circle looking at the origin (world y up)."""
    ks, rs, ts = [], [], []
    for c in range(cfg.cameras):
        # evenly over a half circle: opposite orthographic views would see the same depth
        a = math.radians(cfg.azimuth_deg) + math.pi * c / cfg.cameras
        fwd = torch.tensor([-math.sin(a), 0.0, -math.cos(a)])  # from the eye to the origin
        right = torch.linalg.cross(fwd, torch.tensor([0.0, 1.0, 0.0]))
        down = torch.linalg.cross(fwd, right)
        r = torch.stack([right, down, fwd])
        rs.append(r)
        ts.append(torch.tensor([0.0, 0.0, 5.0]))  # the origin 5 m ahead of every camera
        f = PX_PER_M if cfg.camera == "orthographic" else FOCAL
        ks.append(torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]]))
    n = cfg.cameras
    return CameraRig(
        torch.stack(ks).to(dtype),
        torch.stack(rs).to(dtype),
        torch.stack(ts).to(dtype),
        torch.zeros(n, 5, dtype=dtype),
        torch.tensor([[W, H]] * n, dtype=dtype),
        [f"cam{c}" for c in range(n)],
        orthographic=cfg.camera == "orthographic",
    )


def _part_colours(parts: int) -> Tensor:
    """``(P, 3)`` in [0, 1]: the parts' colours of the rendered images (motion.draw's)."""
    return torch.from_numpy(PART_COLOURS[:parts].astype(np.float32) / 255)


def _postures(cfg: NbpSingleImageConfig, g: torch.Generator):
    """The spec, truth and start part poses (T, P, 7), each frame centred at the origin."""
    bvh = read_bvh(cfg.bvh)
    skeleton = Skeleton.from_bvh(bvh)
    model = BodyModel.from_skeleton(skeleton)
    motion = torch.from_numpy(bvh.motion_frames()).to(torch.float64)
    if cfg.frames > motion.shape[0]:
        raise ConfigError(
            f"frames must be <= {motion.shape[0]} (the BVH's frames); got {cfg.frames}"
        )
    rot, root = local_rotations(skeleton, motion, bvh.channels)
    fk = forward_kinematics(skeleton, rot, root)
    spec = BodySpec.from_motion(skeleton, model, fk, limits=cfg.limits or None)
    step = 1 if cfg.temporal else max(1, motion.shape[0] // cfg.frames)
    frames = torch.arange(cfg.frames) * step
    rot, root = rot[frames], root[frames]
    truth = spec.poses(model, skeleton, forward_kinematics(skeleton, rot, root))
    noise = (
        torch.rand(len(frames), skeleton.num_joints, 3, generator=g, dtype=torch.float64) * 2 - 1
    )
    moved = torch.zeros(skeleton.num_joints, 1, dtype=torch.float64)
    moved[spec.frame_joints] = 1.0
    moved[0] = 0.0  # the root's orientation is the global pose, not a joint angle
    noisy = rot @ euler_to_matrix(noise * moved * math.radians(cfg.noise_deg), "ZYX")
    start = spec.poses(model, skeleton, forward_kinematics(skeleton, noisy, root))
    centre = spec.landmarks(truth).reshape(len(frames), -1, 3).mean(1)
    truth[..., :3] -= centre[:, None]
    start[..., :3] -= centre[:, None]
    return spec, truth.float(), start.float()


def _observe(
    spec: BodySpec, rig: CameraRig, truth: torch.Tensor, g: torch.Generator | None = None
) -> Observation:
    """What cameras see of the true postures: silhouettes, part-coloured images, the
    distance to the images' Canny edges (motion.features, as on a video), and 2-D joints
    (every part end, with ``KEYPOINT_NOISE_PX`` of Gaussian noise: a detector's)."""
    colours = _part_colours(spec.num_parts)
    seg = spec.landmarks(truth)  # (T, P, 2, 3)
    parts = project_parts(rig, seg, spec.shapes.radii.float())  # (T, C, P, ...)
    sil = silhouette(parts, H, W).float()  # (T, C, H, W)
    labels, _ = label_map(parts, H, W)
    image = render_intensity(labels, colours, 0.5)  # (T, C, 3, H, W)
    t, c = sil.shape[:2]
    flat = image.reshape(t * c, 3, H, W)
    dist = distance_to_edges(edges(flat)).reshape(t, c, H, W)
    dist = torch.where(torch.isfinite(dist), dist, torch.full_like(dist, 1e3))
    ends, _ = rig.project(seg.flatten(-3, -2))  # (T, C, 2P, 2): every part's two ends
    noise = torch.randn(ends.shape, generator=g, dtype=ends.dtype) * KEYPOINT_NOISE_PX
    keypoints = torch.cat([ends + noise, torch.ones_like(ends[..., :1])], -1)
    return Observation(sil[None], dist[None], image[None], keypoints[None])


def _cues(cfg: NbpSingleImageConfig, spec: BodySpec) -> list:
    colours = _part_colours(spec.num_parts)
    make = {
        "silhouette": lambda: Silhouette(1.0, 1.0, smooth=cfg.smooth),
        "edges": lambda: Edges(0.2, smooth=cfg.smooth),
        "intensity": lambda: Intensity(
            colours, cfg.intensity_weight, replaces_rest=cfg.intensity_two_way
        ),
        "joints": lambda: Joints2D(torch.arange(2 * spec.num_parts).reshape(-1, 2), 1.0, 4.0),
    }
    return [make[c]() for c in cfg.cues]


def _posture_settings(cfg: NbpSingleImageConfig) -> PostureSettings:
    """The posture solver's settings: the config's search; the start spread and the
    proposal kernels' spreads (2 cm, 0.5 rad: kernel_end's doc) at :class:`PostureSettings`'
    defaults."""
    return PostureSettings(
        particles=cfg.particles,
        iterations=cfg.iterations,
        restarts=cfg.restarts,
        searches=cfg.starts,
        kernel_end=cfg.kernel_end,
        annealing=cfg.annealing,
        proposal=cfg.proposal,
        polish=cfg.polish,
    )


def _errors(spec: BodySpec, rig: CameraRig, truth: torch.Tensor, poses: torch.Tensor):
    """E_2D (camera 0) and E_3D per frame: mean landmark distance / figure height."""
    est, ref = spec.landmarks(poses).flatten(-3, -2), spec.landmarks(truth).flatten(-3, -2)
    e3 = _e3d(est, ref)
    uv, _ = rig.project(est)
    uv_ref, _ = rig.project(ref)
    h2 = uv_ref[:, 0, :, 1].amax(-1) - uv_ref[:, 0, :, 1].amin(-1)
    e2 = (uv[:, 0] - uv_ref[:, 0]).norm(dim=-1).mean(-1) / h2
    return e2.double(), e3.double()


def _e3d_depth_oracle(spec: BodySpec, rig: CameraRig, truth: Tensor, poses: Tensor) -> Tensor:
    """E_3D per frame once every part's depth flip in camera 0 and the body's depth are set
    right (:func:`motion.body.ambiguity.resolve_depth_flips`): what is left when what one
    orthographic view cannot see is given."""
    ref = spec.landmarks(truth)
    est = resolve_depth_flips(spec.parents, spec.landmarks(poses), ref, rig.R[0, 2])
    return _e3d(est.flatten(-3, -2), ref.flatten(-3, -2)).double()


def _e3d(est: Tensor, ref: Tensor) -> Tensor:
    """Eq. 37 per frame: ``(T, L, 3)`` landmarks -> ``(T,)`` mean distance / height."""
    height = ref[..., 1].amax(-1) - ref[..., 1].amin(-1)  # (T,) metres
    return (est - ref).norm(dim=-1).mean(-1) / height


def run(cfg: NbpSingleImageConfig):
    g = torch.Generator().manual_seed(cfg.seed)
    spec, truth, start = _postures(cfg, g)
    rig = _ring(cfg)
    detector = torch.Generator().manual_seed(cfg.seed + 1)  # apart from the search's draws
    obs = _observe(spec, rig, truth, detector)
    t, p = truth.shape[:2]
    shapes = PartShapes(spec.shapes.axis.float(), spec.shapes.radii.float())
    unary = BodyObservation(shapes, rig, obs, cues=_cues(cfg, spec), occlusion=cfg.occlusion)
    it = cfg.iterations
    graph = body_graph(
        spec,
        t,
        [(torch.arange(t * p), unary)],
        Connections(
            pos_std=0.02,
            rot_std=1.0,
            schedule=anneal_schedule(0.25, it, cfg.annealing),
            limits=spec.limits,
        ),
        Temporal() if cfg.temporal else None,
    )
    note(
        f"nbp_single_image: {t} frames x {p} parts x {cfg.particles} particles, "
        f"{cfg.restarts} x {it} iterations, {cfg.starts} searches"
    )
    colours = _part_colours(p) if "intensity" in cfg.cues else None
    images = Images(spec, rig, obs, colours, cfg.intensity_weight)
    t0 = time.perf_counter()
    estimate = solve_posture(graph, start, _posture_settings(cfg), g, images).poses
    seconds = time.perf_counter() - t0
    e2_init, e3_init = _errors(spec, rig, truth, start)
    e2, e3 = _errors(spec, rig, truth, estimate)
    metrics = {
        "e2d_init_mean": float(e2_init.mean()),
        "e2d_mean": float(e2.mean()),
        "e3d_init_mean": float(e3_init.mean()),
        "e3d_mean": float(e3.mean()),
        "e3d_depth_oracle_mean": float(_e3d_depth_oracle(spec, rig, truth, estimate).mean()),
        "sec_per_frame": seconds / t,
    }
    columns = {
        "frame": np.arange(t),
        "e2d_init": e2_init.numpy(),
        "e2d": e2.numpy(),
        "e3d_init": e3_init.numpy(),
        "e3d": e3.numpy(),
    }
    sheet = _sheet(spec, rig, obs, truth, start, estimate)
    return metrics, columns, {"columns": columns, "sheet": sheet}


def _overlay(spec, rig, obs, poses, frame) -> np.ndarray:
    grey = (obs.silhouette[0, frame, 0].numpy() * 90 + 140).astype(np.uint8)
    image = np.repeat(grey[..., None], 3, -1)
    parts = project_parts(rig, spec.landmarks(poses[frame]), spec.shapes.radii.float())
    return draw_parts(image, parts.__class__(parts.ends[0], parts.radii[0], parts.depth[0]))


def _sheet(spec, rig, obs, truth, start, estimate, shown: int = 6) -> np.ndarray:
    """Rows: truth, start, result; columns: frames evenly spaced (camera 0)."""
    t = truth.shape[0]
    frames = sorted({round(i * (t - 1) / max(1, shown - 1)) for i in range(min(shown, t))})
    tiles, captions = [], []
    for label, poses in (("truth", truth), ("start", start), ("result", estimate)):
        for f in frames:
            tiles.append(_overlay(spec, rig, obs, poses, f))
            captions.append(f"{label} {f}")
    return contact_sheet(tiles, columns=len(frames), captions=captions)


def plot_errors(path, x, columns: dict, xlabel: str, title: str, marker: str = "") -> None:
    """Two panels, E_2D and E_3D (Eqs. 36-37) of the start and of the result against ``x``
    (``columns`` holds ``e2d_init``, ``e2d``, ``e3d_init``, ``e3d``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6), dpi=100)
    for ax, name, label in ((axes[0], "e2d", "E_2D (Eq. 36)"), (axes[1], "e3d", "E_3D (Eq. 37)")):
        ax.plot(x, columns[f"{name}_init"], marker + "-", color="0.6", lw=1, label="start")
        ax.plot(x, columns[name], marker + "-", color="C3", lw=1.5, label="particle BP")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(f"{label}, fraction of height")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot(path, data, title: str) -> None:
    c = data["columns"]
    plot_errors(path, c["frame"], c, "frame", title)
    cv2.imwrite(str(Path(path).with_name("contact_sheet.png")), data["sheet"][..., ::-1])
