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
from dataclasses import dataclass, field

import numpy as np
import torch

from motion.alignment import chain_align, coarse_to_fine_align, dtw, robust_cost, slope_step_cost
from motion.bodyparts import BodyModel
from motion.bvh import read_bvh
from motion.kinematics import Skeleton, forward_kinematics, local_rotations
from motion.pose import solve_pose
from motion.synth import time_warp

BUNDLED = "motion/data/cmu_02_01_walk.bvh"


@dataclass
class StickTimeConfig:
    """Fields of ``experiments/configs/stick_time.yaml`` (see experiments/README.md)."""

    bvh: str = BUNDLED
    fps: float = 25.0  # input frame rate (the reference's is read from the BVH)
    warp: float = 0.3  # largest relative change of playback speed
    noise: float = 0.018  # uniform 2-D joint noise, fraction of the 2-D figure height
    corrupt: bool = True
    camera_distance: float = 5.0
    max_step: int = 12
    robust_scale: float = 2.0  # truncation at this many times the median best-match cost
    slope_weight: float = 0.5  # slope prior weight, in units of the truncation level
    # The camera does not move: after a first robust alignment on Eq. 24, one camera pose is
    # fitted to the matched inlier pairs and the chain methods run on the costs under it
    # (the proposal's DTW always runs on Eq. 24's per-pair poses, as published).
    static_camera: bool = True
    seed: int = 0
    out_dir: str = "runs/stick_time"
    tiny: bool = False
    # dtw, chain, robust (full cost matrix); c2f and c2f_robust (the chain and the robust
    # chain coarse-to-fine: Eq. 24 evaluated on demand inside a band, for long sequences)
    methods: list = field(default_factory=lambda: ["dtw", "chain", "robust"])
    full_matrix_max_cells: int = 5_000_000
    c2f_max_cells: int = 200_000


def _reference_landmarks(path: str) -> tuple[torch.Tensor, float]:
    bvh = read_bvh(path)
    skel = Skeleton.from_bvh(bvh)
    motion = bvh.motion_frames()  # without a converter's reference pose
    fk = forward_kinematics(skel, *local_rotations(skel, torch.from_numpy(motion), bvh.channels))
    model = BodyModel.from_skeleton(skel)
    landmarks = model.landmarks(model.skeleton_points(skel, fk))  # (T, R, 3)
    return landmarks - landmarks[:, :1].mean(0, keepdim=True), bvh.frame_rate


def run(cfg: StickTimeConfig) -> tuple[dict, dict, dict]:
    """Returns (metrics, per-frame columns, plot data)."""
    g = torch.Generator().manual_seed(cfg.seed)
    ref, ref_rate = _reference_landmarks(cfg.bvh)
    if cfg.tiny:
        ref = ref[: min(len(ref), 120)]
    num_ref = ref.shape[0]
    num_video = int((num_ref - 1) * cfg.fps / ref_rate) + 1
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
    full_methods = [m for m in cfg.methods if m in ("dtw", "chain", "robust")]
    if full_methods:
        if num_video * num_ref > cfg.full_matrix_max_cells:
            raise ValueError(
                f"{num_video} x {num_ref} cells exceed full_matrix_max_cells={cfg.full_matrix_max_cells}: "
                "use methods=[c2f] for long sequences (coarse-to-fine, no full matrix)"
            )
        # Eq. 24 for every (t', t): one batched pose solve per video frame against all references
        cost = torch.empty(num_video, num_ref, dtype=torch.float64)
        for i in range(num_video):
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
