"""What the registration stages pass between them: typed inputs and outputs.

Notation of the proposal (Section 4.4): video frame ``t'`` corresponds to reference frame
``C(t')``; the body's global rigid transform ``T(t')`` is the student's **root joint**
transform (rotation and position in the cameras' world frame); the articulation ``A(t')`` is,
per joint, the local rotation that turns the reference's joint rotation at ``C(t')`` into the
student's, ``R_student = R_reference A`` (identity for the root, whose rotation is ``T``);
``G`` scales the reference skeleton's bone lengths and part widths to the student.

The reference's posture at frame ``t`` with its root at the origin, unrotated, is ``B_t``
(:meth:`Reference.body_frames`): the student's joints are ``R_T (G B_t) + p_T`` when A = 0.

Units: metres, radians (degrees only in reports and :attr:`Registration.a_degrees`), frames
as 0-based integer indices. Shapes: ``T'`` video frames, ``T`` reference frames, ``J``
skeleton joints, ``P`` body parts, ``C`` cameras, ``H x W`` images.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from motion.body.observation import Observation, PartShapes
from motion.body.spec import BodySpec, joint_parts
from motion.bodyparts import BodyModel
from motion.bvh import read_bvh
from motion.cameras import CameraRig
from motion.kinematics import FKResult, Skeleton, forward_kinematics, local_rotations

__all__ = [
    "FRAME_CHUNK",
    "Proportions",
    "Reference",
    "Registration",
    "RegistrationError",
    "VideoFeatures",
    "expand_to_joints",
    "frame_ranges",
    "nonfinite_frames",
    "paired_part",
    "scaled_spec",
]

#: video frames processed at once wherever a stage derives something per frame of a whole
#: video (stage 1's distance maps and silhouette draws, the part colours, the fit score):
#: each frame's result is its own, so chunks give the same entries while bounding a long
#: video's intermediates (float maps, label maps, colour images) to a few tens of MB
FRAME_CHUNK = 64


class RegistrationError(ValueError):
    """Inputs that registration cannot work with (the message names what and why)."""


@dataclass(frozen=True)
class Reference:
    """A 3-D reference motion, ready to register against.

    Attributes:
        skeleton: the joint tree (metres).
        model: the capsule body model on it (:class:`motion.bodyparts.BodyModel`).
        spec: the body graph's parts (:class:`motion.body.spec.BodySpec`), measured on the
            whole motion.
        rotations: ``(T, J, 3, 3)`` float64 local joint rotations per frame.
        root: ``(T, 3)`` float64 root translation per frame, metres (``forward_kinematics``'s).
        frame_rate: Hz.
        name: where it came from (a path, for messages and reports).
    """

    skeleton: Skeleton
    model: BodyModel
    spec: BodySpec
    rotations: Tensor
    root: Tensor
    frame_rate: float
    name: str = "reference"

    @classmethod
    def from_bvh(
        cls,
        path: str | Path,
        limits: dict | str | Path | None = None,
        drop_reference_pose: bool = True,
        metres_per_unit: float | None = None,
    ) -> Reference:
        """Read a BVH (frame 0 dropped when it is a converter's reference pose, as
        :mod:`motion.synth` does) and build its body model and spec (``limits`` as
        :meth:`BodySpec.from_motion`; ``metres_per_unit`` as :meth:`Skeleton.from_bvh`:
        ``None`` estimates the file's unit)."""
        bvh = read_bvh(path)
        skeleton = Skeleton.from_bvh(bvh, metres_per_unit)
        motion = bvh.motion_frames() if drop_reference_pose else bvh.motion
        rotations, root = local_rotations(
            skeleton, torch.from_numpy(motion).to(torch.float64), bvh.channels
        )
        model = BodyModel.from_skeleton(skeleton)
        spec = BodySpec.from_motion(
            skeleton, model, forward_kinematics(skeleton, rotations, root), limits
        )
        return cls(skeleton, model, spec, rotations, root, float(bvh.frame_rate), str(path))

    @property
    def num_frames(self) -> int:
        return int(self.rotations.shape[0])

    def body_frames(self, frames: Tensor, scale: float | Tensor = 1.0) -> FKResult:
        """``B_t`` at reference ``frames`` (any shape ``S``): the posture with the root joint
        at the origin and its rotation the identity, bones scaled by ``scale`` (G).
        Returns an :class:`FKResult` with positions ``(*S, J, 3)`` metres (float64)."""
        frames = torch.as_tensor(frames, dtype=torch.long, device=self.rotations.device)
        if frames.numel() and (int(frames.min()) < 0 or int(frames.max()) >= self.num_frames):
            raise RegistrationError(
                f"reference frames must be in [0, {self.num_frames}); got "
                f"{int(frames.min())}..{int(frames.max())}"
            )
        return self.posture_frames(self.rotations[frames], scale)

    def posture_frames(
        self, rotations: Tensor, scale: float | Tensor = 1.0, joint_scales: Tensor | None = None
    ) -> FKResult:
        """Like :meth:`body_frames` for any local joint ``rotations`` ``(*S, J, 3, 3)`` on
        this skeleton (e.g. a registered student's): the root's rotation is ignored (taken
        as the identity) and the root joint put at the origin. ``joint_scales`` ``(J,)``
        multiplies each joint's offset on top of ``scale`` (the student's proportions:
        :meth:`Proportions.joint_scales`; differentiable)."""
        rot = rotations.to(torch.float64).clone()
        rot[..., 0, :, :] = torch.eye(3, dtype=rot.dtype, device=rot.device)
        offsets = self.skeleton.offsets.to(rot).clone()
        offsets[0] = 0.0  # the root joint sits at the origin
        if joint_scales is not None:
            offsets = offsets * joint_scales.to(rot)[:, None]
        zero = torch.zeros(*rot.shape[:-3], 3, dtype=rot.dtype, device=rot.device)
        fk = forward_kinematics(self.skeleton, rot, zero, offsets)
        # the root is at the origin, so scaling every position scales every bone
        return FKResult(fk.positions * scale, fk.rotations)

    def body_poses(self, frames: Tensor, scale: float | Tensor = 1.0) -> Tensor:
        """Part poses of ``B_t`` (:meth:`body_frames`): ``(*S, P, 7)`` float64 in the root's
        frame (proximal landmark in metres, frame quaternion ``w`` first)."""
        poses = self.spec.poses(self.model, self.skeleton, self.body_frames(frames))
        return torch.cat([poses[..., :3] * scale, poses[..., 3:]], -1)

    def posture_poses(
        self, rotations: Tensor, scale: float | Tensor = 1.0, joint_scales: Tensor | None = None
    ) -> Tensor:
        """Part poses of :meth:`posture_frames` ``(rotations, 1, joint_scales)``: ``(*S, P,
        7)`` float64 in the root's frame, as :meth:`body_poses`."""
        fk = self.posture_frames(rotations, 1.0, joint_scales)
        poses = self.spec.poses(self.model, self.skeleton, fk)
        return torch.cat([poses[..., :3] * scale, poses[..., 3:]], -1)


@dataclass(frozen=True)
class Proportions:
    """The student's proportions on top of G: a length factor per body part.

    A part's factor scales its capsule's axis and the bones that lie in it (the offsets of
    the joints whose parent moves with it, :func:`motion.body.spec.joint_parts`, and the
    End Sites of its joints); 1 everywhere is the reference's proportions times G.

    Attributes:
        part_names: ``P`` names (the spec's order).
        part_scales: ``(P,)`` float64, each part's length relative to G times the
            reference's.
        joint_parts: ``(J,)`` long, the part each joint moves with (-1: none).
        parents: ``(J,)`` long, the skeleton's parents (-1 for the root).
        measured: whether the factors were estimated (``False``: all 1, not measured).
    """

    part_names: list[str]
    part_scales: Tensor
    joint_parts: Tensor
    parents: Tensor
    measured: bool = True

    @classmethod
    def of(cls, reference: Reference, part_scales: Tensor | None = None) -> Proportions:
        """The proportions of ``part_scales`` ``(P,)`` on ``reference`` (``None``: the
        reference's own, not measured)."""
        measured = part_scales is not None
        if part_scales is None:
            part_scales = torch.ones(
                reference.spec.num_parts, dtype=torch.float64, device=reference.rotations.device
            )
        if part_scales.shape != (reference.spec.num_parts,):
            raise RegistrationError(
                f"expected one scale per part ({reference.spec.num_parts},); got "
                f"{tuple(part_scales.shape)}"
            )
        parts = joint_parts(reference.skeleton, reference.model)
        return cls(
            list(reference.spec.part_names),
            part_scales.to(torch.float64),
            parts,
            reference.skeleton.parents.to(torch.long),
            measured,
        )

    def joint_scales(self, part_scales: Tensor | None = None) -> Tensor:
        """``(J,)`` each joint's offset factor: the scale of the part its parent moves with
        (1 for the root and for bones in no part). ``part_scales`` replaces
        :attr:`part_scales` (e.g. variables being optimised; differentiable)."""
        return expand_to_joints(
            self.part_scales if part_scales is None else part_scales,
            self.joint_parts[self.parents.clamp_min(0)].masked_fill(self.parents < 0, -1),
        )

    def end_site_scales(self) -> Tensor:
        """``(J,)`` the factor of each joint's End Site offset (its own part's scale)."""
        return expand_to_joints(self.part_scales, self.joint_parts)

    def as_dict(self) -> dict[str, float]:
        """``{part: scale}`` in the spec's order."""
        return {n: float(x) for n, x in zip(self.part_names, self.part_scales, strict=True)}


def paired_part(name: str) -> str | None:
    """The name a left and right part share (``"thigh"`` for ``"thigh_l"`` and
    ``"thigh_r"``), or ``None`` for a part without a side (``"pelvis"``)."""
    return name[:-2] if name[-2:] in ("_l", "_r") else None


def expand_to_joints(part_scales: Tensor, parts: Tensor) -> Tensor:
    """``(J,)`` the entries of ``part_scales`` ``(P,)`` at ``parts`` ``(J,)`` long, 1 where
    ``parts`` is -1 (differentiable in ``part_scales``)."""
    picked = part_scales[parts.clamp_min(0)]
    return torch.where(parts >= 0, picked, torch.ones_like(picked))


def nonfinite_frames(*per_frame: Tensor) -> Tensor:
    """The frames (indices along dim 0, shared by every tensor) where any value of any of
    ``per_frame`` is NaN or infinite: ``(F, ...)`` each -> ``(n,)`` long, ascending."""
    bad = torch.zeros(per_frame[0].shape[0], dtype=torch.bool, device=per_frame[0].device)
    for x in per_frame:
        bad |= ~torch.isfinite(x.reshape(x.shape[0], -1)).all(1)
    return bad.nonzero().flatten().cpu()


def frame_ranges(frames: Tensor | list[int], most: int = 6) -> str:
    """Frame indices as runs for a message: ``[3, 4, 5, 9]`` -> ``"3-5, 9"`` (the first
    ``most`` runs, then ``"and N more"``)."""
    values = sorted(int(f) for f in (frames.tolist() if isinstance(frames, Tensor) else frames))
    runs: list[list[int]] = []
    for f in values:
        if runs and f == runs[-1][1] + 1:
            runs[-1][1] = f
        else:
            runs.append([f, f])
    text = [f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:most]]
    if len(runs) > most:
        text.append(f"and {sum(b - a + 1 for a, b in runs[most:])} more")
    return ", ".join(text)


def scaled_spec(
    spec: BodySpec, scale: float | Tensor, part_scales: Tensor | None = None
) -> BodySpec:
    """The spec of a body ``scale`` (G) times the size: capsule axes, radii and joint
    offsets multiplied; rotations, tree and limits unchanged. ``part_scales`` ``(P,)``
    (:attr:`Proportions.part_scales`) further lengthens each part's axis and the offsets of
    its children's joints, which lie in it (differentiable)."""
    if part_scales is None:
        scale = float(scale)
        if scale == 1.0:
            return spec
        shapes = PartShapes(spec.shapes.axis * scale, spec.shapes.radii * scale)
        return dataclasses.replace(spec, shapes=shapes, offsets=spec.offsets * scale)
    along = part_scales.to(spec.shapes.axis)[:, None]
    parent = spec.parents.clamp_min(0)
    shapes = PartShapes(spec.shapes.axis * along * scale, spec.shapes.radii * scale)
    return dataclasses.replace(spec, shapes=shapes, offsets=spec.offsets * along[parent] * scale)


@dataclass
class VideoFeatures:
    """What the cameras saw, as features, with the cameras.

    Attributes:
        observation: :class:`motion.body.observation.Observation` of the ``T'`` frames
            (batch 1): silhouettes ``(1, T', C, H, W)``, optional edge distances, colour
            images and 2-D keypoints ``(1, T', C, K, 3)``.
        cameras: the calibrated rig (C cameras) in the world frame of the result.
        frame_rate: video frames per second.
        keypoint_joints: for each keypoint column, the reference skeleton joint it is
            (``None``: no keypoints, or columns not matched to joints).
        name: where it came from (for messages and reports).
    """

    observation: Observation
    cameras: CameraRig
    frame_rate: float
    keypoint_joints: list[str] | None = None
    name: str = "video"

    def __post_init__(self):
        sil = self.observation.silhouette
        if sil.shape[0] != 1:
            raise RegistrationError(
                f"{self.name}: expected one video (batch 1); got {sil.shape[0]}"
            )
        if sil.shape[2] != self.cameras.num_cameras:
            raise RegistrationError(
                f"{self.name}: {sil.shape[2]} camera streams but {self.cameras.num_cameras} "
                "calibrated cameras"
            )
        if not self.frame_rate > 0:
            raise RegistrationError(f"{self.name}: frame_rate must be > 0; got {self.frame_rate}")
        kp = self.observation.keypoints
        if self.keypoint_joints is not None and (
            kp is None or kp.shape[3] != len(self.keypoint_joints)
        ):
            given = None if kp is None else kp.shape[3]
            raise RegistrationError(
                f"{self.name}: {len(self.keypoint_joints)} keypoint joint names but "
                f"{given} keypoint columns"
            )

    @property
    def num_frames(self) -> int:
        return int(self.observation.silhouette.shape[1])

    def seen(self) -> Tensor:
        """``(T',)`` bool: frames where some camera's silhouette has a pixel."""
        return (self.observation.silhouette[0] > 0.5).flatten(1).any(1)

    def within_sides(self) -> Tensor:
        """``(T',)`` bool: frames where some camera's silhouette has a pixel and none on the
        image's left or right edge: the person has not begun to enter or leave that image.
        (Feet or head cut by the bottom or top edge is a framing that the rest of the body
        still places.)"""
        inside = self.observation.silhouette[0] > 0.5  # (T', C, H, W)
        sides = inside[..., :, 0].any(-1) | inside[..., :, -1].any(-1)
        return (inside.flatten(2).any(-1) & ~sides).any(-1).cpu()

    def cut(self, frames: slice | Tensor) -> VideoFeatures:
        """The same video restricted to ``frames`` (a slice, or ``(N,)`` long indices)."""
        obs = self.observation

        def part(x):
            return None if x is None else x[:, frames]

        cut = Observation(
            obs.silhouette[:, frames], part(obs.edge_distance), part(obs.image), part(obs.keypoints)
        )
        return dataclasses.replace(self, observation=cut)


@dataclass
class Registration:
    """The result: C, T and A per video frame, G, fit scores and timings.

    Attributes:
        C: ``(T',)`` long, reference frame of each video frame.
        T_rotation: ``(T', 3, 3)`` the student root's global rotation.
        T_translation: ``(T', 3)`` the student root's position, metres.
        A: ``(T', J, 3, 3)`` articulation: per joint ``R_reference(C)^T R_student`` of the
            local rotations (identity for the root and for joints no part drives).
        G: body scale (bone lengths and widths relative to the reference).
        G_measured: whether G was measured (or given); ``False``: it is 1 because the
            cameras cannot tell body size from depth (one perspective camera).
        rotations: ``(T', J, 3, 3)`` the student's local rotations (root's = T_rotation).
        fit: ``(T',)`` per-frame fit score, silhouette IoU of the registered body against
            the observed silhouettes (mean over cameras), in [0, 1].
        C_stage1: ``(T',)`` C after approximate registration (stage 1).
        timings: seconds per stage (``"stage0"``, ``"stage1"``, ``"stage2"``, ...).
        notes: what was estimated and how (e.g. the body scale's source), for reports.
        warnings: sentences for the user about what the result cannot be trusted for
            (e.g. frames whose transform had to be carried over from their neighbours).
        part_spread_deg: ``(T', P)`` per body part (the spec's order), how far stages
            2-3's particle marginal lets its orientation go, degrees (the inference's own
            uncertainty: :func:`motion.registration.refine.rotation_spread_deg`; NaN where
            BP found no posture); empty ``(0, 0)`` when not measured.
        proportions: the student's part lengths on top of G (:class:`Proportions`; ``None``:
            the reference's, not measured).
    """

    C: Tensor
    T_rotation: Tensor
    T_translation: Tensor
    A: Tensor
    G: float
    rotations: Tensor
    fit: Tensor
    C_stage1: Tensor
    timings: dict[str, float] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    G_measured: bool = True
    part_spread_deg: Tensor = field(default_factory=lambda: torch.empty(0, 0))
    proportions: Proportions | None = None

    def joint_scales(self) -> Tensor | None:
        """``(J,)`` each joint's offset factor on top of G (``None``: all 1)."""
        return None if self.proportions is None else self.proportions.joint_scales()

    @property
    def num_frames(self) -> int:
        return int(self.C.shape[0])

    @property
    def a_degrees(self) -> Tensor:
        """``(T', J)`` the rotation angle of each joint's articulation, degrees."""
        trace = self.A.diagonal(dim1=-2, dim2=-1).sum(-1)
        return torch.rad2deg(torch.acos(((trace - 1) / 2).clamp(-1, 1)))
