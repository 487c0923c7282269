"""What ``python -m motion register`` writes: joint angles, the student's BVH, the result.

From a :class:`~motion.registration.types.Registration` and its
:class:`~motion.registration.types.Reference`:

* :func:`joint_angles` -- the clinical joint angles (:mod:`motion.angles`: OpenSim's
  ``hip_flexion_r``, ``knee_angle_r``, ...) of the reference at C(t') and of the student,
  their signed difference and the joint's whole change (:class:`JointAngles`);
  :func:`joint_flexion` is the bend between two bones, for skeletons without segments;
  :func:`per_joint_mean_abs_deg` and :func:`largest_differences` (:class:`JointDifference`,
  with a sentence for reports); :func:`write_joint_angles_csv` and :func:`write_mot`
  (OpenSim storage) write them;
* :func:`student_bvh` / :func:`write_student_bvh` -- the recovered motion as a BVH on the
  reference's skeleton (its hierarchy, channels and file units; bones scaled by G);
* :func:`save_registration` / :func:`load_registration` -- the whole result as ``.npz``;
* :func:`summarise` -- :class:`RegistrationSummary`, the run in one JSON record.

Conventions: metres and radians inside; degrees in the angle tables and BVH files (as the
format stores them), the BVH file's own length unit in BVH files; video time
``t' / frame_rate`` seconds. Euler angles follow :mod:`motion.geometry`: channels
``Zrotation Yrotation Xrotation`` mean ``R = Rz(a) Ry(b) Rx(c)`` (intrinsic, channel order).
Shapes: ``T'`` video frames, ``J`` skeleton joints, ``K'`` coordinates the registration estimates.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from motion.angles import (
    COORDINATES,
    SegmentMap,
    clinical_angles,
    coordinate_chain,
    coordinate_joints,
    coordinate_segments,
    describe_coordinate,
)
from motion.body.spec import joint_parts
from motion.bvh import BVH, FRAME_TIME_RANGE, read_bvh, write_bvh
from motion.geometry import matrix_to_euler, rotation_angle
from motion.kinematics import FKResult, end_site_positions_by_joint, forward_kinematics
from motion.registration.method_error import MethodError, shipped_method_error
from motion.registration.movement import MovementCheck, leg_length_m
from motion.registration.types import (
    Proportions,
    Reference,
    Registration,
    RegistrationError,
    paired_part,
)
from motion.settings import Settings, setting

__all__ = [
    "FindingSettings",
    "JointAngles",
    "JointDifference",
    "RegistrationSummary",
    "bvh_from_rotations",
    "end_site_positions",  # = motion.kinematics.end_site_positions_by_joint
    "joint_angles",
    "joint_flexion",
    "joints_trusted",
    "largest_differences",
    "load_registration",
    "matrix_to_bvh_euler",  # = motion.geometry.matrix_to_euler
    "per_joint_mean_abs_deg",
    "proportion_words",
    "save_registration",
    "stated_findings",
    "student_bvh",
    "student_kinematics",
    "summarise",
    "trusted_angles",
    "write_joint_angles_csv",
    "write_mot",
    "write_student_bvh",
]

F64 = torch.float64
#: silhouette IoU below which a frame's posture is not trusted: the summary's largest
#: differences leave such frames out, the report greys them (a person leaving the view, a
#: lost limb)
TRUSTED_FIT = 0.5
#: the method's error (degrees) of a coordinate the shipped calibration does not cover
#: (:class:`FindingSettings`): about the RMS over every coordinate on other performers
FALLBACK_METHOD_ERROR_DEG = 12.0
#: seconds of the running median over a joint's difference before the largest ones are
#: looked for (the posture estimate jitters from frame to frame by several degrees)
SMOOTH_S = 0.2
_AXIS = {"X": 0, "Y": 1, "Z": 2}
#: the End Sites ``(..., J, 3)`` by joint, NaN rows where none (kept under its old name)
end_site_positions = end_site_positions_by_joint
#: rotation matrices to BVH Euler angles (kept under its old name)
matrix_to_bvh_euler = matrix_to_euler

# --------------------------------------------------------------------------- flexion


def _outgoing_candidates(parents: list[int], has_end: list[bool], through: bool) -> Tensor:
    """Per joint, the points that may end its outgoing bone, in order of preference:
    ``(J, K)`` long indices into ``[joints, end sites]`` (``J + j`` = End Site of ``j``),
    padded with the joint itself (a zero bone, never chosen). Children first (joints in
    index order, then the End Site); with ``through``, then grandchildren reached through
    children, and so on (breadth first): a zero-length child bone starts where the joint is,
    so the first non-zero bone found from there also leaves the joint."""
    n = len(parents)
    kids: list[list[int]] = [[] for _ in range(n)]
    for j, p in enumerate(parents):
        if p >= 0:
            kids[p].append(j)
    rows = []
    for j in range(n):
        row, level = [], [j]
        while level:
            nxt = []
            for node in level:
                row.extend(kids[node])
                if has_end[node]:
                    row.append(n + node)
                nxt.extend(kids[node])
            level = nxt if through else []
        rows.append(row)
    width = max(1, *(len(r) for r in rows))
    return torch.tensor([r + [j] * (width - len(r)) for j, r in enumerate(rows)], dtype=torch.long)


def joint_flexion(
    positions: Tensor,
    parents: Tensor | list[int],
    end_sites: Tensor | None = None,
    tol: float = 1e-9,
    through_zero_bones: bool = True,
) -> Tensor:
    """Per joint, the bend angle between the bone coming in and the bone going out.

    The incoming bone runs from the joint's parent to the joint; the outgoing one from the
    joint to its first child (in index order, End Site last) whose bone is non-zero. With
    ``through_zero_bones`` a joint whose children all sit on it (zero bones, as CMU's
    ``LeftFingerBase`` on ``LeftHand``) looks on to their children, breadth first. The angle
    is ``atan2(|u x v|, u . v)`` between the two bone vectors: 0 = straight, 180 = folded
    back. It ignores twist about the bones and is invariant to a global rotation, translation
    and scale of the body.

    Args:
        positions: ``(..., J, 3)`` joint positions (any length unit), e.g.
            :attr:`motion.kinematics.FKResult.positions`.
        parents: ``(J,)`` parent index per joint, -1 for the root; parents before children.
        end_sites: optional ``(..., J, 3)`` End Site positions
            (:func:`motion.kinematics.end_site_positions_by_joint`),
            NaN rows for joints without one; used as children where present.
        tol: bones no longer than this (positions' unit) count as zero length.
        through_zero_bones: look past zero-length children (see above).

    Returns:
        ``(..., J)`` degrees; NaN where the joint has no parent, a zero-length incoming bone,
        or no non-zero outgoing bone.
    """
    parents = torch.as_tensor(parents, dtype=torch.long)
    j = parents.shape[0]
    if positions.shape[-2:] != (j, 3):
        raise ValueError(f"positions must be (..., {j}, 3); got {tuple(positions.shape)}")
    if end_sites is not None and end_sites.shape != positions.shape:
        raise ValueError(
            f"end_sites must have the shape of positions {tuple(positions.shape)}; got "
            f"{tuple(end_sites.shape)}"
        )
    if end_sites is None:
        has_end = [False] * j
        ends = torch.full_like(positions, math.nan)
    else:
        ends = end_sites.to(positions)
        has_end = torch.isfinite(ends).all(-1).reshape(-1, j).any(0).tolist()
    cand = _outgoing_candidates(parents.tolist(), has_end, through_zero_bones)  # (J, K)
    points = torch.cat([positions, ends], -2)  # (..., 2J, 3)
    out_vec = points[..., cand, :] - positions[..., :, None, :]  # (..., J, K, 3)
    length = out_vec.norm(dim=-1)
    usable = torch.isfinite(length) & (length > tol)
    first = usable.to(torch.uint8).argmax(-1, keepdim=True)  # first usable candidate
    v = out_vec.gather(-2, first[..., None].expand(*first.shape, 3)).squeeze(-2)
    has_out = usable.any(-1)
    u = positions - positions[..., parents.clamp_min(0), :]
    has_in = (parents >= 0) & (u.norm(dim=-1) > tol)
    angle = torch.rad2deg(torch.atan2(torch.linalg.cross(u, v).norm(dim=-1), (u * v).sum(-1)))
    return torch.where(has_in & has_out, angle, torch.full_like(angle, math.nan))


@dataclass
class JointAngles:
    """Clinical joint angles (:mod:`motion.angles`) per video frame, the reference at C(t')
    against the student.

    Attributes:
        coordinates: ``K'`` OpenSim coordinate names (``hip_flexion_r``, ``knee_angle_l``,
            ``lumbar_extension``, ...): those the registration estimates.
        time_s: ``(T',)`` float64 time of each frame in the source video, seconds (the
            video's clock: its first registered frame ``first_frame`` is at
            ``first_frame / source rate``).
        reference_deg: ``(T', K')`` float64 the reference's angles at C(t'), degrees.
        student_deg: ``(T', K')`` float64 the student's angles, degrees.
        difference_deg: ``(T', K')`` float64 ``student - reference`` in the coordinate's
            positive sense (:func:`motion.angles.describe_coordinate`: positive, the student
            flexes, adducts, ... more), degrees.
        articulation_deg: ``(T', K')`` float64 the angle of the rotation between the
            reference's and the student's joint (the whole change at the coordinate's joint,
            twist included; the three coordinates of a joint share it), degrees.
        uncertainty_deg: ``(T', K')`` float64 the inference's uncertainty of the student's
            angle, degrees: the orientation spreads of the two segments' body parts
            (:attr:`Registration.part_spread_deg`) added in quadrature; ``None`` when the
            registration did not measure them.
        first_frame, frame_step: frame ``t'`` is frame ``first_frame + t' frame_step`` of
            the source video (0-based).
    """

    coordinates: list[str]
    time_s: Tensor
    reference_deg: Tensor
    student_deg: Tensor
    difference_deg: Tensor
    articulation_deg: Tensor
    uncertainty_deg: Tensor | None = None
    first_frame: int = 0
    frame_step: int = 1

    @property
    def num_frames(self) -> int:
        return int(self.time_s.shape[0])

    @property
    def video_frames(self) -> list[int]:
        """The source video's frame number of each frame."""
        return [self.first_frame + t * self.frame_step for t in range(self.num_frames)]


def _check_registration(reg: Registration, reference: Reference) -> None:
    t, j = reg.num_frames, reference.skeleton.num_joints
    if t < 1:
        raise RegistrationError("the registration has no video frames")
    if reg.rotations.shape != (t, j, 3, 3) or reg.T_translation.shape != (t, 3):
        raise RegistrationError(
            f"registration and reference {reference.name} disagree: expected rotations "
            f"({t}, {j}, 3, 3) and T_translation ({t}, 3); got {tuple(reg.rotations.shape)} "
            f"and {tuple(reg.T_translation.shape)}"
        )


def _check_rate(frame_rate: float) -> float:
    frame_rate = float(frame_rate)
    if not (math.isfinite(frame_rate) and frame_rate > 0):
        raise RegistrationError(f"frame_rate must be a positive number of Hz; got {frame_rate}")
    return frame_rate


def student_offsets(reg: Registration, reference: Reference) -> Tensor:
    """``(J, 3)`` float64 metres: the registered student's joint offsets, the reference's
    scaled by ``reg.G`` (and the student's proportions, where measured)."""
    offsets = reference.skeleton.offsets.to(F64) * float(reg.G)
    if reg.proportions is not None:
        offsets = offsets * reg.proportions.joint_scales().to(F64)[:, None]
    return offsets


def leg_lengths_m(reg: Registration, reference: Reference) -> tuple[float, float]:
    """The reference's and the registered student's standing hip heights, metres
    (:func:`motion.registration.movement.leg_length_m`)."""
    segments = _segments(reference)
    skeleton = reference.skeleton
    return (
        leg_length_m(skeleton, skeleton.offsets, segments),
        leg_length_m(skeleton, student_offsets(reg, reference), segments),
    )


def student_kinematics(reg: Registration, reference: Reference) -> FKResult:
    """The registered student's forward kinematics in the cameras' world frame: the
    reference's skeleton scaled by ``reg.G`` (and the student's proportions, where
    measured), local rotations ``reg.rotations``, root joint at ``reg.T_translation``.
    Positions ``(T', J, 3)`` metres, float64."""
    offsets = student_offsets(reg, reference)
    return forward_kinematics(
        reference.skeleton, reg.rotations.to(F64), reg.T_translation.to(F64) - offsets[0], offsets
    )


def _segments(reference: Reference) -> SegmentMap:
    try:
        return SegmentMap.from_roles(reference.skeleton, reference.model.mapping)
    except ValueError as e:
        raise RegistrationError(f"{reference.name}: {e}") from None


def joints_trusted(angles: JointAngles, reference: Reference, seen: Tensor) -> Tensor:
    """``(T', K')`` bool for the coordinates of ``angles``: every joint the coordinate rests
    on (:func:`motion.angles.coordinate_joints`: both segments' bones) is ``seen``
    ``(T', J)`` (e.g. inside every camera's image): an angle whose bones leave the view is
    a guess."""
    segments = _segments(reference)
    columns = [
        seen[:, coordinate_joints(reference.skeleton, name, segments)].all(1)
        for name in angles.coordinates
    ]
    return torch.stack(columns, 1)


def _estimated_coordinates(reference: Reference, segments: SegmentMap) -> list[bool]:
    """Per coordinate of :data:`COORDINATES`: whether a joint the registration estimates (a
    body part's frame joint, the root excepted) changes it (:func:`motion.angles.
    coordinate_chain`); the others keep the reference's rotations, so their difference
    would be zero by construction."""
    estimated = {int(j) for j in reference.spec.frame_joints} - {0}
    return [
        bool(estimated.intersection(coordinate_chain(reference.skeleton, name, segments)))
        for name in COORDINATES
    ]


def _part_of(reference: Reference, joint: int) -> int:
    """The body part that turns with ``joint``: the part whose frame joint is ``joint`` or
    its nearest ancestor (CMU's Spine1 moves with the torso part, framed by Spine); failing
    that, the part whose chain of joints holds it (:func:`motion.body.spec.joint_parts`):
    the root, where the pelvis is framed by a joint above it (on CMU's jumps the lower
    back's rotation fits the pelvis's landmarks best)."""
    frames = reference.spec.frame_joints.tolist()
    j = joint
    while j >= 0:
        if j in frames:
            return frames.index(j)
        j = int(reference.skeleton.parents[j])
    part = int(joint_parts(reference.skeleton, reference.model)[joint])
    if part < 0:
        raise RegistrationError(f"{reference.name}: no body part moves joint {joint}")
    return part


def _angle_uncertainty(
    reg: Registration, reference: Reference, segments: SegmentMap, names: list[str]
) -> Tensor | None:
    """``(T', K')`` degrees: per coordinate, the part spreads of its two segments added in
    quadrature (independent marginals); ``None`` without spreads."""
    spread = reg.part_spread_deg
    if spread.numel() == 0:
        return None
    if spread.shape != (reg.num_frames, reference.spec.num_parts):
        raise RegistrationError(
            f"part_spread_deg must be ({reg.num_frames}, {reference.spec.num_parts}); got "
            f"{tuple(spread.shape)}"
        )
    spread = spread.to(F64)
    columns = []
    for name in names:
        pair = [
            _part_of(reference, j) for j in coordinate_segments(reference.skeleton, name, segments)
        ]
        columns.append(spread[:, pair].square().sum(-1).sqrt())
    return torch.stack(columns, 1)


def joint_angles(
    reg: Registration,
    reference: Reference,
    frame_rate: float,
    first_frame: int = 0,
    frame_step: int = 1,
) -> JointAngles:
    """Clinical joint angles of the reference at C(t') and of the student, per video frame.

    The reference's posture is its rotations at ``reg.C``, the student's ``reg.rotations``
    (the root's rotation does not change any angle, nor does the body size G); the segments
    come from the reference's role mapping (:meth:`motion.angles.SegmentMap.from_roles`).

    Args:
        reg: the registration (``T'`` frames).
        reference: the reference it was registered against.
        frame_rate: the registered frames' rate (the source video's over ``frame_step``).
        first_frame, frame_step: where the registered frames lie in the source video (its
            ``video.start`` and ``video.step``): times are on the source video's clock.

    Returns:
        :class:`JointAngles` for the coordinates the registration estimates (a joint of a
        body part between the coordinate's two segments).
    """
    _check_registration(reg, reference)
    frame_rate = _check_rate(frame_rate)
    if first_frame < 0 or frame_step < 1:
        raise RegistrationError(
            f"expected first_frame >= 0 and frame_step >= 1; got {first_frame}, {frame_step}"
        )
    segments = _segments(reference)
    ref = clinical_angles(reference.skeleton, reference.rotations[reg.C].to(F64), segments)
    stu = clinical_angles(reference.skeleton, reg.rotations.to(F64), segments)
    keep = torch.tensor(_estimated_coordinates(reference, segments)).nonzero().flatten()
    difference = stu.degrees[:, keep] - ref.degrees[:, keep]
    change = ref.joint_rotations[:, keep].transpose(-1, -2) @ stu.joint_rotations[:, keep]
    names = [COORDINATES[i] for i in keep.tolist()]
    return JointAngles(
        coordinates=names,
        time_s=(first_frame / frame_step + torch.arange(reg.num_frames, dtype=F64)) / frame_rate,
        reference_deg=ref.degrees[:, keep],
        student_deg=stu.degrees[:, keep],
        difference_deg=torch.remainder(difference + 180.0, 360.0) - 180.0,
        articulation_deg=torch.rad2deg(rotation_angle(change)),
        uncertainty_deg=_angle_uncertainty(reg, reference, segments, names),
        first_frame=first_frame,
        frame_step=frame_step,
    )


def per_joint_mean_abs_deg(angles: JointAngles) -> dict[str, float]:
    """Mean ``|student - reference|`` per coordinate over the frames, degrees (NaN frames
    left out; NaN where a coordinate has none), keyed by the coordinate's name."""
    mean = angles.difference_deg.abs().nanmean(0)
    return {name: float(v) for name, v in zip(angles.coordinates, mean.tolist(), strict=True)}


@dataclass
class JointDifference:
    """Where a joint angle differs most from the reference.

    Attributes:
        coordinate: the angle's OpenSim name (:data:`motion.angles.COORDINATES`).
        mean_difference_deg: mean ``student - reference`` over the run, degrees, in the
            coordinate's positive sense (negative: the student flexes, adducts, ... less).
        start_s: video time of the run's first frame, seconds.
        end_s: video time of the run's last frame, seconds.
        mean_abs_deg: mean ``|student - reference|`` over all frames (the ranking), degrees.
        uncertainty_deg: the inference's uncertainty of the difference over the run (the
            RMS of :attr:`JointAngles.uncertainty_deg` there; not divided by the run's
            length, as neighbouring frames' errors go together), degrees; NaN when not
            measured.
        frames: the run's trusted frames.
        method_error_deg: the method's own error of this coordinate's difference, degrees
            (:class:`FindingSettings.method_error`; 0: not counted), added in quadrature to
            the inference's in the sentence's ``±``.
    """

    coordinate: str
    mean_difference_deg: float
    start_s: float
    end_s: float
    mean_abs_deg: float
    uncertainty_deg: float = math.nan
    frames: int = 0
    method_error_deg: float = 0.0

    @property
    def text(self) -> str:
        """One sentence, e.g. ``"Left knee flexes 18 ± 4 degrees less than the reference
        between 1.20 s and 1.60 s"`` (:func:`motion.angles.describe_coordinate`'s words; no
        ``±`` when the uncertainty is not measured)."""
        words = describe_coordinate(self.coordinate)
        name = words.joint[:1].upper() + words.joint[1:]
        size = abs(self.mean_difference_deg)
        amount = f"{size:.0f}" if size >= 1 else f"{size:.1f}"
        unit = "degree" if amount == "1" else "degrees"
        if math.isfinite(self.uncertainty_deg) or self.method_error_deg > 0:
            u = math.hypot(np.nan_to_num(self.uncertainty_deg), self.method_error_deg)
            unit = f"± {u:.0f} degrees" if u >= 1 else f"± {u:.1f} degrees"
        more = "more" if self.mean_difference_deg > 0 else "less"
        when = (
            f"at {self.start_s:.2f} s"
            if self.start_s == self.end_s
            else f"between {self.start_s:.2f} s and {self.end_s:.2f} s"
        )
        return f"{name} {words.verb} {amount} {unit} {more} than the reference {when}"

    def to_dict(self) -> dict:
        """The fields and :attr:`text`, for JSON."""
        return {**dataclasses.asdict(self), "text": self.text}


def _longest_run(diff: np.ndarray) -> tuple[int, int] | None:
    """``(first, last)`` frame of the longest run of consecutive frames where ``|diff|``
    exceeds half its maximum with one sign (ties: the larger ``|mean|``, then the earlier);
    ``None`` when ``diff`` is all zero or NaN."""
    mag = np.abs(diff)
    if not np.isfinite(mag).any() or np.nanmax(mag) == 0:
        return None
    big = np.nan_to_num(mag, nan=0.0) > np.nanmax(mag) / 2
    key = np.where(big, np.sign(diff), 0.0)
    edges = np.flatnonzero(np.diff(key)) + 1
    starts = np.concatenate([[0], edges])
    stops = np.concatenate([edges, [len(key)]])
    best, best_rank = None, None
    for start, stop in zip(starts.tolist(), stops.tolist(), strict=True):
        if key[start] == 0:
            continue
        rank = (stop - start, abs(float(diff[start:stop].mean())))
        if best_rank is None or rank > best_rank:
            best, best_rank = (start, stop - 1), rank
    return best


def _running_median(values: np.ndarray, width: int) -> np.ndarray:
    """Centred running median over ``width`` frames along axis 0 (NaNs ignored; shrinking
    windows at the ends)."""
    if width <= 1:
        return values
    half = width // 2
    out = np.full_like(values, np.nan)
    for t in range(len(values)):
        window = values[max(0, t - half) : t + half + 1]
        ok = np.isfinite(window).any(0)
        out[t, ok] = np.nanmedian(window[:, ok], axis=0)
    return out


def trusted_angles(
    angles: JointAngles, trusted: Tensor | None = None, smooth_s: float = SMOOTH_S
) -> JointAngles:
    """The angles a report should read: differences where ``trusted`` is False set to NaN
    (``(T',)`` bool per frame, or ``(T', K')`` per frame and coordinate of ``angles``), then a
    centred running median over ``smooth_s`` seconds (a frame-to-frame jitter of the
    posture estimate is not a difference of the student's movement)."""
    diff = angles.difference_deg.detach().cpu().numpy().copy()
    if trusted is not None:
        trusted = trusted.to(torch.bool).cpu()
        trusted = trusted[:, None].expand(diff.shape) if trusted.dim() == 1 else trusted
        diff[~trusted.numpy()] = np.nan
    time_s = angles.time_s.cpu().numpy()
    rate = 1.0 / float(np.median(np.diff(time_s))) if len(time_s) > 1 else 1.0
    width = 2 * round(smooth_s * rate / 2) + 1
    smooth = torch.from_numpy(_running_median(diff, width)).to(angles.difference_deg)
    if trusted is not None:  # the median may not fill an untrusted frame from its neighbours
        smooth[~trusted.to(torch.bool)] = float("nan")
    return dataclasses.replace(angles, difference_deg=smooth)


def largest_differences(angles: JointAngles, count: int = 3) -> list[JointDifference]:
    """The ``count`` coordinates that differ most from the reference, each with its
    longest stretch of a large difference.

    Coordinates are ranked by the mean ``|student - reference|`` over the frames
    (:func:`per_joint_mean_abs_deg`; NaN frames left out, e.g. the untrusted ones of
    :func:`trusted_angles`); one with no difference at all is left out. For each, the
    stretch is the longest run of consecutive frames where ``|difference|`` exceeds half
    the coordinate's maximum ``|difference|`` with one sign, and :attr:`JointDifference.
    mean_difference_deg` is the signed mean over it.

    Returns:
        up to ``count`` :class:`JointDifference`, largest first.
    """
    if count < 0:
        raise ValueError(f"count must be >= 0; got {count}")
    mean_abs = per_joint_mean_abs_deg(angles)
    order = sorted(
        (i for i, n in enumerate(angles.coordinates) if math.isfinite(mean_abs[n])),
        key=lambda i: (-mean_abs[angles.coordinates[i]], angles.coordinates[i]),
    )
    diff = angles.difference_deg.detach().cpu().numpy()
    spread = None if angles.uncertainty_deg is None else angles.uncertainty_deg.cpu().numpy()
    time_s = angles.time_s.tolist()
    out = []
    for i in order:
        run = _longest_run(diff[:, i])
        if run is None:
            continue
        first, last = run
        name = angles.coordinates[i]
        here = None if spread is None else spread[first : last + 1, i]
        out.append(
            JointDifference(
                name,
                float(diff[first : last + 1, i].mean()),
                time_s[first],
                time_s[last],
                mean_abs[name],
                _rms(here),
                last - first + 1,
            )
        )
        if len(out) == count:
            break
    return out


def _rms(values: np.ndarray | None) -> float:
    """RMS of the finite values, NaN when there are none (or no values at all)."""
    if values is None or not np.isfinite(values).any():
        return math.nan
    return float(np.sqrt(np.nanmean(np.square(values))))


@dataclass(frozen=True)
class FindingSettings(Settings):
    """When one of the largest differences is stated as a finding (``findings.*`` of
    ``motion register``). Every field is checked at construction (a bad value raises
    :class:`~motion.settings.SettingError`, a ``ValueError``, naming it)."""

    interval_z: float = setting(
        2.0,
        "a finding's interval is its mean difference ± interval_z times its uncertainty "
        "(JointDifference.uncertainty_deg); one whose interval holds 0 is not stated (2: "
        "about 95 % for a normal error)",
        ge=0,
    )
    min_trusted_s: float = setting(
        SMOOTH_S,
        "a finding needs at least this many seconds of trusted frames (by default the running "
        "median's width, SMOOTH_S: a shorter run is a jitter the median let through)",
        ge=0,
    )
    method_error_deg: float | None = setting(
        None,
        "the method's own error of a joint-angle difference, degrees, added in quadrature to "
        "the inference's uncertainty for the interval: the particle spread measures how far "
        "the posterior lets a part turn, not how far the method is off. none: each "
        "coordinate's error as measured on students of other performers, with as many "
        "cameras (motion/registration/data/method_error.json, written by python -m "
        "experiments.findings_calibration; uncovered coordinates: FALLBACK_METHOD_ERROR_DEG); "
        "a number: that for every coordinate (0 trusts the spread alone, fit for a student "
        "of the reference's own performer)",
        ge=0,
    )

    max_interval_deg: float | None = setting(
        5.0,
        "a finding is stated only when its interval is at most ± this many degrees (interval_z "
        "times the inference's uncertainty and the method's error in quadrature): a "
        "difference the method cannot place within it is no finding a coach can act on, "
        "however large (5: a stated finding is then within 5 degrees of the truth about 95 % "
        "of the time; none: any interval clear of 0 is stated)",
        gt=0,
    )

    def method_error(
        self, coordinate: str, cameras: int, table: MethodError | None = None
    ) -> float:
        """The method's error of ``coordinate``'s difference with ``cameras`` cameras,
        degrees: :attr:`method_error_deg`, or when that is none the calibration ``table``
        (default: the shipped one, :func:`~motion.registration.method_error.
        shipped_method_error`; a coordinate it does not cover: :data:`FALLBACK_METHOD_ERROR_DEG`)."""
        if self.method_error_deg is not None:
            return self.method_error_deg
        found = (table or shipped_method_error()).error_deg(coordinate, cameras)
        return FALLBACK_METHOD_ERROR_DEG if found is None else found

    def why_not(
        self,
        finding: JointDifference,
        frame_rate: float,
        cameras: int = 1,
        table: MethodError | None = None,
    ) -> str:
        """Why ``finding`` is not stated ("" when it is), seen by ``cameras`` cameras
        (``table``: as :meth:`method_error`)."""
        needed = math.ceil(self.min_trusted_s * frame_rate - 1e-9)
        if finding.frames < needed:
            return (
                f"only {finding.frames} trusted frame(s) show it; at least {needed} "
                f"({self.min_trusted_s:g} s) expected"
            )
        u = finding.uncertainty_deg if math.isfinite(finding.uncertainty_deg) else 0.0
        e = self.method_error(finding.coordinate, cameras, table)
        spread = self.interval_z * math.hypot(u, e)
        if abs(finding.mean_difference_deg) <= spread:
            method = (
                f"; the inference's ± {u:.0f} and the method's error of {e:.0f} degrees"
                if e
                else ""
            )
            return (
                f"its interval ({finding.mean_difference_deg:+.0f} ± {spread:.0f} degrees"
                f"{method}) holds 0: the inference cannot tell it from no difference"
            )
        if self.max_interval_deg is not None and spread > self.max_interval_deg:
            return (
                f"its interval ({finding.mean_difference_deg:+.0f} ± {spread:.0f} degrees) is "
                f"wider than ± {self.max_interval_deg:g}: the method cannot place this "
                "difference finely enough"
                + (f" (its own error on this angle: {e:.0f} degrees)" if e else "")
            )
        return ""


def _num(x: float) -> str:
    return format(float(x), ".10g")


def write_joint_angles_csv(
    angles: JointAngles, path: str | Path, method_error_deg: dict[str, float] | None = None
) -> Path:
    """Write :class:`JointAngles` as CSV, long format: one row per frame and coordinate,
    columns ``frame`` (the source video's frame number), ``time_s`` (its clock),
    ``coordinate`` (OpenSim's name), ``reference_deg``, ``student_deg``, ``difference_deg``,
    ``articulation_deg``, ``uncertainty_deg`` (the inference's uncertainty of the
    difference, :attr:`JointAngles.uncertainty_deg`) and ``method_error_deg`` (the method's
    own error of that coordinate's difference, ``method_error_deg`` by coordinate:
    :meth:`FindingSettings.method_error`; a difference is known to about the two in
    quadrature) (10 significant digits; NaN, or not measured, written as ``nan``). Returns
    the path."""
    path = Path(path)
    nan = torch.full_like(angles.difference_deg, math.nan, dtype=F64)
    errors = method_error_deg or {}
    method = torch.tensor(
        [errors.get(name, math.nan) for name in angles.coordinates], dtype=F64
    ).expand_as(nan)
    columns = [
        angles.reference_deg,
        angles.student_deg,
        angles.difference_deg,
        angles.articulation_deg,
        nan if angles.uncertainty_deg is None else angles.uncertainty_deg,
        method,
    ]
    values = torch.stack([c.to(F64) for c in columns], -1).tolist()  # (T', K', 6)
    with path.open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(
            [
                "frame",
                "time_s",
                "coordinate",
                "reference_deg",
                "student_deg",
                "difference_deg",
                "articulation_deg",
                "uncertainty_deg",
                "method_error_deg",
            ]
        )
        rows = zip(angles.video_frames, angles.time_s.tolist(), values, strict=True)
        for frame, time_s, row in rows:
            for name, v in zip(angles.coordinates, row, strict=True):
                writer.writerow([frame, _num(time_s), name, *(_num(x) for x in v)])
    return path


def write_mot(angles: JointAngles, path: str | Path, name: str | None = None) -> Path:
    """Write :class:`JointAngles` as an OpenSim storage (``.mot``) table.

    Header lines ``name`` (default: the file's stem), ``version=1``, ``nRows=T'``,
    ``nColumns=1 + 3 K'`` (time included), ``inDegrees=yes``, ``endheader``; then a
    tab-separated column header ``time`` and per coordinate the student's angle under the
    coordinate's own name (as OpenSim's inverse kinematics writes it, so the file opens as
    the student's motion), ``<name>_reference`` and ``<name>_difference``; then one row per
    frame (seconds, degrees, 10 significant digits). Returns the path.
    """
    path = Path(path)
    names = ["time"]
    for coordinate in angles.coordinates:
        names += [coordinate, f"{coordinate}_reference", f"{coordinate}_difference"]
    per_coordinate = [angles.student_deg, angles.reference_deg, angles.difference_deg]
    table = torch.stack([x.to(F64) for x in per_coordinate], -1).flatten(1)  # (T', 3 K')
    table = torch.cat([angles.time_s.to(F64)[:, None], table], 1)
    lines = [
        name or path.stem,
        "version=1",
        f"nRows={table.shape[0]}",
        f"nColumns={len(names)}",
        "inDegrees=yes",
        "endheader",
        "\t".join(names),
    ]
    lines += ["\t".join(_num(x) for x in row) for row in table.tolist()]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


# --------------------------------------------------------------------------- BVH


def bvh_from_rotations(
    hierarchy: BVH,
    metres_per_unit: float,
    rotations: Tensor,
    root_position: Tensor,
    frame_rate: float,
    scale: float = 1.0,
    proportions: Proportions | None = None,
) -> BVH:
    """A BVH on ``hierarchy``'s skeleton playing the given local rotations.

    Args:
        hierarchy: the file whose joints, channels (and their order) and End Sites to keep
            (its motion is not used).
        metres_per_unit: the file's length unit (:attr:`motion.kinematics.Skeleton.
            metres_per_unit`); positions are written in it, so the file opens like
            ``hierarchy``.
        rotations: ``(T', J, 3, 3)`` local joint rotations (the root's is global).
        root_position: ``(T', 3)`` the root joint's world position, metres (the position of
            joint 0, offset included, as ``Registration.T_translation``).
        frame_rate: frames per second (``Frame Time`` = ``1 / frame_rate``).
        scale: body scale G: OFFSETs and End Sites multiplied by it.
        proportions: the student's part lengths on top of G (each OFFSET multiplied by
            :meth:`~motion.registration.types.Proportions.joint_scales`, each End Site by
            its joint's part's factor); ``None``: G alone.

    Returns:
        :class:`motion.bvh.BVH` (``path`` = ``hierarchy.path``). Rotation channels hold the
        Euler angles (:func:`motion.geometry.matrix_to_euler`, degrees) in each joint's channel order;
        root position channels ``root_position / metres_per_unit - scale * OFFSET``; other
        joints' position channels their scaled OFFSET.

    Raises:
        RegistrationError: shapes that do not fit the hierarchy, a joint without rotation
            channels given a rotation other than the identity (it could not be stored), a
            frame time outside :data:`motion.bvh.FRAME_TIME_RANGE`.
    """
    j = len(hierarchy.names)
    if rotations.ndim != 4 or rotations.shape[1:] != (j, 3, 3):
        raise RegistrationError(
            f"{hierarchy.path}: rotations must be (T', {j}, 3, 3); got {tuple(rotations.shape)}"
        )
    t = rotations.shape[0]
    if root_position.shape != (t, 3):
        raise RegistrationError(f"root_position must be ({t}, 3); got {tuple(root_position.shape)}")
    frame_time = 1.0 / _check_rate(frame_rate)
    low, high = FRAME_TIME_RANGE
    if not low <= frame_time <= high:
        raise RegistrationError(
            f"frame time 1/{frame_rate} s is outside the BVH range [{low:g}, {high:g}] s"
        )
    if not (math.isfinite(metres_per_unit) and metres_per_unit > 0):
        raise RegistrationError(f"metres_per_unit must be > 0; got {metres_per_unit}")
    scale = float(scale)
    rotations = rotations.detach().to(F64).cpu()
    bones, ends = np.ones(j), np.ones(j)
    if proportions is not None:
        bones = proportions.joint_scales().detach().cpu().numpy()
        ends = proportions.end_site_scales().detach().cpu().numpy()
    offsets = hierarchy.offsets * scale * bones[:, None]
    root = root_position.detach().to(F64).cpu().numpy() / metres_per_unit - offsets[0]
    motion = np.zeros((t, sum(len(c) for c in hierarchy.channels)))
    col = 0
    eye = torch.eye(3, dtype=F64)
    for joint, chans in enumerate(hierarchy.channels):
        rot = [i for i, c in enumerate(chans) if c.endswith("rotation")]
        if rot:
            if len(rot) != 3:
                raise RegistrationError(
                    f"{hierarchy.path}: joint {hierarchy.names[joint]!r} has {len(rot)} "
                    "rotation channels; 3 or none are supported"
                )
            order = "".join(chans[i][0] for i in rot)
            deg = torch.rad2deg(matrix_to_euler(rotations[:, joint], order)).numpy()
            motion[:, [col + i for i in rot]] = deg
        else:
            off = float((rotations[:, joint] - eye).abs().amax()) if t else 0.0
            if off > 1e-9:
                raise RegistrationError(
                    f"{hierarchy.path}: joint {hierarchy.names[joint]!r} has no rotation "
                    f"channels but is given rotations up to {off:.3g} from the identity"
                )
        for i, c in enumerate(chans):
            if c.endswith("position"):
                axis = _AXIS[c[0]]
                motion[:, col + i] = root[:, axis] if joint == 0 else offsets[joint, axis]
        col += len(chans)
    return BVH(
        path=hierarchy.path,
        names=list(hierarchy.names),
        parents=hierarchy.parents.copy(),
        offsets=offsets,
        channels=[list(c) for c in hierarchy.channels],
        end_sites={k: v * scale * ends[k] for k, v in hierarchy.end_sites.items()},
        frame_time=frame_time,
        motion=motion,
    )


def student_bvh(reg: Registration, reference: Reference, frame_rate: float) -> BVH:
    """The recovered motion as a BVH on the reference's skeleton.

    The reference file (:attr:`Reference.name`) gives the hierarchy, channels and channel
    order; OFFSETs are scaled by G and the student's proportions (where measured); the root's position is ``reg.T_translation``, local
    rotations ``reg.rotations``; lengths in the reference file's own unit
    (``reference.skeleton.metres_per_unit``), frame time ``1 / frame_rate``
    (:func:`bvh_from_rotations`).

    Note: read back with :meth:`Skeleton.from_bvh` and no declared unit, a file with G != 1
    gets its unit *estimated* from the scaled rest leg, i.e. about ``metres_per_unit / G``
    (CMU's unit is itself an estimate); pass ``metres_per_unit`` to get the student's size.

    Raises:
        RegistrationError: the reference file is missing or no longer matches the
            reference's skeleton, or as :func:`bvh_from_rotations`.
    """
    _check_registration(reg, reference)
    if not Path(reference.name).is_file():
        raise RegistrationError(
            f"{reference.name}: the reference's BVH file gives the student's hierarchy, and "
            "there is no such file"
        )
    hierarchy = read_bvh(reference.name)
    skel = reference.skeleton
    if list(hierarchy.names) != list(skel.names):
        raise RegistrationError(
            f"{reference.name}: the file's joints {hierarchy.names} are not the reference's "
            f"{skel.names}"
        )
    return bvh_from_rotations(
        hierarchy,
        skel.metres_per_unit,
        reg.rotations,
        reg.T_translation,
        frame_rate,
        scale=float(reg.G),
        proportions=reg.proportions,
    )


def write_student_bvh(
    reg: Registration, reference: Reference, frame_rate: float, path: str | Path
) -> Path:
    """Write :func:`student_bvh` to ``path`` (:func:`motion.bvh.write_bvh`); returns it."""
    return write_bvh(student_bvh(reg, reference, frame_rate), path)


# --------------------------------------------------------------------------- the result

_FORMAT = "motion.registration.Registration/1"


#: the array fields of :class:`Proportions` in its constructor's order, after ``part_names``
_PROPORTION_ARRAYS = ("part_scales", "joint_parts", "parents")


def save_registration(reg: Registration, path: str | Path) -> Path:
    """Write a :class:`Registration` as ``.npz``: each tensor field as its numpy array (dtype
    kept), ``G`` as a float64 scalar, ``timings`` and ``notes`` as JSON strings, the
    proportions' fields as ``proportions.<field>``, plus a ``format`` tag. Returns the path (numpy adds ``.npz`` when missing)."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    arrays: dict[str, np.ndarray] = {"format": np.array(_FORMAT)}
    for f in dataclasses.fields(Registration):
        value = getattr(reg, f.name)
        if isinstance(value, Tensor):
            arrays[f.name] = value.detach().cpu().numpy()
        elif isinstance(value, dict | list | str | None):
            arrays[f.name] = np.array(json.dumps(value))
        elif isinstance(value, int | float):
            arrays[f.name] = np.array(float(value))
        elif isinstance(value, Proportions):  # its fields, under "proportions.<field>"
            arrays[f"{f.name}.part_names"] = np.array(json.dumps(value.part_names))
            for sub in _PROPORTION_ARRAYS:
                arrays[f"{f.name}.{sub}"] = getattr(value, sub).detach().cpu().numpy()
            arrays[f"{f.name}.measured"] = np.array(value.measured)
        else:
            raise TypeError(f"cannot save Registration.{f.name} of type {type(value).__name__}")
    np.savez(path, **arrays)
    return path


def load_registration(path: str | Path) -> Registration:
    """Read a :func:`save_registration` file back.

    Raises:
        RegistrationError: naming the file, when it is not such a file or misses fields.
    """
    path = Path(path)
    with np.load(path, allow_pickle=False) as data:
        keys = set(data.files)
        if "format" not in keys or str(data["format"]) != _FORMAT:
            raise RegistrationError(f"{path}: not a saved registration (expected {_FORMAT!r})")
        fields = dataclasses.fields(Registration)
        optional = {
            f.name
            for f in fields
            if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
        }
        missing = [f.name for f in fields if f.name not in keys and f.name not in optional]
        if missing:
            raise RegistrationError(f"{path}: missing fields {missing}")
        values = {}
        if "proportions.part_scales" in keys:
            values["proportions"] = Proportions(
                json.loads(str(data["proportions.part_names"])),
                *(torch.from_numpy(data[f"proportions.{k}"].copy()) for k in _PROPORTION_ARRAYS),
                bool(data["proportions.measured"]),
            )
        for f in fields:
            if f.name not in keys:  # an older file, or a field stored in parts: its default
                continue
            arr = data[f.name]
            if arr.dtype.kind == "U":
                values[f.name] = json.loads(str(arr))
            elif arr.ndim == 0 and f.type in ("float", float):
                values[f.name] = float(arr)
            elif arr.ndim == 0 and f.type in ("bool", bool):
                values[f.name] = bool(arr)
            else:
                values[f.name] = torch.from_numpy(arr.copy())
    return Registration(**values)


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


@dataclass
class RegistrationSummary:
    """One registration run as a JSON record (:meth:`to_json`).

    Attributes:
        reference: the reference's name (its path).
        reference_rate_hz: the reference's frame rate.
        num_video_frames: ``T'``.
        video_rate_hz: the video's frame rate.
        c_frames: ``T'`` reference frame C(t') of each video frame.
        c_stage1_frames: ``T'`` C after stage 1.
        video_frames: ``T'`` the source video's frame number of each frame (``video.start``
            and ``video.step`` applied): every time and frame a user sees is on the source
            video's clock.
        video_start_s: the source video's time of the first registered frame, seconds.
        reference_start_s: where the student starts in the reference: the reference's
            time ``C(0) / reference_rate_hz`` matching the first registered frame, seconds
            (the report's "Starts at"; the one quantity of that name).
        speed_ratio: reference seconds per video second: the least-squares slope ``b`` of
            ``C(t') ~ a + b t'`` times ``video_rate_hz / reference_rate_hz`` (``None`` with
            one frame).
        G: body scale.
        G_measured: whether G was measured (``False``: 1 because one perspective camera
            cannot tell body size from depth; "not measured" to a user).
        silhouette_iou_mean: mean of :attr:`fit` (``None`` when it has no finite value).
        fit: ``T'`` per-frame silhouette IoU.
        per_joint_mean_abs_deg: mean ``|student - reference|`` per clinical coordinate
            (OpenSim's names), degrees (coordinates never defined left out).
        largest_differences: :meth:`JointDifference.to_dict` of the coordinates that differ most
            (:func:`largest_differences` on the trusted frames), the largest stretch first.
        timings: seconds per stage.
        notes: what was estimated and how.
        settings: the run's settings as given (JSON-able values; others written as text).
        motions_match: whether the student performs the reference's movement
            (:func:`motion.registration.movement.check_movement`); when not, no difference
            is stated (each of :attr:`largest_differences` has ``stated`` false and ``why``).
        warnings: sentences for the user, most important first: why the movements do not
            match, then the video's ends that have no counterpart in the reference, then what
            the input or the inference could not do (frames carried over, a video cut short).
        movement: the movement check's evidence (:class:`MovementCheck` as a dict).
        proportions: the student's length factor of each body part on top of G
            (:class:`~motion.registration.types.Proportions`; 1: the reference's proportions),
            empty when not measured (no 2-D joints, or the fit turned off).
        detection: the person detector's run when one gave the 2-D joints
            (:meth:`motion.perception.run.DetectionRun.summary`: detector, frames per
            second, frames detected per camera, whether an earlier run's files were
            reused); empty when none ran.
        partial_silhouettes: the videos whose silhouettes miss parts of the body (their
            background, a median of their frames, holds the person: each has a warning).
            When it names every camera, :attr:`fit` was measured against partial
            silhouettes and no difference is stated (:attr:`whole_body_seen` false).
        whole_body_seen: whether some camera's silhouettes show the whole body (false when
            :attr:`partial_silhouettes` names every camera).
    """

    reference: str
    reference_rate_hz: float
    num_video_frames: int
    video_rate_hz: float
    c_frames: list[int]
    c_stage1_frames: list[int]
    video_frames: list[int]
    video_start_s: float
    reference_start_s: float
    speed_ratio: float | None
    G: float
    silhouette_iou_mean: float | None
    fit: list[float | None]
    per_joint_mean_abs_deg: dict[str, float]
    largest_differences: list[dict]
    timings: dict[str, float]
    notes: dict[str, str]
    settings: dict
    motions_match: bool = True
    warnings: list[str] = field(default_factory=list)
    movement: dict = field(default_factory=dict)
    G_measured: bool = True
    proportions: dict[str, float] = field(default_factory=dict)
    detection: dict = field(default_factory=dict)
    partial_silhouettes: list[str] = field(default_factory=list)
    whole_body_seen: bool = True

    def to_json(self, indent: int | None = 2) -> str:
        """The summary as strict JSON text: NaN and infinities as ``null``; paths, tensors,
        numpy values and dataclasses in ``settings`` as their plain values (others as
        text)."""
        return json.dumps(_jsonable(dataclasses.asdict(self)), indent=indent, allow_nan=False)


#: plurals of the part names that do not take an "s" (a left and right pair read as one)
_PLURALS = {"foot": "feet"}


def proportion_words(proportions: dict[str, float], most: int = 4, least_pct: float = 2.0) -> str:
    """The parts whose length differs most from the reference's, for a user: ``"thighs 7 %
    shorter, shins 5 % longer"`` (left and right, named ``X_l`` / ``X_r``, read as one;
    at most ``most``, each differing by at least ``least_pct`` percent; ``""`` when none
    does)."""
    groups: dict[str, list[float]] = {}
    for name, scale in proportions.items():
        pair = paired_part(name)
        key = (name if pair is None else _PLURALS.get(pair, pair + "s")).replace("_", " ")
        groups.setdefault(key, []).append(scale)
    means = {k: sum(v) / len(v) for k, v in groups.items()}
    large = sorted(
        ((k, (x - 1) * 100) for k, x in means.items() if abs(x - 1) * 100 >= least_pct),
        key=lambda kv: -abs(kv[1]),
    )[:most]
    return ", ".join(
        f"{k} {abs(pct):.0f} % {'longer' if pct > 0 else 'shorter'}" for k, pct in large
    )


def _jsonable(value):
    """``value`` with JSON's types only (see :meth:`RegistrationSummary.to_json`)."""
    if isinstance(value, bool | int | str) or value is None:
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, Tensor | np.ndarray | np.generic):
        return _jsonable(value.tolist())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _jsonable(dataclasses.asdict(value))
    if isinstance(value, Path):
        return str(value)
    return str(value)


def stated_findings(
    angles: JointAngles,
    trusted: Tensor | None,
    frame_rate: float,
    rules: FindingSettings | None = None,
    cameras: int = 1,
    matches: bool = True,
    count: int = 3,
    table: MethodError | None = None,
    withhold: str = "",
) -> list[dict]:
    """The ``count`` :func:`largest_differences` of the trusted angles
    (:func:`trusted_angles`), largest ``|mean difference|`` first, each as
    :meth:`JointDifference.to_dict` with its method error (``rules``, ``cameras``,
    ``table``: :meth:`FindingSettings.method_error`) and ``stated`` and ``why``
    (:meth:`FindingSettings.why_not`; every one withheld when the movements do not match,
    ``matches`` false, or with ``withhold`` as its ``why`` when that is given)."""
    rules = rules or FindingSettings()
    out = []
    found = largest_differences(trusted_angles(angles, trusted), count)
    for d in sorted(found, key=lambda d: -abs(d.mean_difference_deg)):
        e = rules.method_error(d.coordinate, cameras, table)
        d = dataclasses.replace(d, method_error_deg=e)
        if not matches:
            why = "the student does not perform the reference's movement"
        else:
            why = withhold or rules.why_not(d, frame_rate, cameras, table)
        out.append({**d.to_dict(), "stated": not why, "why": why})
    return out


def summarise(
    reg: Registration,
    reference: Reference,
    angles: JointAngles,
    frame_rate: float,
    settings: dict,
    count: int = 3,
    trusted: Tensor | None = None,
    movement: MovementCheck | None = None,
    findings: FindingSettings | None = None,
    cameras: int = 1,
    partial_silhouettes: list[str] | tuple[str, ...] = (),
) -> RegistrationSummary:
    """The run in one record (:class:`RegistrationSummary`).

    Args:
        reg: the registration.
        reference: its reference.
        angles: :func:`joint_angles` of ``reg``.
        frame_rate: the video's frames per second.
        settings: the settings the run used (plain JSON-able values).
        count: how many :func:`largest_differences` to keep.
        trusted: ``(T',)`` bool, the frames the largest differences may come from, or
            ``(T', K')`` per frame and coordinate of ``angles`` (default: ``reg.fit >=
            TRUSTED_FIT``).
        movement: the movement check (``None``: taken as matching, with no evidence);
            its reasons come first in :attr:`RegistrationSummary.warnings`, then
            ``reg.warnings``.
        findings: when a largest difference is stated (:class:`FindingSettings`); every
            difference is withheld when the movements do not match.
        cameras: how many cameras saw the student (the method's error depends on it).
        partial_silhouettes: the names of the videos whose silhouettes miss parts of the
            body (:attr:`motion.registration.video.VideoInput.held`); when there are
            ``cameras`` of them, no camera saw the whole body: the fit says little and
            every difference is withheld, saying so.
    """
    matches = movement is None or movement.motions_match
    whole = len(partial_silhouettes) < cameras
    withhold = (
        ""
        if whole
        else "no camera's silhouettes show the whole body (the warning on "
        f"{', '.join(partial_silhouettes)}), so the posture is read from parts of it"
    )
    if trusted is None:
        trusted = reg.fit >= TRUSTED_FIT
    frame_rate = _check_rate(frame_rate)
    c = reg.C.to(torch.long).tolist()
    frames = np.arange(len(c), dtype=np.float64)
    if len(c) >= 2:
        b = np.polyfit(frames, np.asarray(c, dtype=np.float64), 1)[0]
        speed = float(b) * frame_rate / reference.frame_rate
    else:
        speed = None
    fit = [float(x) for x in reg.fit.to(F64).tolist()]
    finite = [x for x in fit if math.isfinite(x)]
    return RegistrationSummary(
        reference=str(reference.name),
        reference_rate_hz=float(reference.frame_rate),
        num_video_frames=reg.num_frames,
        video_rate_hz=frame_rate,
        c_frames=c,
        c_stage1_frames=reg.C_stage1.to(torch.long).tolist(),
        video_frames=angles.video_frames,
        video_start_s=float(angles.time_s[0]),
        reference_start_s=c[0] / reference.frame_rate,
        speed_ratio=speed,
        G=float(reg.G),
        G_measured=bool(reg.G_measured),
        proportions={} if reg.proportions is None else reg.proportions.as_dict(),
        silhouette_iou_mean=sum(finite) / len(finite) if finite else None,
        fit=[_finite_or_none(x) for x in fit],
        per_joint_mean_abs_deg={
            k: v for k, v in per_joint_mean_abs_deg(angles).items() if math.isfinite(v)
        },
        largest_differences=stated_findings(
            angles, trusted, frame_rate, findings, cameras, matches, count, withhold=withhold
        ),
        timings={k: float(v) for k, v in reg.timings.items()},
        notes={k: str(v) for k, v in reg.notes.items()},
        settings=dict(settings),
        motions_match=matches,
        warnings=[
            *(movement.reasons if movement is not None else []),
            *(movement.warnings if movement is not None else []),
            *reg.warnings,
        ],
        movement=movement.to_dict() if movement is not None else {},
        partial_silhouettes=list(partial_silhouettes),
        whole_body_seen=whole,
    )
