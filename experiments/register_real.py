"""Registration on real videos (issue: ``motion register``): the two real cases of
``../shared/data``.

* **sports2d**: the bundled CMU walk (02_01) against the woman walking past in the Sports2D
  demo video -- one uncalibrated phone camera (a nominal field of view), outdoors, another
  person doing jumping jacks on a box; the person to follow is picked by a pixel near her.
  No ground truth: ``sports2d_silhouette_iou_mean`` says how well the registered body
  covers her silhouette.
* **pose2sim**: a reference built from the Pose2Sim trial's own triangulated 3-D keypoints
  (:func:`motion.registration.markers.reference_from_markers`, the Butterworth-filtered
  TRC) against its 4 calibrated cameras. The reference *is* the trial, so the true C is
  the identity and the recovered joints can be compared with the triangulation:
  ``pose2sim_e3d_mean`` (mean joint distance over the joints at markers, fraction of the body
  height), ``pose2sim_c_err_mean`` (frames), and the student's clinical joint angles
  (:mod:`motion.angles`) against the trial's own OpenSim inverse kinematics, RMSE per
  coordinate (``pose2sim_rmse_deg_<coordinate>``, e.g. ``pose2sim_rmse_deg_knee_angle_r``;
  ``pose2sim_rmse_deg_leg_flexion_mean`` over hip, knee and ankle flexion of both legs).
  The reference's own angles against OpenSim (``pose2sim_reference_rmse_deg_...``) are the
  floor a skeleton fitted to the markers allows: two models of one body, which place the
  joint centres and the segments' neutral differently. Each RMSE comes also ``centred``
  (the mean difference taken out: what is left once the two models' neutral is put
  aside), and the student's angles against the reference's own
  (``pose2sim_own_rmse_deg_...``) are the registration's error free of either model's
  conventions.

Each case runs ``python -m motion register`` as a user would (:func:`motion.registration.
command.run_register`), so ``out_dir/sports2d`` and ``out_dir/pose2sim`` hold its report,
overlays and exports. Needs ``../shared/data``: skipped with a message when that default
location is absent.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch

from experiments.config import ConfigError, ExperimentConfig, ExperimentSkipped
from experiments.progress import note
from experiments.stick_time import BUNDLED
from motion.angles import ClinicalAngles, SegmentMap, clinical_angles
from motion.bodyparts import load_spec
from motion.cameras import load_pose2sim_calibration
from motion.keypoints import read_trc
from motion.registration import Reference, Registration
from motion.registration.command import RegisterJob, run_register
from motion.registration.export import student_kinematics
from motion.registration.markers import MARKER_JOINTS, reference_from_markers
from motion.settings import setting

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
TIMINGS = ("sports2d_sec", "pose2sim_sec")

SPORTS2D = Path("video/sports2d_demo/demo.mp4")
POSE2SIM_VIDEOS = Path("video/pose2sim_balancing_trial")
POSE2SIM_CALIBRATION = POSE2SIM_VIDEOS / "calibration" / "Calib_qualisys.toml"
POSE2SIM_TRC = Path(
    "keypoints/pose2sim_balancing_trial/pose3d/S00_P00_T01_BalancingTrial_0-100_filt_butterworth.trc"
)
POSE2SIM_MOT = Path(
    "keypoints/pose2sim_balancing_trial/opensim/S00_P00_T01_BalancingTrial_filt_butterworth_0-100_body25b.mot"
)
#: the trial's OpenPose detections, one folder per camera
POSE2SIM_KEYPOINTS = Path("keypoints/pose2sim_balancing_trial/pose2d_openpose_body25b")
#: the sagittal leg coordinates whose mean RMSE against OpenSim is one figure
LEG_FLEXION = [f"{c}_{s}" for s in ("r", "l") for c in ("hip_flexion", "knee_angle", "ankle_angle")]
#: the TRC's axes (Y up) in the calibration's world (Z up)
TRC_TO_WORLD = [2, 0, 1]


@dataclass
class RegisterRealConfig(ExperimentConfig):
    """Fields of ``experiments/configs/register_real.yaml``."""

    NAME = "register_real"
    TINY_DOC = "a quick run (8 frames at 96 px, 12 particles, 1 iteration)"
    TINY: ClassVar[dict] = {
        "frames": 8,
        "sports2d_width": 96,
        "pose2sim_width": 96,
        "particles": 12,
        "iterations": 1,
        "restarts": 1,
    }

    data: str = setting(
        str(SHARED),
        "the shared data folder (default: ../shared/data beside the checkout; the run is "
        "skipped when that default is absent, a named folder must exist)",
    )
    cases: list[str] = setting(
        ["sports2d", "pose2sim"], "which real cases to run", choices=("sports2d", "pose2sim")
    )
    reference: str = setting(BUNDLED, "the reference BVH of the sports2d case", path="file")
    sports2d_start: int = setting(75, "first video frame of the walk (sports2d)", ge=0)
    sports2d_person: list[float] = setting(
        [1190.0, 660.0], "x,y pixel near the walker in that frame (sports2d)", length=2
    )
    pose2sim_cameras: list[int] | None = setting(
        None,
        "the trial's cameras registered (1-based; none: all 4); fewer get a calibration of "
        "those cameras only, written beside the outputs",
        min_length=1,
    )
    pose2sim_keypoints: bool = setting(
        False,
        "give the pose2sim case the trial's OpenPose BODY_25B 2-D keypoints instead of the "
        "bundled person detector's (2-D joints are needed: without any, a person standing "
        "in place can be registered facing backwards, silhouettes do not tell front from "
        "back)",
    )
    frames: int = setting(80, "video frames per case (pose2sim has 100)", ge=2)
    sports2d_width: int = setting(
        320, "working width of the sports2d video, pixels", ge=32, le=4096
    )
    pose2sim_width: int = setting(
        240, "working width of the pose2sim videos (4 cameras), pixels", ge=32, le=4096
    )
    particles: int = setting(60, "particles per part", ge=2)
    iterations: int = setting(4, "particle BP iterations per pass", ge=1)
    restarts: int = setting(1, "particle BP passes", ge=1)
    polish_steps: int = setting(
        50, "steps of motion register's posture polish (its default: 50; 0: none)", ge=0
    )
    registration: dict[str, str] = setting(
        {},
        "any other setting of motion register by its dotted key (refine.articulation_std: "
        "0.2), as on its command line; applied after the fields above",
    )


def _data_root(cfg: RegisterRealConfig) -> Path:
    root = Path(cfg.data)
    if (root / SPORTS2D).is_file() and (root / POSE2SIM_CALIBRATION).is_file():
        return root
    if root.resolve() == SHARED.resolve():
        raise ExperimentSkipped(f"register_real needs the shared data set ({root} is incomplete)")
    raise ConfigError(
        f"data={cfg.data}: expected the shared data folder (with {SPORTS2D} and "
        f"{POSE2SIM_CALIBRATION})"
    )


def _overrides(cfg: RegisterRealConfig, width: int) -> tuple[str, ...]:
    band = min(12, (cfg.particles - 1) // 2)
    return (
        f"video.width={width}",
        f"refine.particles={cfg.particles}",
        f"refine.iterations={cfg.iterations}",
        f"refine.restarts={cfg.restarts}",
        f"refine.band={band}",
        f"polish.steps={cfg.polish_steps}",
        f"seed={cfg.seed}",
        *(f"{key}={value}" for key, value in cfg.registration.items()),
    )


def _register(cfg: RegisterRealConfig, job: RegisterJob) -> tuple[Registration, float]:
    """``python -m motion register`` as a user runs it (every output and the report in
    ``job.out``); returns the registration and its seconds (stages 0-3)."""
    outcome = run_register(job, show_progress=False)
    note(f"register_real: wrote {len(outcome.files)} files to {job.out}")
    return outcome.registration, sum(outcome.registration.timings.values())


def _sports2d(cfg: RegisterRealConfig, root: Path) -> tuple[dict, dict]:
    job = RegisterJob(
        Path(cfg.reference),
        [root / SPORTS2D],
        Path(cfg.out_dir) / "sports2d",
        overrides=(
            *_overrides(cfg, cfg.sports2d_width),
            f"video.start={cfg.sports2d_start}",
            f"video.count={cfg.frames}",
        ),
        person=tuple(cfg.sports2d_person),
    )
    result, seconds = _register(cfg, job)
    metrics = {
        "sports2d_silhouette_iou_mean": float(result.fit.mean()),
        "sports2d_sec": seconds,
    }
    return metrics, {"sports2d_iou": result.fit.numpy(), "sports2d_c": result.C.numpy()}


def _read_mot(path: Path) -> tuple[list[str], np.ndarray]:
    lines = path.read_text().splitlines()
    head = next(i for i, line in enumerate(lines) if line.strip() == "endheader")
    names = lines[head + 1].split()
    rows = np.array(
        [[float(v) for v in line.split()] for line in lines[head + 2 :] if line.strip()]
    )
    return names, rows


def _clinical(reference: Reference, rotations: torch.Tensor) -> ClinicalAngles:
    segments = SegmentMap.from_roles(reference.skeleton, reference.model.mapping)
    return clinical_angles(reference.skeleton, rotations, segments)


def rmse_against(
    angles: ClinicalAngles, names: list[str], rows: np.ndarray, prefix: str
) -> dict[str, float]:
    """Per coordinate both give, over the frames both have (degrees):
    ``{prefix}_{coordinate}`` the RMSE of ``angles`` against the columns ``names`` of
    ``rows`` ``(F, len(names))``, ``{prefix}_centred_{coordinate}`` the RMSE once the
    mean difference is taken out (what two models of one body that put a joint's neutral
    differently still disagree on), and the mean of each over :data:`LEG_FLEXION`
    (``{prefix}_leg_flexion_mean``, ``{prefix}_centred_leg_flexion_mean``)."""
    n = min(len(rows), angles.degrees.shape[0])
    out = {}
    for coordinate in angles.names:
        if coordinate in names:
            gap = angles[coordinate][:n].numpy() - rows[:n, names.index(coordinate)]
            out[f"{prefix}_{coordinate}"] = float(np.sqrt(np.nanmean(gap**2)))
            centred = gap - np.nanmean(gap)
            out[f"{prefix}_centred_{coordinate}"] = float(np.sqrt(np.nanmean(centred**2)))
    for kind in ("", "centred_"):
        legs = [out[f"{prefix}_{kind}{c}"] for c in LEG_FLEXION if f"{prefix}_{kind}{c}" in out]
        if legs:
            out[f"{prefix}_{kind}leg_flexion_mean"] = float(np.mean(legs))
    return out


def _calibration_of(path: Path, cameras: list[int], out: Path) -> Path:
    """A copy of the trial's calibration with only ``cameras`` (1-based) and its metadata."""
    sections = re.split(r"(?m)^(?=\[)", path.read_text())
    kept = [
        text
        for text in sections
        if text.strip()
        and (text.startswith("[metadata]") or any(text.startswith(f"[cam_0{c}]") for c in cameras))
    ]
    out.mkdir(parents=True, exist_ok=True)
    written = out / f"calibration_cams{''.join(map(str, cameras))}.toml"
    written.write_text("".join(kept))
    return written


def _pose2sim(cfg: RegisterRealConfig, root: Path) -> tuple[dict, dict]:
    markers = read_trc(root / POSE2SIM_TRC)
    bvh = Path(cfg.out_dir) / "pose2sim_reference.bvh"
    bvh.parent.mkdir(parents=True, exist_ok=True)
    reference = reference_from_markers(markers, out_bvh=bvh)
    n = min(cfg.frames, reference.num_frames)
    total = load_pose2sim_calibration(root / POSE2SIM_CALIBRATION).num_cameras
    cameras = cfg.pose2sim_cameras or list(range(1, total + 1))
    if not all(1 <= c <= total for c in cameras):
        raise ConfigError(f"pose2sim_cameras={cameras}: the trial has cameras 1..{total}")
    calibration = root / POSE2SIM_CALIBRATION
    if len(cameras) < total:
        calibration = _calibration_of(calibration, cameras, Path(cfg.out_dir))
    job = RegisterJob(
        bvh,
        [root / POSE2SIM_VIDEOS / f"cam0{c}.mp4" for c in cameras],
        Path(cfg.out_dir) / "pose2sim",
        calibration,
        overrides=(*_overrides(cfg, cfg.pose2sim_width), f"video.count={n}"),
        keypoints=tuple(root / POSE2SIM_KEYPOINTS / f"cam0{c}_json" for c in cameras)
        if cfg.pose2sim_keypoints
        else (),
    )
    result, seconds = _register(cfg, job)

    # joints at markers: recovered against triangulated, in the calibration's world
    world = torch.from_numpy(markers.positions[:n])[..., TRC_TO_WORLD].to(torch.float64)
    fk = student_kinematics(result, reference)
    roles = load_spec("pose2sim_21")
    pairs = [
        (markers.names.index(roles[role][0]), reference.skeleton.index(joint))
        for role, joint in MARKER_JOINTS.items()
        if len(roles.get(role, [])) == 1
        and roles[role][0] in markers.names
        and joint in reference.skeleton.names
    ]
    if not pairs:
        raise ConfigError(f"{POSE2SIM_TRC}: no marker matches a joint of the reference")
    m_idx, j_idx = zip(*pairs, strict=True)
    dist = (fk.positions[:, list(j_idx)] - world[:, list(m_idx)]).norm(dim=-1)  # (T', M)
    height = float((world[..., 2].amax(-1) - world[..., 2].amin(-1)).median())
    e3d = dist.mean(-1) / height

    names, rows = _read_mot(root / POSE2SIM_MOT)
    student = _clinical(reference, result.rotations)
    own = _clinical(reference, reference.rotations[:n])
    metrics = {
        "pose2sim_silhouette_iou_mean": float(result.fit.mean()),
        "pose2sim_e3d_mean": float(e3d.mean()),
        "pose2sim_c_err_mean": float((result.C[:n] - torch.arange(n)).abs().double().mean()),
        **rmse_against(student, names, rows, "pose2sim_rmse_deg"),
        **rmse_against(own, names, rows, "pose2sim_reference_rmse_deg"),
        # the registration's own error: the reference is the trial, so a perfect
        # registration gives the reference's angles, whatever OpenSim's model says
        **rmse_against(student, own.names, own.degrees.numpy(), "pose2sim_own_rmse_deg"),
        "pose2sim_G": float(result.G),
        "pose2sim_sec": seconds,
    }
    note(f"pose2sim: joints compared with markers: {len(pairs)}")
    return metrics, {
        "pose2sim_iou": result.fit.numpy(),
        "pose2sim_e3d": e3d.numpy(),
        "pose2sim_c": result.C.numpy(),
    }


def run(cfg: RegisterRealConfig):
    root = _data_root(cfg)
    metrics: dict[str, float] = {}
    columns: dict[str, np.ndarray] = {}
    if "sports2d" in cfg.cases:
        m, c = _sports2d(cfg, root)
        metrics |= m
        columns |= c
    if "pose2sim" in cfg.cases:
        m, c = _pose2sim(cfg, root)
        metrics |= m
        columns |= c
    length = max(len(v) for v in columns.values())
    table = {"frame": np.arange(length)}
    for key, values in columns.items():
        padded = np.full(length, np.nan)
        padded[: len(values)] = values
        table[key] = padded
    return metrics, table, {"columns": table}


def plot(path, data, title: str) -> None:
    """Per-frame silhouette IoU of each case (and pose2sim's E_3D)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = data["columns"]
    fig, ax = plt.subplots(figsize=(8, 3.4), dpi=100)
    for key, label in (("sports2d_iou", "sports2d IoU"), ("pose2sim_iou", "pose2sim IoU")):
        if key in c:
            ax.plot(c["frame"], c[key], label=label)
    if "pose2sim_e3d" in c:
        ax.plot(c["frame"], c["pose2sim_e3d"] * 10, "--", label="pose2sim E3D x 10")
    ax.set_xlabel("video frame")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
