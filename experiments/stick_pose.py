"""Pose of stick figures from 2-D joints (the proposal's Section 5.1.1, Figs. 6-11).

Per frame of a BVH motion, the 20 body landmarks (``motion.bodyparts`` roles) are placed by
a random global rotation and translation in front of a perspective camera, projected, and
disturbed by uniform noise of +-``noise`` x the 2-D figure height on each coordinate (the
proposal's noise model: 1.8 % and 3.6 %). The global pose is recovered by
``motion.pose.solve_pose`` and by OpenCV's EPnP + ``solvePnPRefineLM`` on the same data.
Errors: E_R (Eq. 21), E_r (Eq. 22, XYZ Euler angles, degrees), E_p (Eq. 23, over the 3-D
figure height). Throughput of both on ``throughput_poses`` poses, same run.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from experiments.config import ConfigError, ExperimentConfig
from experiments.progress import progress
from experiments.stick_time import BUNDLED, reference_landmarks
from motion.kinematics import matrix_to_euler
from motion.metrics import position_error, registration_error, rotation_error_deg
from motion.pose import solve_pose
from motion.settings import setting

K = torch.tensor([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]], dtype=torch.float64)
CAMERAS = ("perspective", "orthographic")
LEVELS = {"n0": 0.0, "n18": 0.018, "n36": 0.036}


#: metrics that are timings: written to timings.json, apart from the accuracy figures
TIMINGS = ("poses_per_s", "poses_per_s_1thread", "opencv_poses_per_s")


@dataclass
class StickPoseConfig(ExperimentConfig):
    """Fields of ``experiments/configs/stick_pose.yaml``."""

    NAME = "stick_pose"
    TINY_DOC = (
        "a quick run: frames=12, throughput_poses=200, throughput_rounds=1, "
        "sweep_noise=[0, 0.036] (values given on the command line win)"
    )
    TINY: ClassVar[dict] = {
        "frames": 12,
        "throughput_poses": 200,
        "throughput_rounds": 1,
        "sweep_noise": [0.0, 0.036],
    }

    bvh: str = setting(BUNDLED, "BVH file whose frames give the stick figures", path="file")
    frames: int = setting(82, "frames taken evenly from the BVH (at most its length)", ge=1)
    camera_distance: float = setting(
        5.0, "distance of the figures from the camera, metres", gt=0, le=1000
    )
    camera: str = setting(
        "perspective", "camera model (orthographic: ours only, no OpenCV)", choices=CAMERAS
    )
    sweep_noise: list[float] = setting(
        [0.0, 0.01, 0.02, 0.03, 0.04, 0.05, 0.06],
        "noise levels of the sweep (fractions of the 2-D figure height)",
        ge=0,
        le=1,
    )
    throughput_poses: int = setting(10000, "poses solved per throughput round", ge=1)
    throughput_rounds: int = setting(
        5, "throughput rounds (best of, interleaved with OpenCV's)", ge=1
    )


def _intrinsics(cfg: StickPoseConfig) -> torch.Tensor:
    """The perspective camera's K, or an orthographic one with the same image scale at the
    figure's distance (pixels per metre = focal length / distance)."""
    if cfg.camera == "perspective":
        return K
    k = K.clone()
    k[0, 0] = k[1, 1] = K[0, 0] / cfg.camera_distance
    return k


def _project(pc: torch.Tensor, k: torch.Tensor, orthographic: bool) -> torch.Tensor:
    xy = pc[..., :2] if orthographic else pc[..., :2] / pc[..., 2:]
    return xy * k[0, 0] + k[:2, 2]


def _problems(cfg: StickPoseConfig, g: torch.Generator):
    ref, _ = reference_landmarks(cfg.bvh)
    if cfg.frames > len(ref):
        raise ConfigError(
            f"frames={cfg.frames}: {cfg.bvh} has {len(ref)} frames; expected at most {len(ref)}"
        )
    step = max(1, len(ref) // cfg.frames)
    x3 = ref[::step][: cfg.frames]
    x3 = x3 - x3.mean(1, keepdim=True)
    b = x3.shape[0]
    rv = torch.randn(b, 3, generator=g, dtype=torch.float64) * 0.6
    r = axis_angle_to_rotation_matrix(rv)
    t = torch.tensor([0.0, 0.0, cfg.camera_distance], dtype=torch.float64) + 0.2 * torch.randn(
        b, 3, generator=g, dtype=torch.float64
    )
    pc = x3 @ r.transpose(1, 2) + t[:, None]
    nearest = float(pc[..., 2].min())
    if cfg.camera == "perspective" and nearest <= 1e-3:  # orthographic sees any depth
        raise ConfigError(
            f"camera_distance={cfg.camera_distance:g}: landmarks reach depth {nearest:.2f} m "
            "from the camera; expected every landmark in front of it (raise camera_distance)"
        )
    ortho = cfg.camera == "orthographic"
    if ortho:  # the depth is unobservable: the solver returns t_z = 0
        t[:, 2] = 0
    return x3, r, t, _project(pc, _intrinsics(cfg), ortho)


def _opencv(x3: torch.Tensor, obs: torch.Tensor):
    rs, ts = [], []
    for x, o in zip(x3.numpy(), obs.numpy(), strict=True):
        _, rv, tv = cv2.solvePnP(x, o, K.numpy(), None, flags=cv2.SOLVEPNP_EPNP)
        rv, tv = cv2.solvePnPRefineLM(x, o, K.numpy(), None, rv, tv)
        rs.append(rv[:, 0])
        ts.append(tv[:, 0])
    return axis_angle_to_rotation_matrix(torch.from_numpy(np.stack(rs))), torch.from_numpy(
        np.stack(ts)
    )


def _seconds(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def _errors(x3, r_true, t_true, obs, r_est, t_est, h2d, h3d, k=K, orthographic=False):
    proj = _project(x3 @ r_est.transpose(1, 2) + t_est[:, None], k, orthographic)
    e_reg = registration_error(proj, obs, h2d)
    e_rot = rotation_error_deg(matrix_to_euler(r_true, "XYZ"), matrix_to_euler(r_est, "XYZ"))
    e_pos = position_error(t_true, t_est, h3d)
    return e_reg, e_rot, e_pos


def run(cfg: StickPoseConfig):
    g = torch.Generator().manual_seed(cfg.seed)
    ortho = cfg.camera == "orthographic"
    k = _intrinsics(cfg)
    x3, r, t, uv = _problems(cfg, g)
    h2d = uv[..., 1].amax(-1) - uv[..., 1].amin(-1)
    h3d = x3[..., 1].amax(-1) - x3[..., 1].amin(-1)
    metrics: dict[str, float] = {}
    columns: dict[str, np.ndarray] = {"frame": np.arange(x3.shape[0])}

    def solve(x3, obs):
        return solve_pose(x3, obs, k, orthographic=ortho)

    def solve_at(level: float) -> dict[str, tuple]:
        """Both solvers at one noise level: {"": (E_R, E_r, E_p), "opencv_": ...} per frame
        (OpenCV's PnP has no orthographic camera: ours only, then)."""
        noise = (torch.rand(uv.shape, generator=g, dtype=torch.float64) * 2 - 1) * level
        obs = uv + noise * h2d[:, None, None]
        ours = solve(x3, obs)
        solutions = {"": (ours.R, ours.t)}
        if not ortho:
            solutions["opencv_"] = _opencv(x3, obs)
        return {
            prefix: _errors(x3, r, t, obs, re, te, h2d, h3d, k, ortho)
            for prefix, (re, te) in solutions.items()
        }

    for suffix, level in LEVELS.items():
        for prefix, (e_reg, e_rot, e_pos) in solve_at(level).items():
            for name, err in (("reg_err", e_reg), ("rot_err_deg", e_rot), ("pos_err", e_pos)):
                metrics[f"{prefix}{name}_mean_{suffix}"] = float(err.mean())
                columns[f"{prefix}{name}_{suffix}"] = err.numpy()
    sweep = {"noise": [], "rot": [], "pos": [], "reg": [], "cv_rot": [], "cv_pos": [], "cv_reg": []}
    for level in cfg.sweep_noise:
        for prefix, (e_reg, e_rot, e_pos) in solve_at(level).items():
            key = "cv_" if prefix else ""
            sweep[key + "rot"].append(float(e_rot.mean()))
            sweep[key + "pos"].append(float(e_pos.mean()))
            sweep[key + "reg"].append(float(e_reg.mean()))
        sweep["noise"].append(level)
    # throughput on many poses (the same generator of problems, tiled)
    n = cfg.throughput_poses
    reps = -(-n // x3.shape[0])
    big3 = x3.repeat(reps, 1, 1)[:n]
    big2 = (
        uv
        + (torch.rand(uv.shape, generator=g, dtype=torch.float64) * 2 - 1)
        * 0.018
        * h2d[:, None, None]
    ).repeat(reps, 1, 1)[:n]
    m = min(n, 2000)
    # Warm both up once (first calls pay for allocations and lazy initialisation), then
    # take the best of interleaved rounds: the machine's speed drifts between seconds.
    solve(big3[:100], big2[:100])
    if not ortho:
        _opencv(big3[:20], big2[:20])
    ours, theirs, single = [], [], []
    for _ in progress(range(cfg.throughput_rounds), "stick_pose: throughput rounds"):
        ours.append(_seconds(lambda: solve(big3, big2)))
        if not ortho:
            theirs.append(_seconds(lambda: _opencv(big3[:m], big2[:m])))
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            single.append(_seconds(lambda: solve(big3, big2)))
        finally:
            torch.set_num_threads(threads)
    metrics["poses_per_s"] = n / min(ours)
    metrics["poses_per_s_1thread"] = n / min(single)
    if not ortho:
        metrics["opencv_poses_per_s"] = m / min(theirs)
    return metrics, columns, {"columns": columns, "sweep": sweep}


def plot(path, data, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c, s = data["columns"], data["sweep"]
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5), dpi=100)
    for i, (name, label) in enumerate(
        (("reg_err", "E_R"), ("rot_err_deg", "E_r (deg)"), ("pos_err", "E_p"))
    ):
        ax = axes[0, i]
        for suffix, colour in (("n0", "k"), ("n18", "C0"), ("n36", "C3")):
            ax.plot(c["frame"], c[f"{name}_{suffix}"], color=colour, lw=1, label=f"ours {suffix}")
            if f"opencv_{name}_{suffix}" not in c:
                continue
            ax.plot(
                c["frame"],
                c[f"opencv_{name}_{suffix}"],
                color=colour,
                lw=1,
                ls=":",
                label=f"OpenCV {suffix}",
            )
        ax.set_title(f"{label} per frame (Figs. 6-8)", fontsize=9)
        ax.set_xlabel("frame")
        if i == 0:
            ax.legend(fontsize=6)
    for i, (key, label) in enumerate((("reg", "E_R"), ("rot", "E_r (deg)"), ("pos", "E_p"))):
        ax = axes[1, i]
        noise = np.array(s["noise"]) * 100
        ax.plot(noise, s[key], "C0o-", label="ours")
        if s["cv_" + key]:
            ax.plot(noise, s["cv_" + key], "C1s--", label="OpenCV EPnP + RefineLM")
        ax.set_xlabel("2-D joint noise (% of figure height)")
        ax.set_title(f"mean {label} vs noise (Figs. 9-11)", fontsize=9)
        ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
