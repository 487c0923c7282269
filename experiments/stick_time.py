"""Temporal correspondence of stick figures (the proposal's Section 5.1.2, Fig. 12).

The 3-D reference is a BVH's 20 body landmarks (``motion.bodyparts`` roles) at 120 Hz; the
2-D input is the same motion through a smooth non-linear time warp (and a frame-rate change),
seen by a perspective camera, with uniform joint noise, optionally with frames 40 %-50 % of
the input replaced by the frames that follow them (the proposal's corruption).
``d(t', t) = (1/n) sum_i ||G X_it - x_it'||^2 / h'^2`` (Eq. 24, normalised by the 2-D
figure height) with ``G`` the best pose for each pair (``motion.pose``); C by the proposal's
DTW, chain Viterbi, and the robust chain (bounded cost, slope prior).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from experiments.config import ConfigError, ExperimentConfig
from experiments.progress import progress
from motion.alignment import chain_align, coarse_to_fine_align, dtw, robust_cost, slope_step_cost
from motion.bodyparts import BodyModel
from motion.bvh import read_bvh
from motion.kinematics import Skeleton, forward_kinematics, local_rotations
from motion.pose import solve_pose
from motion.settings import setting
from motion.synth import time_warp

BUNDLED = "motion/data/cmu_02_01_walk.bvh"


#: the aligners, by the suffix of their metric names
METHODS = ("dtw", "chain", "robust", "c2f", "c2f_robust")
FULL_MATRIX_METHODS = ("dtw", "chain", "robust")


@dataclass
class StickTimeConfig(ExperimentConfig):
    """Fields of ``experiments/configs/stick_time.yaml`` (see experiments/README.md)."""

    NAME = "stick_time"
    TINY_DOC = "a few frames (the first 120 reference frames), for tests"

    bvh: str = setting(BUNDLED, "reference BVH file (120 Hz motion capture)", path="file")
    fps: float = setting(
        25.0, "input frame rate in Hz (the reference's is read from the BVH)", gt=0, le=1000
    )
    warp: float = setting(0.3, "largest relative change of playback speed", ge=0, lt=1)
    noise: float = setting(
        0.018, "uniform 2-D joint noise, a fraction of the 2-D figure height", ge=0, le=1
    )
    corrupt: bool = setting(True, "replace input frames 40-50 % by the frames after them")
    camera_distance: float = setting(
        5.0, "camera distance from the figure's centre, metres", gt=0, le=1000
    )
    max_step: int = setting(12, "S: most reference frames C advances per input frame", ge=1)
    robust_scale: float = setting(
        2.0, "truncation at this many times the median best-match cost", gt=0
    )
    slope_weight: float = setting(0.5, "slope prior weight, in units of the truncation level", ge=0)
    # The camera does not move: after a first robust alignment on Eq. 24, one camera pose is
    # fitted to the matched inlier pairs and the chain methods run on the costs under it
    # (the proposal's DTW always runs on Eq. 24's per-pair poses, as published).
    static_camera: bool = setting(
        True, "fit one camera pose to a first robust alignment's inliers (chain methods)"
    )
    methods: list[str] = setting(
        ["dtw", "chain", "robust"],
        "aligners: dtw, chain, robust on the full cost matrix; c2f and c2f_robust: the chain "
        "and the robust chain coarse-to-fine (Eq. 24 evaluated on demand in a band)",
        choices=METHODS,
        min_length=1,
    )
    full_matrix_max_cells: int = setting(
        5_000_000, "refuse the full cost matrix beyond this many cells (use c2f)", ge=1
    )
    c2f_max_cells: int = setting(
        200_000, "coarse-to-fine: solve directly once a level has at most this many cells", ge=1
    )


def reference_landmarks(path: str) -> tuple[torch.Tensor, float]:
    """The body landmarks of every frame of the BVH file ``path`` ``(T, R, 3)``, metres,
    centred on the mean root landmark, and its frame rate (Hz)."""
    bvh = read_bvh(path)
    skel = Skeleton.from_bvh(bvh)
    motion = bvh.motion_frames()  # without a converter's reference pose
    fk = forward_kinematics(skel, *local_rotations(skel, torch.from_numpy(motion), bvh.channels))
    model = BodyModel.from_skeleton(skel)
    landmarks = model.landmarks(model.skeleton_points(skel, fk))  # (T, R, 3)
    return landmarks - landmarks[:, :1].mean(0, keepdim=True), bvh.frame_rate


def _check_lengths(cfg: StickTimeConfig, num_video: int, num_ref: int, ref_rate: float) -> None:
    """Settings the sequence lengths must allow: enough input frames for the replaced
    stretch, and steps of at most ``max_step`` that can reach the last reference frame."""
    least = 10 if cfg.corrupt else 2
    if num_video < least:
        why = " (for the replaced frames 40-50 %)" if cfg.corrupt else ""
        raise ConfigError(
            f"fps={cfg.fps:g}: {num_video} input frame(s) from {num_ref} reference frames at "
            f"{ref_rate:g} Hz; expected at least {least}{why}: raise fps"
        )
    need = math.ceil((num_ref - 1) / (num_video - 1))
    if cfg.max_step < need:
        raise ConfigError(
            f"max_step={cfg.max_step}: {num_video} input frames cannot reach the last of "
            f"{num_ref} reference frames in steps of at most {cfg.max_step}; expected "
            f"max_step >= {need} (raise max_step or fps)"
        )


def _check_in_front(points: torch.Tensor, distance: float) -> None:
    """Every landmark (camera coordinates ``(..., 3)``, metres) must be in front of the camera."""
    nearest = float(points[..., 2].min())
    if nearest <= 1e-3:
        raise ConfigError(
            f"camera_distance={distance:g}: landmarks reach depth {nearest:.2f} m from the "
            "camera; expected every landmark in front of it (raise camera_distance)"
        )


def run(cfg: StickTimeConfig) -> tuple[dict, dict, dict]:
    """Returns (metrics, per-frame columns, plot data)."""
    g = torch.Generator().manual_seed(cfg.seed)
    ref, ref_rate = reference_landmarks(cfg.bvh)
    if cfg.tiny:
        ref = ref[: min(len(ref), 120)]
    num_ref = ref.shape[0]
    num_video = int((num_ref - 1) * cfg.fps / ref_rate) + 1
    _check_lengths(cfg, num_video, num_ref, ref_rate)
    c_true = time_warp(num_video, num_ref, cfg.warp, g)
    shown = c_true.clone()
    inside = torch.zeros(num_video, dtype=torch.bool)
    if cfg.corrupt:
        lo, hi = int(0.4 * num_video), int(0.5 * num_video)
        shown[lo:hi] = c_true[hi : hi + (hi - lo)]
        inside[lo:hi] = True
    # camera: perspective, looking at the body from the side at camera_distance, random yaw
    yaw = float(torch.rand(1, generator=g)) * 2 * math.pi
    rot = torch.tensor(
        [[math.cos(yaw), 0, math.sin(yaw)], [0, -1.0, 0], [math.sin(yaw), 0, -math.cos(yaw)]],
        dtype=torch.float64,
    )
    t = torch.tensor([0.0, 0.0, cfg.camera_distance], dtype=torch.float64)
    k = torch.tensor([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]], dtype=torch.float64)
    pc = ref[shown] @ rot.T + t
    _check_in_front(pc, cfg.camera_distance)
    x2 = pc[..., :2] / pc[..., 2:] * 800 + torch.tensor([320.0, 240.0], dtype=torch.float64)
    height = float((x2[..., 1].amax(-1) - x2[..., 1].amin(-1)).median())
    x2 = x2 + (torch.rand(x2.shape, generator=g, dtype=torch.float64) * 2 - 1) * cfg.noise * height
    n = ref.shape[1]

    def pair_cost(rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
        """Eq. 24 on demand for video frames ``rows`` (R,) against references ``cols`` (R, W)."""
        rr = rows[:, None].expand_as(cols).reshape(-1)
        res = solve_pose(ref[cols.reshape(-1)], x2[rr], k)
        return (res.cost / height**2).reshape(cols.shape)

    estimates = {}
    full_methods = [m for m in cfg.methods if m in FULL_MATRIX_METHODS]
    if full_methods:
        if num_video * num_ref > cfg.full_matrix_max_cells:
            raise ConfigError(
                f"full_matrix_max_cells={cfg.full_matrix_max_cells}: the full cost matrix has "
                f"{num_video} x {num_ref} cells, more than that: "
                "use methods=[c2f] for long sequences (coarse-to-fine, no full matrix)"
            )
        # Eq. 24 for every (t', t): one batched pose solve per video frame against all references
        cost = torch.empty(num_video, num_ref, dtype=torch.float64)
        for i in progress(range(num_video), "stick_time: cost matrix rows"):
            res = solve_pose(ref, x2[i].expand(num_ref, n, 2), k)
            cost[i] = res.cost / height**2
    slope = (num_ref - 1) / max(num_video - 1, 1)

    def coarse_to_fine(cost_fn, robust: bool) -> torch.Tensor:
        """The chain or (``robust``) the robust chain, coarse-to-fine: no full matrix."""
        extra = {}
        if robust:  # the robust chain's cost and prior, in units of the truncation level
            extra = {
                "robust": "truncate",
                "robust_scale": cfg.robust_scale,
                "step_cost": slope_step_cost(cfg.max_step, slope, cfg.slope_weight).double(),
            }
        return coarse_to_fine_align(
            cost_fn,
            num_video,
            num_ref,
            cfg.max_step,
            fix_start=True,
            fix_end=True,
            max_cells=cfg.c2f_max_cells,
            **extra,
        ).path[0]

    def robust_chain(cost: torch.Tensor) -> torch.Tensor:
        """The robust chain (truncated cost, slope prior) on a full cost matrix."""
        threshold = max(cfg.robust_scale * float(cost.amin(-1).median()), 1e-12)
        truncated = robust_cost(cost, threshold=threshold)
        prior = slope_step_cost(cfg.max_step, slope, cfg.slope_weight * threshold).double()
        return chain_align(
            truncated, cfg.max_step, fix_start=True, fix_end=True, step_cost=prior
        ).path[0]

    def under_one_camera(path: torch.Tensor, matched: torch.Tensor):
        """Costs under one camera pose fitted to the matched pairs that fit well (below
        robust_scale x their median): the reference projected once, then ``(rows, cols)``
        costs are mean squared pixel distances like Eq. 24's, without a pose per pair."""
        inliers = matched <= cfg.robust_scale * matched.median()
        camera = solve_pose(ref[path[inliers]].reshape(1, -1, 3), x2[inliers].reshape(1, -1, 2), k)
        pc = ref @ camera.R[0].T + camera.t[0]
        uv = pc[..., :2] / pc[..., 2:] * 800 + torch.tensor([320.0, 240.0], dtype=torch.float64)

        def cost_fn(rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
            d = (x2[rows][:, None] - uv[cols]).square().sum(-1).mean(-1)
            return d / height**2

        return cost_fn

    if full_methods and cfg.static_camera:
        first = robust_chain(cost)
        cost_fn = under_one_camera(first, cost[torch.arange(num_video), first])
        chain_cost = cost_fn(torch.arange(num_video), torch.arange(num_ref).expand(num_video, -1))
    elif full_methods:
        chain_cost = cost
    for method in ("c2f", "c2f_robust"):
        if method not in cfg.methods:
            continue
        fn = pair_cost
        if cfg.static_camera:
            first = coarse_to_fine(pair_cost, robust=True)
            fn = under_one_camera(first, pair_cost(torch.arange(num_video), first[:, None])[:, 0])
        estimates[method] = coarse_to_fine(fn, robust=method == "c2f_robust")
    if "dtw" in cfg.methods:
        estimates["dtw"] = dtw(cost).choice
    if "chain" in cfg.methods:
        estimates["chain"] = chain_align(
            chain_cost, cfg.max_step, fix_start=True, fix_end=True
        ).path[0]
    if "robust" in cfg.methods:
        estimates["robust"] = robust_chain(chain_cost)
    metrics: dict[str, float] = {}
    columns = {
        "t_video": np.arange(num_video),
        "c_true": c_true.numpy(),
        "replaced": inside.numpy().astype(int),
    }
    for name, est in estimates.items():
        err = (est - c_true).abs().double()
        metrics[f"c_err_mean_{name}"] = float(err.mean())
        metrics[f"c_err_outside_mean_{name}"] = float(err[~inside].mean())
        metrics[f"c_err_inside_mean_{name}"] = float(err[inside].mean()) if inside.any() else 0.0
        columns[f"c_{name}"] = est.numpy()
    metrics["num_video_frames"] = num_video
    metrics["num_reference_frames"] = num_ref
    return metrics, columns, {"c_true": c_true, "estimates": estimates, "inside": inside}


def plot(path, data, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2), dpi=110)
    t = np.arange(len(data["c_true"]))
    inside = data["inside"].numpy()
    if inside.any():
        idx = np.nonzero(inside)[0]
        ax.axvspan(idx[0] - 0.5, idx[-1] + 0.5, color="0.9", label="replaced frames")
    ax.plot(t, data["c_true"].numpy(), "k-", lw=2, label="true C")
    styles = {
        "dtw": ("C3", "--", "proposal DTW"),
        "chain": ("C0", ":", "chain Viterbi"),
        "robust": ("C2", "-", "robust chain"),
        "c2f": ("C4", "-.", "chain, coarse-to-fine"),
        "c2f_robust": ("C5", "--", "robust chain, coarse-to-fine"),
    }
    for name, est in data["estimates"].items():
        colour, ls, label = styles[name]
        ax.plot(t, est.numpy(), color=colour, ls=ls, lw=1.4, label=label)
    ax.set_xlabel("input frame t'")
    ax.set_ylabel("reference frame C(t')")
    ax.set_title(title)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
