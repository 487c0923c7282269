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

from motion.geometry import matrix_to_euler, skew_matrix
from motion.kinematics import Skeleton, forward_kinematics

__all__ = [
    "CMU_SEGMENTS",
    "COORDINATES",
    "ClinicalAngles",
    "CoordinateWords",
    "SegmentMap",
    "clinical_angles",
    "coordinate_chain",
    "coordinate_joints",
    "coordinate_segments",
    "describe_coordinate",
]

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

    @classmethod
    def from_roles(cls, skeleton: Skeleton, mapping: dict[str, list[str]]) -> SegmentMap:
        """The segments of a skeleton whose joints are mapped to landmark roles
        (:func:`motion.bodyparts.map_roles`, :attr:`motion.bodyparts.BodyModel.mapping`): a
        limb segment turns with the joint at its proximal role (``hip_r`` the thigh,
        ``knee_r`` the shank, ``ankle_r`` the foot, ``shoulder_r`` the upper arm, ``elbow_r``
        the forearm), the pelvis with ``hips``, the torso with the neck's parent joint (the
        last spine joint, which carries the shoulders).

        Raises:
            ValueError: naming the role that is not one joint of ``skeleton``.
        """

        def joint(role: str) -> str:
            points = mapping.get(role, [])
            if len(points) != 1 or points[0] not in skeleton.names:
                raise ValueError(
                    f"clinical angles need role {role!r} mapped to one joint of the skeleton; "
                    f"got {points or 'nothing'}"
                )
            return points[0]

        def sides(role: str) -> tuple[str, str]:
            return joint(f"{role}_r"), joint(f"{role}_l")

        neck = skeleton.index(joint("neck"))
        if int(skeleton.parents[neck]) < 0:
            raise ValueError(f"the neck joint {skeleton.names[neck]!r} has no parent (the torso)")
        return cls(
            pelvis=joint("hips"),
            torso=skeleton.names[int(skeleton.parents[neck])],
            thigh=sides("hip"),
            shank=sides("knee"),
            foot=sides("ankle"),
            upper_arm=sides("shoulder"),
            forearm=sides("elbow"),
        )

    def joint(self, segment: str, side: int) -> str:
        """The joint turning ``segment`` (a field name) on ``side`` (0 right, 1 left; the
        midline segments ignore it)."""
        value = getattr(self, segment)
        return value if isinstance(value, str) else value[side]


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


#: per coordinate (without its side): the joint a reader knows, the verb of the
#: coordinate's positive sense (a finding reads "<joint> <verb> N degrees more/less") and
#: the angle's name after the joint (for tables and plots)
_WORDS = {
    "hip_flexion": ("hip", "flexes", "flexion"),
    "hip_adduction": ("hip", "adducts", "adduction"),
    "hip_rotation": ("hip", "rotates inwards", "internal rotation"),
    "knee_angle": ("knee", "flexes", "flexion"),
    "ankle_angle": ("ankle", "dorsiflexes", "dorsiflexion"),
    "arm_flex": ("shoulder", "flexes", "flexion"),
    "arm_add": ("shoulder", "adducts", "adduction"),
    "arm_rot": ("shoulder", "rotates inwards", "internal rotation"),
    "elbow_flex": ("elbow", "flexes", "flexion"),
    "lumbar_extension": ("lower back", "extends", "extension"),
    "lumbar_bending": ("lower back", "bends to the right", "bending to the right"),
    "lumbar_rotation": ("lower back", "turns to the left", "rotation to the left"),
}


@dataclass(frozen=True)
class CoordinateWords:
    """How a report names a coordinate: ``joint`` ("right knee"), ``verb`` of its positive
    sense ("flexes") and ``label`` ("right knee flexion")."""

    joint: str
    verb: str
    label: str


def describe_coordinate(name: str) -> CoordinateWords:
    """The words for a coordinate of :data:`COORDINATES`, e.g. ``knee_angle_r``: ("right
    knee", "flexes", "right knee flexion"); an unknown name is its own joint and label,
    with the verb "measures"."""
    base, _, side = name.rpartition("_")
    if side in ("r", "l") and base in _WORDS:
        joint, verb, noun = _WORDS[base]
        joint = f"{'right' if side == 'r' else 'left'} {joint}"
    elif name in _WORDS:
        joint, verb, noun = _WORDS[name]
    else:
        return CoordinateWords(name, "measures", name)
    return CoordinateWords(joint, verb, f"{joint} {noun}")


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


def _coordinate(name: str) -> _Coordinate:
    for c in _coordinates():
        if c.name == name:
            return c
    raise ValueError(f"unknown coordinate {name!r}; expected one of {COORDINATES}")


def coordinate_segments(
    skeleton: Skeleton, name: str, segments: SegmentMap = CMU_SEGMENTS
) -> tuple[int, int]:
    """The skeleton indices of the joints turning a coordinate's parent and child segments."""
    c = _coordinate(name)
    side = 1 if name.endswith("_l") else 0
    return skeleton.index(segments.joint(c.parent, side)), skeleton.index(
        segments.joint(c.child, side)
    )


def coordinate_joints(
    skeleton: Skeleton, name: str, segments: SegmentMap = CMU_SEGMENTS
) -> list[int]:
    """The joints a coordinate rests on: the joint of each of its two segments and that
    joint's children (each segment's bones), as skeleton indices in skeleton order; a
    coordinate is only as good as these joints are seen."""
    ends = set(coordinate_segments(skeleton, name, segments))
    parents = skeleton.parents.tolist()
    return sorted(ends | {k for k, p in enumerate(parents) if p in ends})


def coordinate_chain(
    skeleton: Skeleton, name: str, segments: SegmentMap = CMU_SEGMENTS
) -> list[int]:
    """The joints whose rotations change a coordinate: from its child segment's joint up
    to, not including, its parent segment's joint (skeleton indices, child first).

    Raises:
        ValueError: when the child segment's joint is not below the parent's.
    """
    top, j = coordinate_segments(skeleton, name, segments)
    chain = []
    while j >= 0 and j != top:
        chain.append(j)
        j = int(skeleton.parents[j])
    if j != top:
        raise ValueError(
            f"{name}: joint {skeleton.names[chain[0]]!r} is not below {skeleton.names[top]!r}"
        )
    return chain


@dataclass
class ClinicalAngles:
    """Clinical joint angles of a motion.

    Attributes:
        names: the coordinates (:data:`COORDINATES`), OpenSim's names.
        degrees: ``(..., K)`` one column per name, degrees.
        joint_rotations: ``(..., K, 3, 3)`` per coordinate, its joint's rotation (the child
            segment's anatomical frame in the parent's; the identity at neutral), the three
            coordinates of one joint sharing it.
    """

    names: list[str]
    degrees: Tensor
    joint_rotations: Tensor

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
    kx = skew_matrix(k)
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
        joint = segments.joint(field, side)
        neutral = turned.get(joint, torch.eye(3, dtype=F64))
        return glob[:, skeleton.index(joint)] @ neutral.T @ axes

    columns, relatives, cache = [], [], {}
    for c in _coordinates():
        side = 1 if c.name.endswith("_l") else 0
        key = (c.parent, c.child, side)
        if key not in cache:
            relative = frame(c.parent, side).transpose(-1, -2) @ frame(c.child, side)
            cache[key] = relative, torch.rad2deg(matrix_to_euler(relative, "ZXY"))
        relative, euler = cache[key]
        sign = -c.sign if (c.mirrored and side == 1) else c.sign
        columns.append(sign * euler[:, c.axis])
        relatives.append(relative)
    k = len(columns)
    degrees = torch.stack(columns, -1).reshape(*lead, k)
    return ClinicalAngles(
        list(COORDINATES), degrees, torch.stack(relatives, 1).reshape(*lead, k, 3, 3)
    )
