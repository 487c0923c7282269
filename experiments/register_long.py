"""Registration of a long video: a 5-minute student (25 fps, 7,500 frames) against a 120 Hz
reference of the same length (issue: registration engine at scale; the proposal's Section 6,
variation 3, and DESIGN.md's "coarse-to-fine in time so that long sequences stay
near-linear in cost").

The reference is built by chaining the bundled walk (:func:`chain_walk`): the clip's loop
(its first frames up to the one whose posture best matches frame 0, two gait cycles) is
repeated, each copy moved and turned about the vertical so that it starts where the previous
copy would have gone on -- root position and heading carry over, no jump at the seams. A
straight 5-minute walk would cover ~400 m, out of any static camera's view, so the chained
path is also bent onto a circle (``radius_m``): the heading turns in proportion to the
distance walked and the root's horizontal steps are turned with it (a walk round a track;
the feet slide by the few degrees the body turns per step). The chain is written as a BVH
(:func:`motion.bvh.write_bvh`, with the clip's reference-pose frame 0 kept in front so that
:mod:`motion.synth` and :meth:`Reference.from_bvh` drop it alike), and the student is
rendered from it by :func:`motion.synth.synthesize`: time-warped (its warp), lightly
re-articulated, one static camera, 160 x 120 pixels.

:func:`motion.registration.register` then recovers C, T and A with settings cheap enough for
the targets (stage 1 under 5 minutes, the whole registration under 1 hour, peak memory under
8 GB on 2 cores; see the config's comment).

The copies are the same motion, so the reference's root-normalised postures (what the images
show) repeat exactly every loop: C is observable only up to whole loops. ``c_phase_err_mean``
(and ``_stage1``) is therefore the error modulo the loop, ``|C - C_true|`` folded onto
``[0, L / 2]`` -- what any registration can be asked for -- while ``c_err_mean`` also counts
the copy it landed on.

Metrics: ``c_err_mean``, ``c_err_mean_stage1``, ``c_err_max``, ``c_phase_err_mean``,
``c_phase_err_mean_stage1``, ``c_phase_within5`` (fraction of frames within 5 reference
frames of the truth modulo the loop) (reference frames),
``a_err_deg_mean`` (the joints the parts drive), ``t_rot_err_deg_mean``,
``silhouette_iou_mean`` -- the definitions of :mod:`experiments.register_synthetic`, whose
truth and metric helpers are used. Timings (timings.json): ``sec_stage1``, ``sec_total``
(the whole :func:`register` call), ``peak_rss_mb`` (this process's peak resident memory,
``getrusage``, synthesis included), ``peak_rss_mb_inputs`` (the same before
:func:`register`: what synthesis and the features took; when ``peak_rss_mb`` is larger, the
registration set the peak), ``sec_stages23``, ``sec_synthesize``.
"""

from __future__ import annotations

import math
import resource
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from kornia.geometry.conversions import (
    axis_angle_to_rotation_matrix,
    rotation_matrix_to_axis_angle,
)
from torch import Tensor

from experiments.config import ConfigError, ExperimentConfig
from experiments.progress import note, progress
from experiments.register_synthetic import synthetic_truth
from experiments.stick_time import BUNDLED
from motion.bvh import BVH, read_bvh, write_bvh
from motion.geometry import matrix_to_euler, rotation_about_y
from motion.kinematics import Skeleton, local_rotations
from motion.metrics import rotation_angle_error_deg
from motion.registration import Reference, RegistrationSettings, register
from motion.registration.approximate import Stage1Settings
from motion.registration.inputs import features_from_sequence
from motion.registration.refine import RefineSettings
from motion.runtime import release_freed_memory
from motion.settings import setting
from motion.synth import SynthConfig, synthesize

TIMINGS = (
    "sec_stage1",
    "sec_total",
    "peak_rss_mb",
    "peak_rss_mb_inputs",
    "sec_stages23",
    "sec_synthesize",
)


@dataclass
class RegisterLongConfig(ExperimentConfig):
    """Fields of ``experiments/configs/register_long.yaml``."""

    NAME = "register_long"
    TINY_DOC = "a quick run (a few seconds of video, few particles)"
    TINY: ClassVar[dict] = {
        "minutes": 0.06,
        "particles": 16,
        "iterations": 1,
        "restarts": 1,
        "rounds": 1,
        "window": 12,
        "yaw_starts": 4,
        "final_yaw_starts": 4,
    }

    reference: str = setting(BUNDLED, "the clip the reference is chained from (BVH)", path="file")
    minutes: float = setting(5.0, "video length, minutes (the reference as long)", gt=0, le=60)
    fps: float = setting(25.0, "video frame rate, Hz", gt=0, le=240)
    radius_m: float = setting(
        2.0, "radius of the circle the chained walk is bent onto, metres (0: straight)", ge=0
    )
    warp_seed: int = setting(0, "seed of the synthetic student (time warp, articulation)", ge=0)
    warp: float = setting(0.3, "largest relative change of playback speed", ge=0, lt=1)
    articulation: dict[str, float] = setting(
        {"LeftLeg": 10.0, "RightForeArm": 10.0},
        "joint -> largest articulation offset of the student, degrees (motion synth's)",
        ge=0,
        le=90,
    )
    size: list[int] = setting([160, 120], "image width, height in pixels", length=2, ge=32)
    focal_px: float = setting(230.0, "focal length, pixels", gt=0)
    camera_distance_m: float = setting(
        7.0, "the camera's distance from the centre of the walk, metres", gt=0
    )
    image: bool = setting(True, "give the colour frames (the intensity cue) to the engine")
    keypoints: bool = setting(False, "give noisy 2-D joints as an extra observation")
    # stage 1
    yaw_starts: int = setting(8, "stage 1: yaw starts screened per pair", ge=1, le=64)
    refine_starts: int = setting(2, "stage 1: starts refined per pair", ge=1, le=64)
    stage1_iterations: int = setting(5, "stage 1: LM iterations per refined start", ge=1)
    anchor_stride: int = setting(8, "stage 1: every n-th pair of a band from all starts", ge=1)
    warm_iterations: int = setting(3, "stage 1: LM iterations of the other pairs", ge=1)
    final_yaw_starts: int = setting(8, "stage 1: yaw starts of the final T per frame", ge=1)
    final_refine_starts: int = setting(2, "stage 1: starts refined for the final T", ge=1)
    final_iterations: int = setting(20, "stage 1: LM iterations of the final T", ge=1)
    smooth_rounds: int = setting(1, "stage 1: warm-started rounds of the final T", ge=0)
    beam: int = setting(
        7, "stage 1: the alignment's tracking half-width, reference frames (0: none)", ge=0
    )
    prune: float = setting(
        1.0, "stage 1: a beam for the next best partial path within this (threshold units)", ge=0
    )
    # stages 2-3
    particles: int = setting(50, "particles per part (stages 2-3)", ge=2, le=2000)
    iterations: int = setting(3, "particle BP iterations per run", ge=1, le=50)
    restarts: int = setting(1, "annealing runs", ge=1, le=10)
    rounds: int = setting(2, "stage 3: at most this many rounds of C", ge=1, le=10)
    window: int = setting(24, "stages 2-3: video frames per window", ge=4)
    overlap: int = setting(4, "stages 2-3: frames shared by neighbouring windows", ge=0)
    refine_c: bool = setting(True, "stage 3: refine C through the body graph")
    threads: int = setting(
        1,
        "torch threads of this process (0: torch's default); on a machine shared with other "
        "busy processes more threads than free cores stall at every parallel region",
        ge=0,
    )


# -- the chained reference ---------------------------------------------------------------------
def heading(rotation: Tensor) -> Tensor:
    """The heading of root rotations ``(..., 3, 3)``: the yaw (radians, about +Y) of the
    root's +Z axis projected on the floor, ``(...,)``."""
    return torch.atan2(rotation[..., 0, 2], rotation[..., 2, 2])


def loop_end(rotations: Tensor, first: float = 0.5) -> int:
    """The frame ``f`` (in the last ``1 - first`` of the clip) whose joint rotations (every
    joint but the root) are closest to frame 0's: frames ``0 .. f - 1`` repeat without a
    posture jump. ``rotations`` ``(F, J, 3, 3)``."""
    dist = (rotations[:, 1:] - rotations[:1, 1:]).flatten(1).norm(dim=1)
    lo = max(1, int(first * rotations.shape[0]))
    return lo + int(dist[lo:].argmin())


def _root_columns(bvh: BVH) -> tuple[list[int], list[int], str]:
    chans = bvh.channels[0]
    pos = (
        [chans.index(f"{a}position") for a in "XYZ"]
        if all(f"{a}position" in chans for a in "XYZ")
        else None
    )
    rot = [i for i, c in enumerate(chans) if c.endswith("rotation")]
    if pos is None or len(rot) != 3:
        raise ConfigError(
            f"{bvh.path}: the root must have 3 position and 3 rotation channels to be chained; "
            f"got {chans}"
        )
    return pos, rot, "".join(chans[i][0] for i in rot)


def _slerp(a: Tensor, b: Tensor, w: Tensor) -> Tensor:
    """Rotations ``(N, ..., 3, 3)`` from ``a`` (``w = 0``) to ``b`` (``w = 1``) along the
    geodesic, ``w`` ``(N,)``."""
    rel = a.transpose(-1, -2) @ b
    flat = rotation_matrix_to_axis_angle(rel.reshape(-1, 3, 3).contiguous())
    lead = rel.shape[:-2]
    scaled = flat.reshape(*lead, 3) * w.reshape(-1, *([1] * (len(lead) - 1)), 1)
    return a @ axis_angle_to_rotation_matrix(scaled.reshape(-1, 3)).reshape(*lead, 3, 3)


def chain_walk(
    path: str | Path, num_frames: int, radius_m: float = 0.0, blend: int = 40
) -> tuple[BVH, dict[str, object]]:
    """The clip at ``path`` chained to ``num_frames`` motion frames (module docstring).

    The loop is the clip's frames ``0 .. L - 1`` (``L = loop_end``); its first ``blend``
    frames are cross-faded from the clip's continuation (frames ``L, L + 1, ...``, moved
    back by the loop's rigid displacement) to its own frames, so that the loop's frame 0 is
    exactly what follows frame ``L - 1``: the posture, root height and tilt run on without a
    jump. Copy ``k`` of the loop is turned by ``k`` times the clip's heading change over the
    loop and moved so that its frame 0 lies where frame ``L`` of copy ``k - 1`` would be.
    With ``radius_m > 0`` the whole path is then bent: the heading turns by ``distance
    walked / radius_m`` (the root's horizontal steps turned with it), a walk round a circle
    of about that radius.

    Returns:
        the chained :class:`BVH` (the clip's frame 0 in front when it is a converter's
        reference pose, so ``motion_frames()`` has ``num_frames`` rows), and facts for
        reports and tests: ``loop`` (L), ``seams`` (motion-frame index of each copy's first
        frame after the first copy), ``metres_per_unit``.
    """
    bvh = read_bvh(path)
    skeleton = Skeleton.from_bvh(bvh)
    clip = torch.from_numpy(bvh.motion_frames()).to(torch.float64)
    rot, _ = local_rotations(skeleton, clip, bvh.channels)  # (F, J, 3, 3), root's included
    loop = loop_end(rot)
    pos_cols, _, _ = _root_columns(bvh)
    unit = skeleton.metres_per_unit
    pos = clip[:, pos_cols]  # (F, 3) file units
    floor = torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)
    psi = heading(rot[:, 0])
    turn = psi[loop] - psi[0]
    step = (pos[loop] - pos[0]) * floor
    # cross-fade the loop's first frames from the continuation, moved back by one loop
    n = min(blend, clip.shape[0] - loop)
    if n > 0:
        j = torch.arange(n)
        back = rotation_about_y(-turn)
        cont_pos = (back @ ((pos[loop + j] - pos[loop]) * floor)[..., None]).squeeze(-1)
        cont_pos = cont_pos + pos[0] * floor + pos[loop + j] * (1 - floor)
        cont_rot = rot[loop + j].clone()
        cont_rot[:, 0] = back @ cont_rot[:, 0]
        u = j.double() / n
        w = u * u * (3 - 2 * u)  # smoothstep: 0 at the seam, 1 where the clip takes over
        rot = rot.clone()
        pos = pos.clone()
        rot[:n] = _slerp(cont_rot, rot[:n], w)
        pos[:n] = cont_pos + w[:, None] * (pos[:n] - cont_pos)
    copies = math.ceil(num_frames / loop)
    turns = rotation_about_y(torch.arange(copies, dtype=torch.float64) * turn)  # (copies, 3, 3)
    starts = torch.zeros(copies, 3, dtype=torch.float64)
    for i in range(1, copies):  # each copy starts where the previous would go on
        starts[i] = starts[i - 1] + turns[i - 1] @ step
    rel = pos[:loop] - pos[0] * floor
    new_pos = (turns[:, None] @ rel[None, :, :, None]).squeeze(-1) + starts[:, None]
    new_rot = rot[None, :loop].expand(copies, -1, -1, -1, -1).clone()
    new_rot[:, :, 0] = turns[:, None] @ rot[None, :loop, 0]
    new_pos = new_pos.reshape(-1, 3)[:num_frames]
    new_rot = new_rot.reshape(-1, *rot.shape[1:])[:num_frames]
    if radius_m > 0:
        flat = new_pos * floor
        d = flat.diff(dim=0)  # (F - 1, 3) horizontal steps
        walked = torch.cat([torch.zeros(1, dtype=d.dtype), (d.norm(dim=-1) * unit).cumsum(0)])
        bend = rotation_about_y(walked / radius_m)  # (F, 3, 3)
        steps = (bend[1:] @ d[..., None]).squeeze(-1)
        new_pos = torch.cat([flat[:1], flat[:1] + steps.cumsum(0)]) + new_pos * (1 - floor)
        new_rot[:, 0] = bend @ new_rot[:, 0]
    motion = clip[torch.arange(num_frames) % loop].clone()
    motion[:, pos_cols] = new_pos
    col = 0
    for joint, chans in enumerate(bvh.channels):
        cols = [col + i for i, c in enumerate(chans) if c.endswith("rotation")]
        if cols:
            order = skeleton.rotation_orders[joint]
            angles = matrix_to_euler(new_rot[:, joint], order)
            motion[:, torch.tensor(cols)] = torch.rad2deg(angles)
        col += len(chans)
    motion = motion.numpy()
    if bvh.has_reference_pose():
        motion = np.concatenate([bvh.motion[:1], motion])
    chained = BVH(
        path=Path(path),
        names=list(bvh.names),
        parents=bvh.parents.copy(),
        offsets=bvh.offsets.copy(),
        channels=[list(c) for c in bvh.channels],
        end_sites=dict(bvh.end_sites),
        frame_time=bvh.frame_time,
        motion=motion,
    )
    seams = list(range(loop, num_frames, loop))
    return chained, {"loop": loop, "seams": seams, "metres_per_unit": unit}


# -- the run -----------------------------------------------------------------------------------
def _settings(cfg: RegisterLongConfig) -> RegistrationSettings:
    stage1 = Stage1Settings(
        yaw_starts=cfg.yaw_starts,
        refine_starts=min(cfg.refine_starts, cfg.yaw_starts),
        iterations=cfg.stage1_iterations,
        anchor_stride=cfg.anchor_stride,
        warm_iterations=cfg.warm_iterations,
        final_yaw_starts=cfg.final_yaw_starts,
        final_refine_starts=min(cfg.final_refine_starts, cfg.final_yaw_starts),
        final_iterations=cfg.final_iterations,
        smooth_rounds=cfg.smooth_rounds,
        beam=cfg.beam,
        prune=cfg.prune,
    )
    if cfg.overlap >= cfg.window:
        raise ConfigError(f"overlap must be < window ({cfg.window}); got {cfg.overlap}")
    refine = RefineSettings(
        particles=cfg.particles,
        iterations=cfg.iterations,
        restarts=cfg.restarts,
        rounds=cfg.rounds,
        window=cfg.window,
        overlap=cfg.overlap,
        refine_c=cfg.refine_c,
        band=min(12, (cfg.particles - 1) // 2),
    )
    return RegistrationSettings(stage1, refine, scale=None, seed=cfg.seed)


def loop_phase_error(error: Tensor, loop: int) -> Tensor:
    """``C - C_true`` ``(T',)`` (reference frames) modulo a loop of ``loop`` frames, folded
    onto ``[0, loop / 2]``: the error of a periodic reference's posture, ``(T',)`` float64."""
    e = error.double()
    return (torch.remainder(e + loop / 2, loop) - loop / 2).abs()


def peak_rss_mb() -> float:
    """This process's peak resident memory so far, MB (``ru_maxrss``: KiB on Linux, bytes
    on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024


def run(cfg: RegisterLongConfig):
    """The experiment (module docstring) with ``cfg.threads`` torch threads, restored after."""
    before = torch.get_num_threads()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)  # process-wide: experiments set it, never motion/
    try:
        return _run(cfg)
    finally:
        torch.set_num_threads(before)


def _run(cfg: RegisterLongConfig):
    num_video = max(2, round(cfg.minutes * 60 * cfg.fps))
    rate = read_bvh(cfg.reference).frame_rate
    num_ref = math.ceil((num_video - 1) * rate / cfg.fps) + 1  # synthesize rounds down
    t0 = time.perf_counter()
    chained, facts = chain_walk(cfg.reference, num_ref, cfg.radius_m)
    synth = SynthConfig(
        fps=cfg.fps,
        warp=cfg.warp,
        articulation=dict(cfg.articulation),
        cameras=1,
        size=list(cfg.size),
        focal_px=cfg.focal_px,
        camera_distance_m=cfg.camera_distance_m,
        seed=cfg.warp_seed,
    )
    with tempfile.TemporaryDirectory() as tmp:
        path = write_bvh(chained, Path(tmp) / "chained.bvh")
        seq = synthesize(path, synth)
        reference = replace(Reference.from_bvh(path), name=f"{cfg.reference} chained")
    if seq.meta["num_video_frames"] != num_video:
        raise ConfigError(
            f"expected {num_video} video frames from {num_ref} reference frames; synthesize "
            f"made {seq.meta['num_video_frames']}"
        )
    truth = synthetic_truth(seq, reference, None)
    # the colour frames stay uint8 (the engine converts them a window at a time): float32
    # images of every frame would be 1.7 GB of the 5-minute video's memory
    video = features_from_sequence(
        seq, keypoints=cfg.keypoints, image=cfg.image, image_dtype=torch.uint8
    )
    del seq  # the rendered arrays: the features hold what the engine reads
    release_freed_memory()
    sec_synth = time.perf_counter() - t0
    peak_inputs = peak_rss_mb()
    note(
        f"register_long: {num_video} video frames, {reference.num_frames} reference frames "
        f"({len(facts['seams'])} seams, loop {facts['loop']} frames); synthesized in "
        f"{sec_synth:.0f} s, peak {peak_inputs:.0f} MB"
    )
    t0 = time.perf_counter()
    result = register(reference, video, settings=_settings(cfg), progress=progress, log=note)
    seconds = time.perf_counter() - t0

    driven = sorted(set(reference.spec.frame_joints.tolist()) - {0})
    a_true = reference.rotations[truth.C].transpose(-1, -2) @ truth.local
    a_err = rotation_angle_error_deg(a_true[:, driven], result.A[:, driven])  # (T', J')
    t_rot = rotation_angle_error_deg(truth.rotation, result.T_rotation)
    c_err = (result.C - truth.C).abs().double()
    c_err1 = (result.C_stage1 - truth.C).abs().double()
    phase = loop_phase_error(result.C - truth.C, facts["loop"])
    phase1 = loop_phase_error(result.C_stage1 - truth.C, facts["loop"])
    metrics = {
        "c_err_mean": float(c_err.mean()),
        "c_err_mean_stage1": float(c_err1.mean()),
        "c_err_max": float(c_err.max()),
        "c_phase_err_mean": float(phase.mean()),
        "c_phase_err_mean_stage1": float(phase1.mean()),
        "c_phase_within5": float((phase <= 5).double().mean()),
        "a_err_deg_mean": float(a_err.mean()),
        "t_rot_err_deg_mean": float(t_rot.mean()),
        "silhouette_iou_mean": float(result.fit.mean()),
        "num_video_frames": float(num_video),
        "num_reference_frames": float(reference.num_frames),
        "sec_stage1": result.timings["stage1"],
        "sec_stages23": result.timings["stages23"],
        "sec_total": seconds,
        "sec_synthesize": sec_synth,
        "peak_rss_mb": peak_rss_mb(),
        "peak_rss_mb_inputs": peak_inputs,
    }
    columns = {
        "frame": np.arange(num_video),
        "c_true": truth.C.numpy(),
        "c_stage1": result.C_stage1.numpy(),
        "c": result.C.numpy(),
        "c_err": c_err.numpy(),
        "c_phase_err": phase.numpy(),
        "a_err_deg": a_err.mean(-1).numpy(),
        "t_rot_err_deg": t_rot.numpy(),
        "silhouette_iou": result.fit.numpy(),
    }
    return metrics, columns, {"columns": columns, "fps": cfg.fps}


def plot(path, data, title: str) -> None:
    """Top: true C, stage 1's and the final one over the whole video; bottom: |C - C_true|
    over time (stage 1's and the final one, and the final one modulo the loop), against
    minutes of video."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = data["columns"]
    minutes = np.asarray(c["frame"]) / data["fps"] / 60
    fig, axes = plt.subplots(2, 1, figsize=(11, 6), dpi=100, sharex=True)
    ax = axes[0]
    ax.plot(minutes, c["c_true"], "-", color="0.2", lw=2, label="true C")
    ax.plot(minutes, c["c_stage1"], "--", color="C0", lw=1, label="stage 1")
    ax.plot(minutes, c["c"], "-", color="C3", lw=1, label="stages 2-3")
    ax.set_ylabel("reference frame C(t')")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax = axes[1]
    ax.plot(
        minutes,
        np.abs(np.asarray(c["c_stage1"]) - c["c_true"]),
        color="C0",
        lw=0.6,
        label="stage 1",
    )
    ax.plot(minutes, c["c_err"], color="C3", lw=0.6, label="stages 2-3")
    ax.plot(minutes, c["c_phase_err"], color="C2", lw=0.6, label="stages 2-3, modulo the loop")
    ax.set_xlabel("video time, minutes")
    ax.set_ylabel("|C - C_true|, reference frames")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
