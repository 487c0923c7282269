"""Registration of a reference BVH against a synthetic student video (issue: registration
engine; the proposal's Section 6, variation 3).

The student is rendered by :mod:`motion.synth` from either the reference itself --
time-warped (C known), re-articulated on a few joints (A known), turned and moved (T known)
-- or another performer's BVH of the same action (``student=``): then the true C is the
monotone alignment of the two true 3-D motions, root-normalised (each frame's joints in its
root's frame; :func:`true_correspondence`), up to the reference's own repetitions: a walk
matches another gait cycle of the reference almost as well, so every alignment about as good
(:func:`true_correspondences`) is true, and the one nearest the registration's C scores it
(``c_err_mean_best_truth``: against the best one alone; ``c_truths``: how many there are;
``c_posture_excess`` and ``_stage1``: how much farther, as a share, the student's postures
lie from the reference's along the registration's C than along the best true one -- a C
within :data:`TRUTH_TIE` of it matches the student's postures as well as an equally true
alignment does, whatever its distance in frames; NaN for the reference itself);
the true A is the student's local rotations relative to the reference's at that C. :func:`motion.registration.register` recovers C, T
and A from the silhouettes, edges and colours (and 2-D joints with ``keypoints=true``).

Metrics: ``c_err_mean`` and ``c_err_mean_stage1`` (reference frames, after refinement and
after stage 1), ``t_rot_err_deg_mean`` (root rotation), ``t_pos_err_mean`` (root position,
fraction of height), ``a_err_deg_mean`` (articulation error over the joints the body parts
drive, mean over joints and frames), ``e3d_mean`` (joint positions, fraction of height),
``silhouette_iou_mean``; ``motions_match`` (1: :func:`motion.registration.movement.
check_movement` finds the reference's movement, as ``motion register`` reports it) with its
evidence ``travel_ratio``, ``c_stalled_fraction``, ``c_fast_fraction``, ``c_held_fraction``
(video frames at the ends holding C's first or last reference frame, left out of the check),
``student_froude`` and ``reference_froude`` (the gait check's Froude numbers; NaN: not
measured; ``..._peak``: the largest over 1 s windows) and ``student_froude_true`` (from
the true root and the student's own legs), ``student_straightness`` and
``reference_straightness`` (the paths' net displacement over length: the back-and-forth
check) beside ``student_straightness_true`` (the true root's; per_frame.csv carries the
registered and the true root, ``root_x`` ... ``root_true_z``, to reread the checks offline);
``a_swing_err_deg_mean`` is the articulation error without the twist about each bone (what a capsule body can show); ``a_err_deg_mean_no_change`` and
``a_swing_err_deg_mean_no_change`` score the anchor "no articulation difference" (A =
identity) the same way: the size of the true A, what a registration that recovers nothing
of it scores; ``a_err_deg_mean_long_bones`` (and ``_no_change``) the same over the joints
whose bone is at least :data:`LONG_BONE` of the height (thighs, shins, upper arms,
forearms); ``bone_dir_err_deg_mean`` (and ``_no_change``: the reference's rotations at C under
the estimated T) the angle between those bones' estimated and true directions in the world,
from joint positions -- the articulation as an image shows it, free of the twist about a
bone that local rotations carry into every child, and of the two skeletons' rest poses;
``sec_polish`` the posture polish's seconds; ``findings_stated`` (how many of the
summary's largest differences ``motion register`` would state), ``findings_agree_fraction``
(of those, the share that agree with the truth in sign and within
:data:`FINDING_AGREE_DEG`: the true difference of clinical angles, :mod:`motion.angles`, over
the finding's frames, the student's true angle minus the reference's at the true C; NaN when
none is stated) and ``findings_withheld_fraction`` (of the largest differences, the share not
stated); ``angle_diff_err_deg_rms`` (per frame and coordinate, the estimated difference's
error), ``angle_uncertainty_deg_rms`` (the uncertainty stated for it) and
``angle_err_within_2u`` (how often the error is within twice it: ~0.95 for an honest
uncertainty); ``sec_per_video_frame`` and per stage in timings.json.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from experiments.config import ConfigError, ExperimentConfig
from experiments.progress import note, progress
from experiments.stick_time import BUNDLED
from motion.alignment import chain_align
from motion.angles import COORDINATES, ClinicalAngles, SegmentMap, clinical_angles
from motion.body.observation import PartShapes
from motion.geometry import euler_to_matrix, rotation_about_y
from motion.kinematics import forward_kinematics
from motion.metrics import rotation_angle_error_deg
from motion.registration import Reference, RegistrationSettings, register
from motion.registration.approximate import Stage1Settings
from motion.registration.config import override, parse_value
from motion.registration.export import (
    TRUSTED_FIT,
    joint_angles,
    leg_lengths_m,
    summarise,
)
from motion.registration.inputs import features_from_sequence
from motion.registration.movement import (
    MovementSettings,
    check_movement,
    froude_number,
    leg_length_m,
    net_displacement_m,
    path_straightness,
)
from motion.registration.pipeline import silhouette_iou
from motion.registration.polish import PosturePolishSettings
from motion.registration.refine import RefineSettings, place_poses
from motion.registration.types import VideoFeatures, paired_part, scaled_spec
from motion.settings import setting
from motion.synth import SynthConfig, synthesize

TIMINGS = ("sec_per_video_frame", "sec_stage1", "sec_stages23")
#: a stated finding agrees with the truth when its sign is the true one and it is within this
#: many degrees of the true mean difference over its frames (the issue's criterion)
FINDING_AGREE_DEG = 5.0
#: the parts whose length a limb's two detected joints span (the proportions' limb metric)
LIMB_PARTS = ("upper_arm", "forearm", "thigh", "shin")


@dataclass
class SyntheticStudentConfig(ExperimentConfig):
    """The synthetic student of the experiments that register one (:func:`synthetic_inputs`):
    its source motion, time warp, articulation, cameras and images, and the registration's
    settings by dotted key."""

    reference: str = setting(BUNDLED, "reference BVH", path="file")
    student: str = setting(
        "",
        "another performer's BVH of the same action as the student (empty: the reference "
        "itself, time-warped and re-articulated)",
    )
    warp_seed: int = setting(0, "seed of the synthetic student (time warp, articulation)", ge=0)
    warp: float = setting(0.3, "largest relative change of playback speed", ge=0, lt=1)
    articulation: dict[str, float] = setting(
        {"LeftLeg": 15.0, "RightForeArm": 20.0},
        "joint -> largest articulation offset of the student, degrees (motion synth's)",
        ge=0,
        le=90,
    )
    yaw_deg: float = setting(30.0, "the student's turn about the vertical over the video")
    fps: float = setting(25.0, "video frame rate, Hz", gt=0, le=240)
    cameras: int = setting(1, "static cameras around the student", ge=1, le=8)
    size: list[int] = setting([320, 240], "image width, height in pixels", length=2, ge=32)
    focal_px: float = setting(450.0, "focal length, pixels", gt=0)
    keypoints: bool = setting(False, "give noisy 2-D joints as an extra observation")
    frames: int = setting(0, "use the first N video frames only (0: all)", ge=0)
    registration: dict[str, str] = setting(
        {},
        "any other setting of the registration by its dotted key, as `motion register` names "
        "it under `registration` (refine.articulation_std: 0.15), its value read as on "
        "`motion register`'s command line; applied after the fields above",
    )


@dataclass
class RegisterSyntheticConfig(SyntheticStudentConfig):
    """Fields of ``experiments/configs/register_synthetic.yaml``."""

    NAME = "register_synthetic"
    TINY_DOC = "a quick run (8 frames, 30 particles, 2 iterations)"
    TINY: ClassVar[dict] = {"frames": 8, "particles": 30, "iterations": 2, "restarts": 1}

    particles: int = setting(100, "particles per part (stages 2-3)", ge=2, le=2000)
    iterations: int = setting(5, "particle BP iterations per run", ge=1, le=50)
    restarts: int = setting(2, "annealing runs", ge=1, le=10)
    refine_c: bool = setting(True, "stage 3: refine C through the body graph")
    scale: float = setting(0.0, "the body scale G if known (0: estimated)", ge=0)
    polish_steps: int = setting(
        50,
        "steps of the posture polish after stages 2-3 (motion register's default; 0: none)",
        ge=0,
    )
    proportion_steps: int = setting(
        0,
        "steps of the polish's fit of the student's proportions, where there are 2-D joints "
        "(0, motion register's default: the reference's proportions; 100: fitted)",
        ge=0,
    )
    device: str = setting(
        "cpu",
        "where the registration runs: cpu, cuda or cuda:N (the runner then holds a GPU for "
        "the run; RegistrationSettings.device)",
    )

    def gpus(self) -> int:
        return int(self.device.startswith("cuda"))


@dataclass
class Truth:
    """The synthetic student's true C, T and A."""

    C: Tensor  # (T',) long reference frames
    rotation: Tensor  # (T', 3, 3) root
    position: Tensor  # (T', 3) root, metres
    local: Tensor  # (T', J, 3, 3) the student's local rotations
    joints: Tensor  # (T', J, 3) metres
    height: float  # metres
    #: (A, T') every equally true C (:func:`true_correspondences`), C first
    C_alternatives: Tensor
    #: (T', T) metres, :func:`posture_cost` of the student against the reference (another
    #: performer only; ``None`` for the reference itself)
    posture_cost: Tensor | None = None


def posture_cost(student: Reference, shown: Tensor, reference: Reference) -> Tensor:
    """``(T', T)`` metres: the mean distance of the joints (matched by name) of student frame
    ``shown[t']`` and reference frame t, each in its root's frame."""
    names = [n for n in student.skeleton.names if n in reference.skeleton.names]
    si = [student.skeleton.index(n) for n in names]
    ri = [reference.skeleton.index(n) for n in names]
    a = student.body_frames(shown).positions[:, si]  # (T', J, 3)
    b = reference.body_frames(torch.arange(reference.num_frames)).positions[:, ri]
    return (a[:, None] - b[None]).norm(dim=-1).mean(-1)


def truth_max_step(shown: Tensor) -> int:
    """The true alignment's largest step: twice the mean reference frames per video frame
    that the student's ``shown`` frames advance."""
    return max(1, math.ceil(2 * (shown[-1] - shown[0]).item() / max(1, len(shown) - 1)))


def true_correspondence(student: Reference, shown: Tensor, reference: Reference) -> Tensor:
    """The monotone alignment of two true 3-D motions, root-normalised: video frame t'
    (student frame ``shown[t']``) -> the reference frame whose joints in the root's frame are
    closest on average (chain Viterbi, steps 0..S with S twice the frame ratio, free ends).
    Joints are matched by name."""
    return chain_align(posture_cost(student, shown, reference), truth_max_step(shown)).path[0]


#: alignments of two performers' motions whose mean posture distance is within this share of
#: the best one's are equally true. A periodic movement (a walk) matches the reference's
#: cycles almost equally well: subject 7's walk against subject 2's, the best alignment
#: 0.072 m on average and the one a gait cycle earlier 0.076 (+5.6 %), the next distinct
#: one +22 %. A registration that picks any of the equally true ones is right.
TRUTH_TIE = 0.1


def true_correspondences(
    student: Reference, shown: Tensor, reference: Reference, tie: float = TRUTH_TIE
) -> Tensor:
    """``(A, T')`` long: :func:`true_correspondence` first, then the other locally best
    alignments (one per start frame C(0) that is a local minimum of the best cost given
    that start) whose mean posture distance is within ``tie`` of the best one's -- the
    truth up to the reference's own repetitions (another gait cycle)."""
    return equally_true_alignments(
        posture_cost(student, shown, reference), truth_max_step(shown), tie
    )


def equally_true_alignments(cost: Tensor, max_step: int, tie: float = TRUTH_TIE) -> Tensor:
    """``(A, T')`` long: the monotone alignments of the ``(T', T)`` distance table ``cost``
    (:func:`motion.alignment.chain_align`, steps 0..``max_step``, free ends) that are equally
    true: the best one first, then, per start frame C(0) that is a local minimum of the best
    total given that start (and more than a step from the best one's), its best alignment
    when that total is within ``tie`` of the best one's."""
    best = chain_align(cost, max_step)
    n = cost.shape[1]
    totals, paths = [], []
    for starts in torch.arange(n).split(64):
        batch = cost[None].repeat(len(starts), 1, 1)
        only = torch.full((len(starts), n), math.inf, dtype=cost.dtype)
        only[torch.arange(len(starts)), starts] = 0.0
        batch[:, 0] += only
        fixed = chain_align(batch, max_step)
        totals.append(fixed.cost)
        paths.append(fixed.path)
    total, path = torch.cat(totals), torch.cat(paths)
    limit = float(best.cost[0]) * (1 + tie)
    out = [best.path[0]]
    for s in range(n):
        local = (s == 0 or total[s] <= total[s - 1]) and (s == n - 1 or total[s] <= total[s + 1])
        distinct = abs(s - int(best.path[0, 0])) > max_step
        if local and distinct and float(total[s]) <= limit:
            out.append(path[s])
    return torch.stack(out)


def nearest_truth(c: Tensor, alternatives: Tensor) -> int:
    """The row of ``alternatives`` ``(A, T')`` nearest C ``(T',)`` on average."""
    return int((alternatives - c).abs().double().mean(-1).argmin())


def synthetic_truth(seq, reference: Reference, student: Reference | None) -> Truth:
    """The true C, T and A of the synthetic student ``seq`` (``motion synth``'s arrays):
    ``student`` is the other performer it was rendered from (``None``: the reference
    itself, whose true C is the one shown; otherwise every equally true C,
    :func:`true_correspondences`)."""
    arrays = seq.arrays
    shown = torch.from_numpy(arrays["C_shown"]).long()
    source = student or reference
    local = source.rotations[shown].clone()
    a_deg = torch.from_numpy(arrays["A_deg"])
    for j in range(source.skeleton.num_joints):
        if bool((a_deg[:, j] != 0).any()):
            order = source.skeleton.rotation_orders[j] or "ZYX"
            local[:, j] = local[:, j] @ euler_to_matrix(torch.deg2rad(a_deg[:, j]), order)
    rotation = rotation_about_y(torch.from_numpy(arrays["T_yaw_rad"])) @ local[:, 0]
    joints = torch.from_numpy(arrays["joints3d"])
    cost = None
    if student is None:
        alternatives = shown[None]
    else:
        alternatives = true_correspondences(student, shown, reference)
        cost = posture_cost(student, shown, reference)
    height = float((joints[..., 1].amax(-1) - joints[..., 1].amin(-1)).mean())
    return Truth(alternatives[0], rotation, joints[:, 0], local, joints, height, alternatives, cost)


def posture_excess(cost: Tensor | None, c: Tensor, best: Tensor) -> float:
    """How much farther the student's postures lie from the reference's along ``c`` than
    along ``best`` (``(T',)`` reference frames; ``cost`` ``(T', T)``, :func:`posture_cost`):
    mean distance along ``c`` over mean along ``best``, minus 1 (0 where both are 0, inf
    where only the truth's is: a student identical to the reference); NaN without a cost."""
    if cost is None:
        return math.nan
    frames = torch.arange(len(c))
    along, truth = float(cost[frames, c].mean()), float(cost[frames, best].mean())
    if truth == 0.0:
        return 0.0 if along == 0.0 else math.inf
    return along / truth - 1.0


def _bone_directions(reference: Reference, joints: list[int]) -> Tensor:
    """``(J', 3)`` unit direction of each joint's bone in its own frame: the mean offset of
    its children (what a capsule shows of the joint's rotation)."""
    offsets, parents = reference.skeleton.offsets, reference.skeleton.parents
    out = []
    for j in joints:
        children = (parents == j).nonzero().flatten()
        d = offsets[children].mean(0) if len(children) else offsets[j]
        out.append(torch.nn.functional.normalize(d, dim=0))
    return torch.stack(out)


#: a bone counts as long (its direction visible in a small image) at this share of the height
LONG_BONE = 0.12


def _long_bones(reference: Reference, joints: list[int]) -> list[int]:
    """Positions in ``joints`` whose bone (the mean offset of the joint's children) is at
    least :data:`LONG_BONE` of the reference's height in its rest pose."""
    offsets, parents = reference.skeleton.offsets, reference.skeleton.parents
    rest = reference.body_frames(torch.zeros(1, dtype=torch.long)).positions[0]
    height = float(rest[:, 1].amax() - rest[:, 1].amin())
    out = []
    for i, j in enumerate(joints):
        children = (parents == j).nonzero().flatten()
        bone = offsets[children].mean(0) if len(children) else offsets[j]
        if float(bone.norm()) >= LONG_BONE * height:
            out.append(i)
    return out


def _bone_direction_error_deg(
    reference: Reference, joints: list[int], estimated: Tensor, true: Tensor
) -> Tensor:
    """``(T', J')`` degrees: the angle between each bone's estimated and true direction in
    the world (from the joint to the mean of its children), from joint positions ``(T', J,
    3)`` -- the articulation as an image shows it, free of the twist about a bone and of
    how each skeleton's rest pose sets its local frames."""
    parents = reference.skeleton.parents
    children = [(parents == j).nonzero().flatten() for j in joints]

    def directions(positions: Tensor) -> Tensor:
        bones = [
            positions[:, c].mean(1) - positions[:, j] for j, c in zip(joints, children, strict=True)
        ]
        return torch.nn.functional.normalize(torch.stack(bones, 1), dim=-1)

    cos = (directions(estimated.double()) * directions(true.double())).sum(-1)
    return torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))


def _swing_error_deg(a_true: Tensor, a_est: Tensor, directions: Tensor) -> Tensor:
    """The articulation error a capsule can show: the angle between the bone directions
    ``(J', 3)`` turned by the true and the estimated A ``(T', J', 3, 3)`` (its twist about
    the bone left out). ``(T', J')`` degrees."""
    u = (a_true @ directions[..., None]).squeeze(-1)
    v = (a_est @ directions[..., None]).squeeze(-1)
    return torch.rad2deg(torch.acos((u * v).sum(-1).clamp(-1, 1)))


def _student_joints(
    reference: Reference,
    rotations: Tensor,
    root: Tensor,
    scale: float,
    joint_scales: Tensor | None = None,
):
    offsets = reference.skeleton.offsets.to(rotations) * scale
    if joint_scales is not None:
        offsets = offsets * joint_scales.to(rotations)[:, None]
    zero = torch.zeros(rotations.shape[0], 3, dtype=rotations.dtype)
    fk = forward_kinematics(reference.skeleton, rotations, zero, offsets)
    return fk.positions - fk.positions[:, :1] + root[:, None]


def _settings(cfg: RegisterSyntheticConfig) -> RegistrationSettings:
    refine = RefineSettings(
        particles=cfg.particles,
        iterations=cfg.iterations,
        restarts=cfg.restarts,
        refine_c=cfg.refine_c,
        # C's band: 24 reference frames either side (RefineSettings: 12). Stage 1 can stall a
        # few frames where the legs pass and leave the truth ~24 frames off; the narrower band
        # could not reach it (docs/decisions/004-tuning-evidence.md)
        band=min(24, (cfg.particles - 1) // 2),
    )
    return registration_settings(
        cfg,
        stage1=Stage1Settings(),
        refine=refine,
        polish=PosturePolishSettings(steps=cfg.polish_steps, proportion_steps=cfg.proportion_steps),
        scale=cfg.scale or None,
        seed=cfg.seed,
        device=cfg.device,
    )


@dataclass
class SyntheticInputs:
    """What :func:`synthetic_inputs` makes of a :class:`SyntheticStudentConfig`."""

    reference: Reference
    student: Reference | None  # the other performer (None: the reference itself)
    video: VideoFeatures
    truth: Truth


def synth_config(cfg: SyntheticStudentConfig) -> SynthConfig:
    """The :class:`motion.synth.SynthConfig` that renders ``cfg``'s student."""
    return SynthConfig(
        fps=cfg.fps,
        warp=cfg.warp,
        articulation=dict(cfg.articulation) if not cfg.student else {},
        yaw_deg=cfg.yaw_deg,
        cameras=cfg.cameras,
        size=list(cfg.size),
        focal_px=cfg.focal_px,
        seed=cfg.warp_seed,
    )


def synthetic_inputs(cfg: SyntheticStudentConfig) -> SyntheticInputs:
    """The synthetic student of ``cfg`` rendered (:func:`motion.synth.synthesize`), its video
    features and its truth (:func:`synthetic_truth`), cut to ``cfg.frames`` if set: only
    those frames are rendered, the truth is the whole video's (a DP over all its frames),
    then cut."""
    synth, other = synth_config(cfg), cfg.student or None
    seq = synthesize(cfg.reference, synth, student=other, frames=cfg.frames or None)
    whole = synthesize(cfg.reference, synth, student=other, images=False) if cfg.frames else seq
    reference = Reference.from_bvh(cfg.reference)
    student = Reference.from_bvh(cfg.student) if cfg.student else None
    if student is not None and student.skeleton.names != reference.skeleton.names:
        raise ConfigError(
            f"student: {cfg.student} has other joints than {cfg.reference}; expected the "
            "same skeleton (the true A compares joints by name)"
        )
    truth = synthetic_truth(whole, reference, student)
    video = features_from_sequence(seq, keypoints=cfg.keypoints)
    if cfg.frames:
        video, truth = _first(video, truth, cfg.frames)
    return SyntheticInputs(reference, student, video, truth)


def registration_settings(cfg: SyntheticStudentConfig, **fields) -> RegistrationSettings:
    """:class:`RegistrationSettings` of ``fields``, then ``cfg.registration``'s dotted keys
    (a bad key or value: a :class:`ConfigError` naming it)."""
    settings = RegistrationSettings(**fields)
    for key, value in cfg.registration.items():
        settings = override(settings, key, parse_value(value), where="registration")
    return settings


def run(cfg: RegisterSyntheticConfig):
    inputs = synthetic_inputs(cfg)
    reference, student, video, truth = inputs.reference, inputs.student, inputs.video, inputs.truth
    n = video.num_frames
    note(f"register_synthetic: {n} video frames, {reference.num_frames} reference frames")
    t0 = time.perf_counter()
    result = register(reference, video, settings=_settings(cfg), progress=progress, log=note)
    seconds = time.perf_counter() - t0
    first_c = truth.C
    truth = dataclasses.replace(
        truth, C=truth.C_alternatives[nearest_truth(result.C, truth.C_alternatives)]
    )

    driven = sorted(set(reference.spec.frame_joints.tolist()) - {0})
    a_true = reference.rotations[truth.C].transpose(-1, -2) @ truth.local
    a_err = rotation_angle_error_deg(a_true[:, driven], result.A[:, driven])  # (T', J')
    swing = _swing_error_deg(
        a_true[:, driven], result.A[:, driven], _bone_directions(reference, driven)
    )
    # the anchor: "the student moves as the reference" (A = identity) scored the same way
    no_change = torch.eye(3, dtype=a_true.dtype).expand_as(a_true[:, driven])
    a_err0 = rotation_angle_error_deg(a_true[:, driven], no_change)
    swing0 = _swing_error_deg(a_true[:, driven], no_change, _bone_directions(reference, driven))
    # the long bones (thighs, shins, upper arms, forearms...): the joints whose bone is at
    # least LONG_BONE of the body's height, whose direction an image can show; hands, feet
    # and the neck turn short bones that a 320 px silhouette hardly shows
    long = _long_bones(reference, driven)
    t_rot = rotation_angle_error_deg(truth.rotation, result.T_rotation)
    t_pos = (truth.position - result.T_translation).norm(dim=-1) / truth.height
    joints = _student_joints(
        reference, result.rotations, result.T_translation, result.G, result.joint_scales()
    )
    e3d = (joints - truth.joints).norm(dim=-1).mean(-1) / truth.height
    long_joints = [driven[i] for i in long]
    bone_err = _bone_direction_error_deg(reference, long_joints, joints, truth.joints)
    unchanged = _unchanged(reference, result)
    bone_err0 = _bone_direction_error_deg(
        reference,
        long_joints,
        _student_joints(reference, unchanged, result.T_translation, result.G),
        truth.joints,
    )
    movement = check_movement(
        result.C,
        result.T_translation,
        reference.root,
        reference.frame_rate,
        video.frame_rate,
        result.G,
        legs_m=leg_lengths_m(result, reference),
        in_view=video.within_sides(),
    )
    angles = joint_angles(result, reference, video.frame_rate)
    trusted = (result.fit >= TRUSTED_FIT) & ~movement.held(result.num_frames)
    summary = summarise(
        result,
        reference,
        angles,
        video.frame_rate,
        {},
        trusted=trusted,
        movement=movement,
        cameras=cfg.cameras,
    )
    truth_diff = true_differences(reference, student, truth)
    keep = [COORDINATES.index(c) for c in angles.coordinates]
    findings = finding_agreement(
        summary.largest_differences, angles.time_s, truth_diff[:, keep], angles.coordinates
    )
    findings |= angle_error_metrics(angles, truth_diff[:, keep], result.fit >= TRUSTED_FIT)
    c_err = (result.C - truth.C).abs().double()
    c_err1 = (result.C_stage1 - truth.C).abs().double()
    metrics = {
        "c_err_mean": float(c_err.mean()),
        "c_err_mean_stage1": float(c_err1.mean()),
        "c_err_mean_best_truth": float((result.C - first_c).abs().double().mean()),
        "c_truths": len(truth.C_alternatives),
        "c_posture_excess": posture_excess(truth.posture_cost, result.C, first_c),
        "c_posture_excess_stage1": posture_excess(truth.posture_cost, result.C_stage1, first_c),
        "t_rot_err_deg_mean": float(t_rot.mean()),
        "t_pos_err_mean": float(t_pos.mean()),
        "a_err_deg_mean": float(a_err.mean()),
        "a_swing_err_deg_mean": float(swing.mean()),
        "a_err_deg_mean_no_change": float(a_err0.mean()),
        "a_swing_err_deg_mean_no_change": float(swing0.mean()),
        "a_err_deg_mean_long_bones": float(a_err[:, long].mean()),
        "a_err_deg_mean_long_bones_no_change": float(a_err0[:, long].mean()),
        "bone_dir_err_deg_mean": float(bone_err.mean()),
        "bone_dir_err_deg_mean_no_change": float(bone_err0.mean()),
        **proportion_errors(reference, student, result),
        "sec_polish": result.timings.get("polish", 0.0),
        "e3d_mean": float(e3d.mean()),
        "silhouette_iou_mean": float(result.fit.mean()),
        **_iou_of_alternatives(reference, video, result, truth),
        "G": float(result.G),
        "motions_match": float(movement.motions_match),
        "travel_ratio": movement.student_travel_m / max(movement.reference_travel_m, 1e-9),
        "c_stalled_fraction": float((result.C.diff() == 0).double().mean()),
        "c_fast_fraction": movement.fast_fraction,
        "c_held_fraction": (movement.held_start + movement.held_end) / n,
        "student_froude": movement.student_froude,
        "reference_froude": movement.reference_froude,
        "student_froude_peak": movement.student_froude_peak,
        "reference_froude_peak": movement.reference_froude_peak,
        "student_froude_true": _true_froude(student or reference, truth, video.frame_rate),
        "student_straightness": movement.student_straightness,
        "reference_straightness": movement.reference_straightness,
        "student_straightness_true": _true_straightness(truth, video.frame_rate),
        **findings,
        "sec_per_video_frame": seconds / n,
        "sec_stage1": result.timings["stage1"],
        "sec_stages23": result.timings["stages23"],
    }
    columns = {
        "frame": np.arange(n),
        "time_s": angles.time_s.numpy(),
        "c_true": truth.C.numpy(),
        "c_stage1": result.C_stage1.numpy(),
        "c": result.C.numpy(),
        "a_err_deg": a_err.mean(-1).numpy(),
        "t_rot_err_deg": t_rot.numpy(),
        "e3d": e3d.numpy(),
        "silhouette_iou": result.fit.numpy(),
        "trusted": trusted.numpy().astype(int),
        # the registered and the true root, metres: the movement check's paths, for
        # rereading the check offline
        **{f"root_{a}": result.T_translation[:, i].numpy() for i, a in enumerate("xyz")},
        **{f"root_true_{a}": truth.position[:, i].numpy() for i, a in enumerate("xyz")},
        **angle_columns(angles, truth_diff[:, keep]),
    }
    joint_names = [reference.skeleton.names[j] for j in driven]
    for f in summary.largest_differences:  # what each finding says against the truth
        true = true_mean(f, angles.time_s, truth_diff[:, keep], angles.coordinates)
        agrees = "agrees" if _agrees(f, true) else "disagrees"
        note(
            f"finding ({'stated' if f['stated'] else 'withheld'}): {f['text']}; true "
            f"{true:+.1f} degrees: {agrees}{'; ' + f['why'] if f['why'] else ''}"
        )
    data = {"columns": columns, "joints": joint_names, "joint_err": a_err.mean(0).numpy()}
    return metrics, columns, data


def _unchanged(reference: Reference, result) -> Tensor:
    """``(T', J, 3, 3)``: the reference's local rotations at the registration's C, turned by
    its T (A = identity: "the student moves as the reference")."""
    rotations = reference.rotations[result.C].clone()
    rotations[:, 0] = result.T_rotation
    return rotations


def _iou_of_alternatives(reference: Reference, video, result, truth: Truth) -> dict[str, float]:
    """How well two other postures on the registration's own body (its G and proportions)
    cover the silhouettes, scored as its fit is (mean IoU over frames and cameras):

    * ``silhouette_iou_truth_mean``: the student's true posture (local rotations, root
      rotation and position). Where it scores no better than the registration's, the
      silhouettes on this body cannot tell the student's articulation from the estimate's:
      a floor of the observation, not of the inference.
    * ``silhouette_iou_no_change_mean``: the reference's posture at the registration's C,
      placed by its T (A = identity): what the articulation adds to the fit.
    """
    scales = result.joint_scales()
    spec = scaled_spec(
        reference.spec,
        result.G,
        None if result.proportions is None else result.proportions.part_scales,
    )
    shapes = PartShapes(spec.shapes.axis.float(), spec.shapes.radii.float())
    unchanged = _unchanged(reference, result)
    out = {}
    for name, rotations, root in (
        ("truth", truth.local.clone(), truth.position),
        ("no_change", unchanged, result.T_translation),
    ):
        if name == "truth":
            rotations[:, 0] = truth.rotation
        posture = reference.posture_poses(rotations, result.G, scales)
        poses = place_poses(rotations[:, 0], root, posture).float()
        iou = silhouette_iou(shapes, video.cameras, video.observation.silhouette[0], poses)
        out[f"silhouette_iou_{name}_mean"] = float(iou.mean())
    return out


def true_part_scales(reference: Reference, student: Reference | None) -> Tensor:
    """``(P,)`` each body part's true length factor: the student's capsule axis over the
    reference's (each measured on its own motion, :class:`motion.body.spec.BodySpec`; one
    bone per limb part, so its length ratio); all 1 for the reference itself."""
    if student is None:
        return torch.ones(reference.spec.num_parts, dtype=torch.float64)
    return student.spec.shapes.axis.norm(dim=-1) / reference.spec.shapes.axis.norm(dim=-1)


def _true_froude(owner: Reference, truth: Truth, rate: float) -> float:
    """The synthetic student's true Froude number over the whole video (its root's net
    speed, the mean positions over ``MovementSettings().end_window_s`` at each end, and the
    standing hip height of ``owner``'s skeleton, the student's)."""
    n = truth.position.shape[0]
    k = max(1, min(round(MovementSettings().end_window_s * rate), n // 2))
    if n - k <= 0:
        return math.nan
    speed = net_displacement_m(truth.position, k) / ((n - k) / rate)
    segments = SegmentMap.from_roles(owner.skeleton, owner.model.mapping)
    leg = leg_length_m(owner.skeleton, owner.skeleton.offsets, segments)
    return froude_number(speed, leg)


def _true_straightness(truth: Truth, rate: float) -> float:
    """The true root's path straightness over the video, as the movement check measures the
    registered one's (:func:`motion.registration.movement.path_straightness`)."""
    window = max(1, round(MovementSettings().path_window_s * rate))
    return path_straightness(truth.position.double(), window)[0]


def proportion_errors(reference: Reference, student: Reference | None, result) -> dict[str, float]:
    """The estimated part lengths (G times the proportions) against the truth, percent:
    ``scale_err_pct_mean`` / ``_max`` over the parts, and ``proportion_err_pct_mean`` /
    ``_max`` of their shape alone (both divided by their geometric mean: what one
    perspective camera can tell, with the body's size traded against its depth), and
    ``proportion_err_pct_mean_limbs`` over :data:`LIMB_PARTS` alone; each with
    its ``_no_change`` anchor (G alone, the reference's proportions); NaN-free."""
    truth = true_part_scales(reference, student)
    estimate = torch.full_like(truth, float(result.G))
    anchor = estimate.clone()
    if result.proportions is not None:
        estimate = estimate * result.proportions.part_scales.to(truth)
    names = reference.spec.part_names
    limbs = [i for i, n in enumerate(names) if (paired_part(n) or n) in LIMB_PARTS]
    out = {}
    for name, est in (("", estimate), ("_no_change", anchor)):
        ratio = est / truth
        shape = ratio / ratio.log().mean().exp()
        out[f"scale_err_pct_mean{name}"] = float((ratio - 1).abs().mean() * 100)
        out[f"scale_err_pct_max{name}"] = float((ratio - 1).abs().max() * 100)
        out[f"proportion_err_pct_mean{name}"] = float((shape - 1).abs().mean() * 100)
        out[f"proportion_err_pct_max{name}"] = float((shape - 1).abs().max() * 100)
        out[f"proportion_err_pct_mean_limbs{name}"] = float((shape[limbs] - 1).abs().mean() * 100)
    parts = ", ".join(
        f"{n} {float(e):.3f}/{float(t):.3f}" for n, e, t in zip(names, estimate, truth, strict=True)
    )
    note(f"part lengths, estimated (G x proportions) / true: {parts}")
    return out


def clinical_angles_of(body: Reference, rotations: Tensor) -> ClinicalAngles:
    """:func:`motion.angles.clinical_angles` of local ``rotations`` ``(..., J, 3, 3)`` on
    ``body``'s skeleton, its segments found from its roles."""
    segments = SegmentMap.from_roles(body.skeleton, body.model.mapping)
    return clinical_angles(body.skeleton, rotations, segments)


def true_differences(reference: Reference, student: Reference | None, truth: Truth) -> Tensor:
    """``(T', K)`` degrees: per video frame and coordinate of :data:`motion.angles.
    COORDINATES`, the student's true clinical angle (on its own skeleton) minus the
    reference's at the true C, wrapped to [-180, 180)."""
    mine = clinical_angles_of(student or reference, truth.local).degrees
    theirs = clinical_angles_of(reference, reference.rotations[truth.C]).degrees
    return torch.remainder(mine - theirs + 180.0, 360.0) - 180.0


def true_mean(finding: dict, time_s: Tensor, truth: Tensor, names: list[str]) -> float:
    """The true mean difference (degrees) over a finding's frames."""
    frames = (time_s >= finding["start_s"] - 1e-9) & (time_s <= finding["end_s"] + 1e-9)
    return float(truth[frames, names.index(finding["coordinate"])].mean())


def _agrees(finding: dict, true: float) -> bool:
    est = float(finding["mean_difference_deg"])
    return bool(np.sign(est) == np.sign(true) and abs(est - true) <= FINDING_AGREE_DEG)


def finding_agreement(
    findings: list[dict], time_s: Tensor, truth: Tensor, names: list[str]
) -> dict[str, float]:
    """Score the findings of a summary (:attr:`RegistrationSummary.largest_differences`)
    against true differences ``truth`` ``(T', K)`` (columns ``names``) at video times
    ``time_s`` ``(T',)``: a stated finding agrees when the true mean difference over its
    frames (``start_s`` to ``end_s``) has its sign and lies within
    :data:`FINDING_AGREE_DEG` of it (a true difference of exactly 0, a joint the student
    moves as the reference does, has no sign: any finding there disagrees).

    Returns:
        ``findings_stated``, ``findings_agree_fraction`` (NaN when none is stated) and
        ``findings_withheld_fraction`` (NaN when there is no finding at all).
    """
    stated = [f for f in findings if f["stated"]]
    agree = sum(int(_agrees(f, true_mean(f, time_s, truth, names))) for f in stated)
    return {
        "findings_stated": float(len(stated)),
        "findings_agree_fraction": agree / len(stated) if stated else math.nan,
        "findings_withheld_fraction": (1 - len(stated) / len(findings) if findings else math.nan),
    }


def angle_columns(angles, truth: Tensor) -> dict[str, np.ndarray]:
    """Per-frame columns of each estimated coordinate: ``diff_<name>`` (the estimated
    difference, degrees), ``true_<name>`` (the true one, ``truth`` ``(T', K')``) and
    ``unc_<name>`` (the inference's uncertainty; absent without one): what a calibration of
    the findings' method error reads back from the run records
    (:mod:`experiments.findings_calibration`)."""
    out = {}
    for k, name in enumerate(angles.coordinates):
        out[f"diff_{name}"] = angles.difference_deg[:, k].numpy()
        out[f"true_{name}"] = truth[:, k].numpy()
        if angles.uncertainty_deg is not None:
            out[f"unc_{name}"] = angles.uncertainty_deg[:, k].numpy()
    return out


def angle_error_metrics(angles, truth: Tensor, trusted: Tensor) -> dict[str, float]:
    """How well the per-frame differences and their uncertainty match the truth, over the
    trusted frames and every coordinate: ``angle_diff_err_deg_rms`` (RMS of estimated minus
    true difference, degrees), ``angle_uncertainty_deg_rms`` (RMS of the stated
    uncertainty) and ``angle_err_within_2u`` (the share of errors within twice their
    uncertainty: about 0.95 if the uncertainty were honest and normal; NaN without one)."""
    err = (angles.difference_deg - truth)[trusted]
    out = {"angle_diff_err_deg_rms": float(err.square().mean().sqrt())}
    if angles.uncertainty_deg is None:
        return out | {"angle_uncertainty_deg_rms": math.nan, "angle_err_within_2u": math.nan}
    u = angles.uncertainty_deg[trusted]
    ok = torch.isfinite(u)
    out["angle_uncertainty_deg_rms"] = float(u[ok].square().mean().sqrt())
    out["angle_err_within_2u"] = float((err[ok].abs() <= 2 * u[ok]).double().mean())
    return out


def _first(video, truth: Truth, n: int):
    if n > video.num_frames:
        raise ConfigError(f"frames must be <= {video.num_frames} (the video's); got {n}")
    video = video.cut(slice(0, n))
    cut = Truth(
        truth.C[:n],
        truth.rotation[:n],
        truth.position[:n],
        truth.local[:n],
        truth.joints[:n],
        truth.height,
        truth.C_alternatives[:, :n],
        None if truth.posture_cost is None else truth.posture_cost[:n],
    )
    return video, cut


def plot(path, data, title: str) -> None:
    """Left: true C, stage 1's and the final one against the video frame; right: the mean
    articulation error of each joint."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = data["columns"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), dpi=100)
    ax = axes[0]
    ax.plot(c["frame"], c["c_true"], "-", color="0.2", lw=2, label="true C")
    ax.plot(c["frame"], c["c_stage1"], "--", color="C0", lw=1, label="stage 1")
    ax.plot(c["frame"], c["c"], "-", color="C3", lw=1, label="stages 2-3")
    ax.set_xlabel("video frame t'")
    ax.set_ylabel("reference frame C(t')")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax = axes[1]
    y = np.arange(len(data["joints"]))
    ax.barh(y, data["joint_err"], color="C3")
    ax.set_yticks(y, data["joints"], fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("articulation error, degrees (mean over frames)")
    ax.grid(alpha=0.3, axis="x")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
