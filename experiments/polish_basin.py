"""Where the posture polish settles on another performer when C and T are the truth: started
at the student's true articulation and at none (the reference's posture at the true C).

A synthetic student of another performer (``motion synth``'s ``student=``, as
``register_synthetic`` renders it) is polished (:func:`motion.registration.polish.
polish_posture`, G 1) from two starts that share the true C and the true root transform T:

* ``truth``: the student's own local rotations -- where the polish's objective has its
  optimum near the truth (the reference's bone lengths and capsules are not the student's,
  so even the truth is not a perfect fit);
* ``none``: the reference's rotations at the true C (articulation A = 0) -- what stages 2-3
  hand the polish when they find no difference.

Per start: the RMS error of each clinical angle (``motion.angles``, OpenSim's coordinates)
against the student's true angle, before and after, averaged over the coordinates; and how
much of the student's range of motion beyond the reference's the polished posture shows
(``range_recovered``: the least-squares slope, through 0 and over the coordinates, of the
estimated against the true extra range -- 1 recovers it, 0 keeps the reference's). A polish
that moves ``none`` toward the truth can find an articulation that stages 2-3 miss; one that
stays where it starts cannot, whatever its objective's optimum.
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from experiments.config import ConfigError, ExperimentConfig
from experiments.progress import note
from experiments.register_synthetic import RegisterSyntheticConfig, synthetic_truth
from experiments.stick_time import BUNDLED
from motion.angles import COORDINATES, SegmentMap, clinical_angles
from motion.registration.inputs import features_from_sequence
from motion.registration.polish import PosturePolishSettings, polish_posture
from motion.registration.types import Reference
from motion.settings import setting
from motion.synth import SynthConfig, synthesize

#: the two starts, in the order of the metrics and the plot
STARTS = ("truth", "none")


@dataclass
class PolishBasinConfig(ExperimentConfig):
    """Fields of ``experiments/configs/polish_basin.yaml``."""

    NAME = "polish_basin"
    TINY_DOC = "a quick run (6 frames, 5 polish steps)"
    TINY: ClassVar[dict] = {"frames": 6, "steps": 5}

    reference: str = setting(BUNDLED, "reference BVH", path="file")
    student: str = setting(
        "motion/data/cmu_07_01_walk.bvh",
        "another performer's BVH of the same action (the same joints)",
        path="file",
    )
    cameras: int = setting(2, "static cameras around the student", ge=1, le=8)
    keypoints: bool = setting(False, "give noisy 2-D joints to the polish as well")
    frames: int = setting(40, "video frames polished (the first N)", ge=2)
    steps: int = setting(50, "Adam steps of the polish (motion register's default: 50)", ge=1)
    articulation_deg: float = setting(
        20.0, "the polish's articulation prior, degrees (motion register's default: 20)", gt=0
    )
    lr: float = setting(
        0.02, "the polish's Adam step size (motion register's default: 0.02)", gt=0, le=1
    )
    smooth_deg: float = setting(
        3.0, "the polish's frame-to-frame smoothness, degrees (motion register's default: 3)", gt=0
    )
    proportion_steps: int = setting(
        0,
        "steps of the polish's fit of the student's proportions to the 2-D joints (motion "
        "register's default: 0, the reference's proportions)",
        ge=0,
    )
    joints_first_steps: int = setting(
        0,
        "steps of a descent on the 2-D joints alone before the polish (motion register's "
        "default: 0, none)",
        ge=0,
    )
    warp_seed: int = setting(0, "seed of the synthetic student's time warp", ge=0)


def _angles(reference: Reference, rotations: torch.Tensor) -> np.ndarray:
    """``(T', K)`` clinical angles, degrees, of local ``rotations`` on the reference's body."""
    segments = SegmentMap.from_roles(reference.skeleton, reference.model.mapping)
    return clinical_angles(reference.skeleton, rotations.double(), segments).degrees.numpy()


def _extra_range(angles: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``(K,)`` each coordinate's range over the frames minus the reference's, degrees."""
    return np.ptp(angles, 0) - np.ptp(reference, 0)


def range_recovered(estimated: np.ndarray, true: np.ndarray) -> float:
    """The least-squares slope through 0 of ``estimated`` on ``true`` ``(K,)``: 1 where the
    estimate shows the true values, 0 where it shows none of them."""
    return float(np.dot(estimated, true) / max(float(np.dot(true, true)), 1e-12))


def run(cfg: PolishBasinConfig):
    rendering = RegisterSyntheticConfig()  # the student as register_synthetic renders it
    synth = SynthConfig(
        fps=rendering.fps,
        cameras=cfg.cameras,
        size=list(rendering.size),
        focal_px=rendering.focal_px,
        yaw_deg=rendering.yaw_deg,
        warp=rendering.warp,
        seed=cfg.warp_seed,
    )
    # the truth is the whole video's (a DP over all its frames); only the frames used are drawn
    whole = synthesize(cfg.reference, synth, student=cfg.student, images=False)
    seq = synthesize(cfg.reference, synth, student=cfg.student, frames=cfg.frames)
    reference, student = Reference.from_bvh(cfg.reference), Reference.from_bvh(cfg.student)
    if student.skeleton.names != reference.skeleton.names:
        raise ConfigError(
            f"student: {cfg.student} has other joints than {cfg.reference}; expected the same"
        )
    truth = synthetic_truth(whole, reference, student)
    video = features_from_sequence(seq, keypoints=cfg.keypoints)
    if cfg.frames > whole.meta["num_video_frames"]:
        raise ConfigError(
            f"frames must be <= {whole.meta['num_video_frames']} (the video's); got {cfg.frames}"
        )
    n = cfg.frames
    video = video.cut(slice(0, n))
    c, local, position = truth.C[:n], truth.local[:n], truth.position[:n]
    none = reference.rotations[c].clone()
    none[:, 0] = local[:, 0]  # the true T
    settings = PosturePolishSettings(
        steps=cfg.steps,
        articulation_deg=cfg.articulation_deg,
        lr=cfg.lr,
        smooth_deg=cfg.smooth_deg,
        proportion_steps=cfg.proportion_steps,
        joints_first_steps=cfg.joints_first_steps,
    )
    true_angles = _angles(reference, local)
    reference_angles = _angles(reference, reference.rotations[c])
    true_extra = _extra_range(true_angles, reference_angles)
    metrics, columns = {}, {"frame": np.arange(n)}
    per_coordinate = {}
    for name, start in zip(STARTS, (local, none), strict=True):
        note(f"polish_basin: polishing {n} frames from the {name} start")
        polished = polish_posture(reference, video, c, start, position, 1.0, settings)
        for when, rotations in (("start", start), ("polished", polished.rotations)):
            angles = _angles(reference, rotations)
            error = angles - true_angles
            rms = np.sqrt(np.mean(error**2, 0))  # (K,)
            metrics[f"angle_rms_deg_{when}_{name}"] = float(rms.mean())
            if when == "polished":
                per_coordinate[name] = rms
                columns[f"angle_err_deg_{name}"] = np.abs(error).mean(1)
                extra = _extra_range(angles, reference_angles)
                metrics[f"range_recovered_{name}"] = range_recovered(extra, true_extra)
    metrics["true_extra_range_deg_rms"] = float(np.sqrt(np.mean(true_extra**2)))
    data = {"coordinates": list(COORDINATES), "rms": per_coordinate}
    return metrics, columns, data


def plot(path, data, title: str) -> None:
    """Each clinical angle's RMS error against the truth after the polish, from each start."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = data["coordinates"]
    y = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(7, 6), dpi=100)
    for i, start in enumerate(STARTS):
        ax.barh(y + (i - 0.5) * 0.4, data["rms"][start], height=0.4, label=f"from {start}")
    ax.set_yticks(y, names, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("RMS error against the true angle after the polish, degrees")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="x")
    fig.suptitle("\n".join(textwrap.wrap(title, 80)), fontsize=8)  # a sweep entry's long name
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
