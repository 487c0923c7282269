"""Real data: camera extrinsics and time correspondence from the shared pose2sim trial.

The triangulated 3-D keypoints are the reference; the 2-D keypoints of each of the 4 cameras
are the input. (1) Each camera's extrinsics are recovered from its 2-D-3-D correspondences
over all frames (``motion.pose.solve_pose``: weak-perspective/DLT starts, LM) and compared
with the shipped calibration. (2) The reference is time-warped by a known smooth warp and
upsampled to ``reference_rate``; C of every input frame is recovered by chain alignment on
``d(t', t)`` = mean reprojection error over cameras and joints (the recovered cameras fixed).
Needs ``../shared/data``: skipped with a message when that default location is absent; a
``data`` folder the user names must hold the trial (else a ConfigError).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from experiments.config import ConfigError, ExperimentConfig, ExperimentSkipped
from motion.alignment import chain_align, robust_cost
from motion.cameras import CameraRig, load_pose2sim_calibration
from motion.keypoints import BODY_25B, read_openpose_folder, read_trc
from motion.pose import solve_pose
from motion.settings import setting
from motion.synth import time_warp

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


@dataclass
class Pose2simRealConfig(ExperimentConfig):
    """Fields of ``experiments/configs/pose2sim_real.yaml``."""

    NAME = "pose2sim_real"
    TINY_DOC = "the first 40 frames only, for tests"

    data: str = setting(
        str(SHARED),
        "the shared data folder (default: ../shared/data beside the checkout; the run is "
        "skipped when that default is absent, a named folder must exist)",
    )
    reference_rate: float = setting(
        120.0, "the warped reference is resampled to this rate (Hz)", gt=0, le=10000
    )
    warp: float = setting(0.3, "largest relative change of playback speed", ge=0, lt=1)
    min_confidence: float = setting(
        0.3, "2-D detections below this confidence are ignored", ge=0, lt=1
    )
    max_step: int = setting(6, "S: most reference frames C advances per input frame", ge=1)


#: the files the run reads, relative to ``data``
CALIBRATION = Path("video/pose2sim_balancing_trial/calibration/Calib_qualisys.toml")
TRIAL = Path("keypoints/pose2sim_balancing_trial")


def _data_root(cfg: Pose2simRealConfig) -> Path:
    """The data folder: absent at the default location -> :class:`ExperimentSkipped` (the
    test suite without ../shared/data); a named folder without the trial -> ConfigError."""
    root = Path(cfg.data)
    if (root / CALIBRATION).is_file():
        return root
    if root.resolve() == SHARED.resolve():
        raise ExperimentSkipped(
            f"pose2sim_real needs the shared data set ({root / CALIBRATION} is missing)"
        )
    what = "no such folder" if not root.is_dir() else f"it has no {CALIBRATION}"
    raise ConfigError(
        f"data={cfg.data}: expected the shared data folder (with {CALIBRATION} and {TRIAL}); "
        f"got {what}"
    )


def run(cfg: Pose2simRealConfig):
    root = _data_root(cfg)
    trial = root / TRIAL
    calib_path = root / CALIBRATION
    calib = load_pose2sim_calibration(calib_path)
    markers = read_trc(trial / "pose3d" / "S00_P00_T01_BalancingTrial_0-100.trc")
    world = torch.from_numpy(markers.positions)[..., [2, 0, 1]]  # TRC (Y up) -> calibration world
    shared = [n for n in markers.names if n in BODY_25B]
    m_idx = [markers.names.index(n) for n in shared]
    k_idx = [BODY_25B.index(n) for n in shared]
    x3 = world[:, m_idx]  # (F, n, 3)
    frames = x3.shape[0] if not cfg.tiny else 40
    x3 = x3[:frames]
    det = [
        read_openpose_folder(trial / "pose2d_associated" / f"cam0{c + 1}_json")[:frames, k_idx]
        for c in range(4)
    ]

    # (1) extrinsics per camera from all confident correspondences (undistorted pixels)
    metrics: dict[str, float] = {}
    rot_err, pos_err, reproj = [], [], []
    rs, ts = [], []
    for c in range(4):
        d = torch.from_numpy(det[c])
        ok = (d[..., 2] > cfg.min_confidence) & torch.isfinite(x3).all(-1)
        pts3, pts2 = x3[ok], d[ok][:, :2]
        res = solve_pose(pts3[None], pts2[None], calib.K[c])
        rs.append(res.R[0])
        ts.append(res.t[0])
        rel = calib.R[c].T @ res.R[0]
        rot_err.append(math.degrees(float(torch.acos(((torch.trace(rel) - 1) / 2).clamp(-1, 1)))))
        centre_est = -(res.R[0].T @ res.t[0])
        pos_err.append(float((centre_est - calib.centres()[c]).norm()))
        reproj.append(float(res.cost[0].sqrt()))
    rig = CameraRig(
        calib.K,
        torch.stack(rs),
        torch.stack(ts),
        torch.zeros(4, 5, dtype=torch.float64),
        calib.size,
        calib.names,
    )
    for c in range(4):
        metrics[f"cam{c + 1}_rot_err_deg"] = rot_err[c]
        metrics[f"cam{c + 1}_pos_err_m"] = pos_err[c]
    metrics["cam_rot_err_deg_mean"] = float(np.mean(rot_err))
    metrics["cam_pos_err_m_mean"] = float(np.mean(pos_err))
    # median reprojection error of all confident detections with the recovered cameras
    uv, _ = rig.project(x3)  # (F, C, n, 2)
    errs = []
    for c in range(4):
        d = det[c]
        ok = d[..., 2] > cfg.min_confidence
        e = np.linalg.norm(uv[:, c].numpy() - d[..., :2], axis=-1)[ok]
        errs.append(e[np.isfinite(e)])
    metrics["reproj_px_median"] = float(np.median(np.concatenate(errs)))

    # (2) C: the reference is the 3-D keypoints through a known warp, at reference_rate
    g = torch.Generator().manual_seed(cfg.seed)
    num_video = frames
    num_ref = round((frames - 1) * cfg.reference_rate / markers.rate) + 1
    need = math.ceil((num_ref - 1) / max(num_video - 1, 1))
    if cfg.max_step < need:
        raise ConfigError(
            f"max_step={cfg.max_step}: {num_video} input frames cannot reach the last of "
            f"{num_ref} reference frames in steps of at most {cfg.max_step}; expected "
            f"max_step >= {need} (raise max_step, or lower reference_rate)"
        )
    c_true = time_warp(num_video, num_ref, cfg.warp, g)  # video frame -> reference frame
    # reference frame r shows the pose of video time s(r): invert the warp by interpolation
    s_of_r = np.interp(np.arange(num_ref), c_true.numpy(), np.arange(num_video))
    lo = np.floor(s_of_r).astype(int).clip(0, num_video - 1)
    hi = (lo + 1).clip(0, num_video - 1)
    w = torch.from_numpy(s_of_r - lo)[:, None, None]
    ref = x3[lo] * (1 - w) + x3[hi] * w  # (T, n, 3)
    ref_uv, _ = rig.project(ref)  # (T, C, n, 2)
    cost = torch.zeros(num_video, num_ref, dtype=torch.float64)
    count = torch.zeros(num_video, 1, dtype=torch.float64)
    for c in range(4):
        d = torch.from_numpy(det[c])
        ok = (d[..., 2] > cfg.min_confidence).double()  # (F, n)
        diff = (ref_uv[None, :, c] - d[:, None, :, :2].nan_to_num()).norm(dim=-1)  # (F, T, n)
        cost += (diff.clamp(max=100.0) * ok[:, None]).sum(-1)  # robust to stray detections
        count += ok.sum(-1, keepdim=True)
    cost = cost / count.clamp_min(1)
    est = chain_align(robust_cost(cost), cfg.max_step, fix_start=True, fix_end=True).path[0]
    err = (est - c_true).abs().double()
    metrics["c_err_mean"] = float(err.mean())
    metrics["num_video_frames"] = num_video
    metrics["num_reference_frames"] = num_ref
    columns = {"t_video": np.arange(num_video), "c_true": c_true.numpy(), "c_est": est.numpy()}
    return (
        metrics,
        columns,
        {"c_true": c_true, "c_est": est, "rot_err": rot_err, "pos_err": pos_err},
    )


def plot(path, data, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.6), dpi=110)
    t = np.arange(len(data["c_true"]))
    a.plot(t, data["c_true"].numpy(), "k-", lw=2, label="true C")
    a.plot(t, data["c_est"].numpy(), "C2-", lw=1.2, label="chain (robust)")
    a.set_xlabel("input frame (60 fps)")
    a.set_ylabel("reference frame")
    a.legend(fontsize=8)
    cams = np.arange(1, len(data["rot_err"]) + 1)
    b.bar(cams - 0.2, data["rot_err"], 0.4, label="rotation error (deg)")
    b.bar(cams + 0.2, np.array(data["pos_err"]) * 100, 0.4, label="position error (cm)")
    b.set_xticks(cams)
    b.set_xlabel("camera")
    b.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
