"""Clinical joint angles: the anatomical coordinates OpenSim's gait models name
(``hip_flexion_r``, ``knee_angle_r``, ``ankle_angle_r``, ``lumbar_extension``, ...), zero at
the anatomical neutral (standing, arms at the sides), from segment frames.

Each segment (pelvis, torso, thigh, shank, foot, upper arm, forearm) carries an anatomical
frame with the axes of the ISB recommendations and of OpenSim: X anterior, Y up, Z to the
body's right, all at neutral. A joint's coordinates are the intrinsic Z-X-Y Euler angles of
the child's frame in the parent's (the joint coordinate system: flexion about Z first, then
ab/adduction about the floating X, then axial rotation about Y), with OpenSim's signs: hip,
arm and elbow flexion, knee flexion and ankle dorsiflexion positive; adduction and internal
rotation positive on both sides (the left side's X and Y mirrored); lumbar extension, bending
to the right and rotation about +Y positive.

The segment frames come from the skeleton's global joint rotations (a BVH bone turns with its
joint), so the angles are exactly what the motion does, not a fit to markers. Neutral is the
skeleton's rest pose with each leg and each arm turned, as a whole, until the thigh and the
upper arm point straight down (BVH rest poses stand with the legs apart and the arms out, a
T- or A-pose; the knee, ankle and elbow keep their rest bends); the body's axes are the world's vertical (:data:`UP`) and the
rest pose's left-to-right hip line made horizontal; anterior completes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from motion.kinematics import Skeleton, forward_kinematics, matrix_to_euler

__all__ = ["CMU_SEGMENTS", "COORDINATES", "ClinicalAngles", "SegmentMap", "clinical_angles"]

F64 = torch.float64


@dataclass(frozen=True)
class SegmentMap:
    """Which joint's rotation turns each segment (the joint at the segment's proximal end),
    by the skeleton's names, (right, left) for the limbs."""

    pelvis: str
    torso: str
    thigh: tuple[str, str]  # (right, left)
    shank: tuple[str, str]
    foot: tuple[str, str]
    upper_arm: tuple[str, str]
    forearm: tuple[str, str]


#: the CMU skeleton (cgspeed BVH conversions and the bundled walks)
CMU_SEGMENTS = SegmentMap(
    pelvis="Hips",
    torso="Spine1",
    thigh=("RightUpLeg", "LeftUpLeg"),
    shank=("RightLeg", "LeftLeg"),
    foot=("RightFoot", "LeftFoot"),
    upper_arm=("RightArm", "LeftArm"),
    forearm=("RightForeArm", "LeftForeArm"),
)

#: the world's vertical (BVH files are Y-up)
UP = (0.0, 1.0, 0.0)


@dataclass(frozen=True)
class _Coordinate:
    name: str
    parent: str  # a SegmentMap field (sides picked by the name's _r / _l)
    child: str
    axis: int  # index into the Z-X-Y angles: 0 Z, 1 X, 2 Y
    sign: float  # right side's (or a midline joint's) sign
    mirrored: bool  # the left side's sign is the opposite


_TABLE = [
    # hips: thigh in pelvis
    ("hip_flexion", "pelvis", "thigh", 0, 1.0, False),
    ("hip_adduction", "pelvis", "thigh", 1, 1.0, True),
    ("hip_rotation", "pelvis", "thigh", 2, 1.0, True),
    # knees, ankles
    ("knee_angle", "thigh", "shank", 0, -1.0, False),
    ("ankle_angle", "shank", "foot", 0, 1.0, False),
    # shoulders: upper arm in torso; elbows
    ("arm_flex", "torso", "upper_arm", 0, 1.0, False),
    ("arm_add", "torso", "upper_arm", 1, 1.0, True),
    ("arm_rot", "torso", "upper_arm", 2, 1.0, True),
    ("elbow_flex", "upper_arm", "forearm", 0, 1.0, False),
]
_MIDLINE = [
    ("lumbar_extension", "pelvis", "torso", 0, 1.0, False),
    ("lumbar_bending", "pelvis", "torso", 1, 1.0, False),
    ("lumbar_rotation", "pelvis", "torso", 2, 1.0, False),
]


def _coordinates() -> list[_Coordinate]:
    out = [_Coordinate(*row) for row in _MIDLINE]
    for side in ("r", "l"):
        out += [
            _Coordinate(f"{name}_{side}", parent, child, axis, sign, mirrored)
            for name, parent, child, axis, sign, mirrored in _TABLE
        ]
    return out


#: the coordinates :func:`clinical_angles` returns, in its column order
COORDINATES = [c.name for c in _coordinates()]


@dataclass
class ClinicalAngles:
    """Clinical joint angles of a motion.

    Attributes:
        names: the coordinates (:data:`COORDINATES`), OpenSim's names.
        degrees: ``(..., K)`` one column per name, degrees.
    """

    names: list[str]
    degrees: Tensor

    def __getitem__(self, name: str) -> Tensor:
        """``(...,)`` one coordinate's angles, degrees."""
        return self.degrees[..., self.names.index(name)]


def _unit(v: Tensor) -> Tensor:
    return v / v.norm()


def _rotation_between(a: Tensor, b: Tensor) -> Tensor:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b`` (Rodrigues)."""
    axis = torch.linalg.cross(a, b)
    s, c = axis.norm(), torch.dot(a, b)
    if s < 1e-12:
        return torch.eye(3, dtype=F64)
    k = axis / s
    kx = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=F64)
    angle = math.atan2(float(s), float(c))
    return torch.eye(3, dtype=F64) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def _neutral(skeleton: Skeleton, segments: SegmentMap) -> tuple[Tensor, dict[str, Tensor]]:
    """The body's axes at rest ``(3, 3)`` (columns: anterior, up, right) and, per joint that
    turns a limb segment, its global rotation at neutral (the limb turned down)."""
    j = skeleton.num_joints
    rest = forward_kinematics(
        skeleton,
        torch.eye(3, dtype=F64).expand(1, j, 3, 3),
        torch.zeros(1, 3, dtype=F64),
        skeleton.offsets.to(F64),
    ).positions[0]
    at = {name: rest[skeleton.index(name)] for name in skeleton.names}
    right = _unit(at[segments.thigh[0]] - at[segments.thigh[1]])
    up = torch.tensor(UP, dtype=F64)
    right = _unit(right - torch.dot(right, up) * up)
    anterior = torch.linalg.cross(up, right)
    axes = torch.stack([anterior, up, right], 1)
    turned = {}
    for side in range(2):
        hip, knee, ankle = segments.thigh[side], segments.shank[side], segments.foot[side]
        down = _rotation_between(_unit(at[knee] - at[hip]), -up)
        turned[hip] = turned[knee] = turned[ankle] = down
        shoulder, elbow = segments.upper_arm[side], segments.forearm[side]
        down = _rotation_between(_unit(at[elbow] - at[shoulder]), -up)
        turned[shoulder] = turned[elbow] = down
    return axes, turned


def clinical_angles(
    skeleton: Skeleton, rotations: Tensor, segments: SegmentMap = CMU_SEGMENTS
) -> ClinicalAngles:
    """Clinical joint angles of a posture or a motion.

    Args:
        skeleton: the skeleton (its rest pose defines neutral, see the module's docstring).
        rotations: ``(..., J, 3, 3)`` local joint rotations, the root's included (its
            global orientation does not change any angle).
        segments: which joints turn which segments.

    Returns:
        :class:`ClinicalAngles` with ``degrees`` ``(..., K)``, K = ``len(COORDINATES)``.
    """
    if rotations.shape[-3:] != (skeleton.num_joints, 3, 3):
        raise ValueError(
            f"rotations must be (..., {skeleton.num_joints}, 3, 3) for this skeleton; "
            f"got {tuple(rotations.shape)}"
        )
    lead = rotations.shape[:-3]
    flat = rotations.to(F64).reshape(-1, skeleton.num_joints, 3, 3)
    glob = forward_kinematics(
        skeleton, flat, torch.zeros(len(flat), 3, dtype=F64), skeleton.offsets.to(F64)
    ).rotations  # (N, J, 3, 3)
    axes, turned = _neutral(skeleton, segments)

    def frame(field: str, side: int) -> Tensor:
        """(N, 3, 3) the segment's anatomical frame: R(t) M^T A, identity at neutral."""
        joint = getattr(segments, field)
        joint = joint if isinstance(joint, str) else joint[side]
        neutral = turned.get(joint, torch.eye(3, dtype=F64))
        return glob[:, skeleton.index(joint)] @ neutral.T @ axes

    columns, cache = [], {}
    for c in _coordinates():
        side = 1 if c.name.endswith("_l") else 0
        key = (c.parent, c.child, side)
        if key not in cache:
            relative = frame(c.parent, side).transpose(-1, -2) @ frame(c.child, side)
            cache[key] = torch.rad2deg(matrix_to_euler(relative, "ZXY"))
        sign = -c.sign if (c.mirrored and side == 1) else c.sign
        columns.append(sign * cache[key][:, c.axis])
    degrees = torch.stack(columns, -1).reshape(*lead, len(columns))
    return ClinicalAngles(list(COORDINATES), degrees)
