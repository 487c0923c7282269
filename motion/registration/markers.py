"""A registration reference from triangulated 3-D keypoints (a TRC file, e.g. Pose2Sim's).

Keypoints have no hierarchy and no joint angles; registration wants a BVH-like reference.
:func:`skeleton_bvh_from_markers` builds one: a 22-joint skeleton with the CMU cgspeed joint
names (so :class:`motion.bodyparts.BodyModel` maps all 15 parts, automatically or with the
``cmu_cgspeed`` spec), whose joints sit at the markers' roles, and per-frame local rotations
that put them there under :func:`motion.kinematics.forward_kinematics`.

Skeleton (parents before children; ``l``/``r`` the marker roles of the keypoint spec):

    Hips (root, at the mid-hip (hip_l + hip_r) / 2; 6 channels)
      LeftUpLeg (hip_l) > LeftLeg (knee_l) > LeftFoot (ankle_l) > LeftToeBase (toe_l) > End
      RightUpLeg ... (the same on the right)
      Spine (a third of the way from the mid-hip to the neck, the keypoint specs' ``spine``)
        Neck (neck) > Head (halfway from the neck to the head top) > End Site (head_top)
        LeftShoulder (clavicle, at the neck) > LeftArm (shoulder_l) > LeftForeArm (elbow_l)
          > LeftHand (wrist_l) > LeftHandIndex1 (HAND_END_M beyond the wrist) > End
        RightShoulder ... (the same on the right)

Rest pose (all rotations zero): a T-pose facing +Z with +X to the person's left, Y up (the
BVH convention; Pose2Sim's TRC is Y up too): legs straight down -Y, feet forward +Z (the ankle-to-toe bone sloping down as a flat
foot's does, by its median angle to the heel-to-toe line where there are heel markers), spine,
neck and head up +Y, clavicles and arms sideways (+X left, -X right). Bone lengths are the
median over frames of the distance from the parent joint to the child's marker, so on a
recording whose bones are rigid the skeleton reproduces it exactly, and on triangulated
keypoints (whose marker-to-marker distances vary by centimetres) the errors are those length
deviations: every bone is aimed from where forward kinematics put its parent, so no angle
error compounds down a chain, and a joint is off by at most its parent's error plus its own
bone's deviation from the median.

Rotations: each joint's global rotation turns its bone's rest direction onto the direction
to its child's marker by the minimal swing from the parent's frame, with the twist about the
bone fixed by a second direction where the markers give one: pelvis (root) from the hip
line and the trunk, torso (Spine) from the shoulder line, thigh from the plane with the shin
(knee flexing backward), upper arm from the plane with the forearm (elbow flexing forward),
head from the nose (when there is a ``Nose`` marker). With no pelvis markers but the hips,
the pelvis takes the trunk's forward lean (its Y axis is the mid-hip-to-neck line made
perpendicular to the hip line), so the Spine joint bends sideways and twists but never flexes
forward on it. A plane that nearly
vanishes (a straight knee or elbow) hands the twist over smoothly to the minimal swing
(between :data:`PLANE_WEAK_DEG` and :data:`PLANE_STRONG_DEG` of bend). Shin and forearm have
no second direction (minimal swing: knee and elbow as hinges), nor the clavicles, the neck
and the feet (Pose2Sim's small toe triangulates mostly *behind* the big toe, not beside it, so
it would roll the foot); hands and toes keep their parent's frame (local rotation zero). A
twist never turns by more than a quarter turn between frames: where the second direction
flips (a noisy elbow bending "backward" for one frame), the last frame's twist is kept.

Euler orders (BVH channels, degrees, unwrapped over frames so angles are continuous):
``ZXY`` for the root, spine, neck, head and arms (gimbal lock at 90 degrees of pitch, trunk
flexion, head flexion or upper-arm twist -- all rare), ``ZYX`` (the CMU order) for the legs
(the ``ZXY`` lock would sit at 90 degrees of hip flexion). Units: metres throughout (a TRC in
millimetres or centimetres is converted); the BVH's frame time is ``1 / rate``.
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch

from motion.bodyparts import HAND_END_M, load_spec
from motion.bvh import BVH, write_bvh
from motion.geometry import matrix_to_euler
from motion.keypoints import Markers, read_trc
from motion.registration.types import Reference, RegistrationError

__all__ = [
    "HEAD_JOINT_FRACTION",
    "MARKER_JOINTS",
    "PLANE_STRONG_DEG",
    "PLANE_WEAK_DEG",
    "reference_from_markers",
    "skeleton_bvh_from_markers",
]

#: where the Head joint sits between the neck and the head top (no marker gives it)
HEAD_JOINT_FRACTION = 0.5
#: a twist plane (thigh-shin, upper arm-forearm, ...) is ignored below this bend, degrees ...
PLANE_WEAK_DEG = 5.0
#: ... and used alone above this one; in between, blended with the minimal swing
PLANE_STRONG_DEG = 20.0
TOE_END_M = 0.05  # End Site ahead of the toe joint (no marker; BVH leaves carry one)
FINGER_END_M = 0.03  # End Site beyond LeftHandIndex1

#: the point of the skeleton (a joint, or ``NAME.end`` for an End Site) at each marker role
MARKER_JOINTS = {
    "hip_l": "LeftUpLeg",
    "knee_l": "LeftLeg",
    "ankle_l": "LeftFoot",
    "toe_l": "LeftToeBase",
    "hip_r": "RightUpLeg",
    "knee_r": "RightLeg",
    "ankle_r": "RightFoot",
    "toe_r": "RightToeBase",
    "neck": "Neck",
    "head_top": "Head.end",
    "shoulder_l": "LeftArm",
    "elbow_l": "LeftForeArm",
    "wrist_l": "LeftHand",
    "shoulder_r": "RightArm",
    "elbow_r": "RightForeArm",
    "wrist_r": "RightHand",
}
# markers used only for twists, looked up by name (absent: the minimal swing is used)
_OPTIONAL = {"nose": "Nose", "heel_l": "LHeel", "heel_r": "RHeel"}
_UNITS = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}

_X = np.array([1.0, 0.0, 0.0])
_Y = np.array([0.0, 1.0, 0.0])
_Z = np.array([0.0, 0.0, 1.0])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _perp(v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """The part of ``v`` perpendicular to the unit vectors ``a`` (both ``(F, 3)``)."""
    return v - (v * a).sum(-1, keepdims=True) * a


def _frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(F, 3, 3)`` orthonormal frames, columns ``a``, ``b`` made perpendicular, ``a x b``."""
    e1 = _unit(a)
    e2 = _unit(_perp(b, e1))
    return np.stack([e1, e2, np.cross(e1, e2)], -1)


def _swing(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``(F, 3, 3)`` the smallest rotations taking unit vectors ``u`` onto ``v`` (``(F, 3)``).
    For (anatomically impossible) opposite vectors the axis is any perpendicular."""
    axis = np.cross(u, v)
    sin = np.linalg.norm(axis, axis=-1)
    cos = (u * v).sum(-1)
    other = np.where(np.abs(u[:, :1]) < 0.9, _X, _Y)
    axis = np.where(sin[:, None] > 1e-12, axis, np.cross(u, other))
    k = _unit(axis)
    angle = np.arctan2(sin, cos)
    kx = np.zeros((len(k), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx = kx - kx.transpose(0, 2, 1)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * kx + (1 - c) * (kx @ kx)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


class _Builder:
    """Joints added parent first; each joint's position comes from its parent's frame, then
    its own global rotation is set (:meth:`aim` or :meth:`keep`) before its children."""

    def __init__(self, frames: int):
        self.frames = frames
        self.names: list[str] = []
        self.parents: list[int] = []
        self.offsets: list[np.ndarray] = []
        self.orders: list[str] = []
        self.end_sites: dict[int, np.ndarray] = {}
        self.pos: dict[str, np.ndarray] = {}  # (F, 3) world positions
        self.rot: dict[str, np.ndarray] = {}  # (F, 3, 3) global rotations

    def root(self, name: str, pos: np.ndarray, rot: np.ndarray, order: str) -> None:
        self.names.append(name)
        self.parents.append(-1)
        self.offsets.append(np.zeros(3))
        self.orders.append(order)
        self.pos[name], self.rot[name] = pos, rot

    def joint(self, name: str, parent: str, offset: np.ndarray, order: str) -> None:
        self.names.append(name)
        self.parents.append(self.names.index(parent))
        self.offsets.append(np.asarray(offset, dtype=np.float64))
        self.orders.append(order)
        self.pos[name] = self.pos[parent] + self.rot[parent] @ self.offsets[-1]

    def median_length(self, target: np.ndarray, parent: str) -> float:
        """The median over frames of the distance from ``parent``'s joint to ``target``."""
        return float(np.median(np.linalg.norm(target - self.pos[parent], axis=-1)))

    def end_site(self, name: str, offset: np.ndarray) -> None:
        self.end_sites[self.names.index(name)] = np.asarray(offset, dtype=np.float64)

    def keep(self, name: str) -> None:
        """Local rotation zero: the joint turns with its parent."""
        self.rot[name] = self.rot[self.names[self.parents[self.names.index(name)]]]

    def aim(
        self,
        name: str,
        target: np.ndarray,
        rest: np.ndarray,
        second: np.ndarray | None = None,
        second_rest: np.ndarray | None = None,
    ) -> None:
        """Global rotation of ``name``: ``rest`` (its bone's direction at rest) onto the
        direction to ``target``, twisted so that ``second_rest`` turns toward the world
        direction ``second`` (where given and not nearly along the bone), else the minimal
        swing from the parent's frame."""
        parent = self.rot[self.names[self.parents[self.names.index(name)]]]
        a = _unit(target - self.pos[name])
        swung = _swing(parent @ rest, a) @ parent
        if second is None:
            self.rot[name] = swung
            return
        b_swing = _unit(_perp(swung @ second_rest, a))
        s = _perp(_unit(second), a)
        weak, strong = (math.sin(math.radians(d)) for d in (PLANE_WEAK_DEG, PLANE_STRONG_DEG))
        g = _smoothstep((np.linalg.norm(s, axis=-1) - weak) / (strong - weak))[:, None]
        b = g * _unit(s) + (1 - g) * b_swing
        b = _unit(np.where(np.linalg.norm(b, axis=-1, keepdims=True) > 1e-6, b, b_swing))
        for t in range(1, len(b)):  # no half turn of twist between frames: keep the last one
            prev = b[t - 1] - (b[t - 1] @ a[t]) * a[t]
            if b[t] @ prev < 0:
                b[t] = prev / max(float(np.linalg.norm(prev)), 1e-12)
        rest_frame = _frame(rest[None], second_rest[None])
        self.rot[name] = _frame(a, b) @ rest_frame.transpose(0, 2, 1)


def _fill_gaps(x: np.ndarray) -> np.ndarray:
    """``(F, 3)`` with NaN frames linearly interpolated (held at the ends)."""
    ok = np.isfinite(x).all(-1)
    if ok.all():
        return x
    t = np.arange(len(x))
    return np.stack([np.interp(t, t[ok], x[ok, k]) for k in range(3)], -1)


def _role_points(markers: Markers, spec) -> dict[str, np.ndarray]:
    """Role -> ``(F, 3)`` metres (mean of the spec's markers); gaps filled, with a warning."""
    scale = _UNITS.get(markers.unit.strip().lower())
    if scale is None:
        raise RegistrationError(
            f"marker unit {markers.unit!r} is not one of {sorted(_UNITS)}; convert the "
            "positions to metres first"
        )
    roles = load_spec(spec) if isinstance(spec, str | Path) else dict(spec)
    index = {n: i for i, n in enumerate(markers.names)}
    pos = np.asarray(markers.positions, dtype=np.float64) * scale
    if pos.ndim != 3 or pos.shape[1:] != (len(markers.names), 3) or len(pos) < 1:
        raise RegistrationError(
            f"marker positions must be (F, {len(markers.names)}, 3); got {pos.shape}"
        )
    notes, cache = [], {}

    def marker(name: str) -> np.ndarray | None:
        if name not in cache:
            x = pos[:, index[name]]
            ok = np.isfinite(x).all(-1)
            if not ok.any():
                cache[name] = None
            else:
                if not ok.all():
                    notes.append(f"{name}: {int((~ok).sum())} of {len(x)} frames interpolated")
                cache[name] = _fill_gaps(x)
        return cache[name]

    out, problems = {}, []
    for role in MARKER_JOINTS:
        names = roles.get(role)
        if names is None:
            problems.append(f"{role} (not in the spec)")
            continue
        names = [names] if isinstance(names, str) else list(names)
        absent = [n for n in names if n not in index]
        empty = [n for n in names if n in index and marker(n) is None]
        if absent or empty:
            problems.append(
                f"{role} ({', '.join(absent + empty)} {'absent' if absent else 'all NaN'})"
            )
            continue
        out[role] = np.mean([marker(n) for n in names], axis=0)
    if problems:
        raise RegistrationError(
            f"cannot build a skeleton from the markers: no usable marker for {'; '.join(problems)}. "
            f"Markers: {markers.names}"
        )
    for role, name in _OPTIONAL.items():
        if name in index and marker(name) is not None:
            out[role] = marker(name)
    if notes:
        warnings.warn(
            f"markers with NaN frames, interpolated linearly: {'; '.join(notes)}", stacklevel=3
        )
    return out


def _rest_foot(ankle: np.ndarray, toe: np.ndarray, heel: np.ndarray | None) -> np.ndarray:
    """The rest direction of the ankle-to-toe bone: forward (+Z), sloping down by the
    median angle between the ankle-to-toe and heel-to-toe lines where a heel marker exists,
    so that the rest foot stands flat (the sole, heel to toe, horizontal: the neutral of the
    clinical ankle angle, :mod:`motion.angles`); without one, horizontal."""
    if heel is None:
        return _Z
    cos = np.sum(_unit(toe - ankle) * _unit(toe - heel), axis=-1)
    slope = float(np.median(np.arccos(np.clip(cos, -1.0, 1.0))))
    return np.array([0.0, -math.sin(slope), math.cos(slope)])


def skeleton_bvh_from_markers(markers: Markers, spec="pose2sim_21") -> BVH:
    """A BVH skeleton and motion whose joints follow the markers (the module docstring
    says how).

    Args:
        markers: ``(F, M, 3)`` trajectories (:func:`motion.keypoints.read_trc`), in metres,
            millimetres or centimetres; NaN gaps are interpolated linearly over frames
            (held at the ends), with a ``UserWarning`` naming the markers.
        spec: the keypoint spec whose ``roles`` name the markers of each role
            (:func:`motion.bodyparts.load_spec`: a bundled name, a path, or a dict): every
            role of :data:`MARKER_JOINTS` is needed; a ``Nose`` marker, where present,
            fixes the head's twist, ``LHeel``/``RHeel`` the rest slope of the feet.

    Returns:
        :class:`motion.bvh.BVH` in metres at ``markers.rate`` (path ``<markers>``; write it
        with :func:`motion.bvh.write_bvh`).

    Raises:
        RegistrationError: a role without a usable marker (named), an unknown unit, a
            rate that is not positive.
    """
    if not markers.rate > 0:
        raise RegistrationError(f"marker rate must be > 0 Hz; got {markers.rate}")
    pts = _role_points(markers, spec)
    frames = len(pts["neck"])
    mid = 0.5 * (pts["hip_l"] + pts["hip_r"])
    b = _Builder(frames)
    b.root("Hips", mid, _frame(pts["hip_l"] - pts["hip_r"], pts["neck"] - mid), "ZXY")
    for side, s, sign in (("Left", "l", 1.0), ("Right", "r", -1.0)):
        hip, knee, ankle, toe = (pts[f"{k}_{s}"] for k in ("hip", "knee", "ankle", "toe"))
        b.joint(f"{side}UpLeg", "Hips", sign * b.median_length(hip, "Hips") * _X, "ZYX")
        b.aim(f"{side}UpLeg", knee, -_Y, ankle - knee, -_Z)  # the knee flexes backward
        b.joint(f"{side}Leg", f"{side}UpLeg", -b.median_length(knee, f"{side}UpLeg") * _Y, "ZYX")
        b.aim(f"{side}Leg", ankle, -_Y)
        b.joint(f"{side}Foot", f"{side}Leg", -b.median_length(ankle, f"{side}Leg") * _Y, "ZYX")
        foot = _rest_foot(ankle, toe, pts.get(f"heel_{s}"))
        b.aim(f"{side}Foot", toe, foot)
        b.joint(f"{side}ToeBase", f"{side}Foot", b.median_length(toe, f"{side}Foot") * foot, "ZYX")
        b.keep(f"{side}ToeBase")
        b.end_site(f"{side}ToeBase", TOE_END_M * _Z)
    trunk = float(np.median(np.linalg.norm(pts["neck"] - mid, axis=-1)))
    b.joint("Spine", "Hips", trunk / 3 * _Y, "ZXY")
    b.aim("Spine", pts["neck"], _Y, pts["shoulder_l"] - pts["shoulder_r"], _X)
    neck_offset = b.median_length(pts["neck"], "Spine") * _Y
    b.joint("Neck", "Spine", neck_offset, "ZXY")
    b.aim("Neck", pts["head_top"], _Y)
    head = b.median_length(pts["head_top"], "Neck")
    b.joint("Head", "Neck", HEAD_JOINT_FRACTION * head * _Y, "ZXY")
    nose = pts.get("nose")
    b.aim("Head", pts["head_top"], _Y, None if nose is None else nose - b.pos["Head"], _Z)
    b.end_site("Head", (1 - HEAD_JOINT_FRACTION) * head * _Y)
    for side, s, sign in (("Left", "l", 1.0), ("Right", "r", -1.0)):
        shoulder, elbow, wrist = (pts[f"{k}_{s}"] for k in ("shoulder", "elbow", "wrist"))
        out = sign * _X
        b.joint(f"{side}Shoulder", "Spine", neck_offset, "ZXY")
        b.aim(f"{side}Shoulder", shoulder, out)
        b.joint(
            f"{side}Arm",
            f"{side}Shoulder",
            b.median_length(shoulder, f"{side}Shoulder") * out,
            "ZXY",
        )
        b.aim(f"{side}Arm", elbow, out, wrist - elbow, _Z)  # the elbow flexes forward
        b.joint(f"{side}ForeArm", f"{side}Arm", b.median_length(elbow, f"{side}Arm") * out, "ZXY")
        b.aim(f"{side}ForeArm", wrist, out)
        b.joint(
            f"{side}Hand", f"{side}ForeArm", b.median_length(wrist, f"{side}ForeArm") * out, "ZXY"
        )
        b.keep(f"{side}Hand")
        b.joint(f"{side}HandIndex1", f"{side}Hand", HAND_END_M * out, "ZXY")
        b.keep(f"{side}HandIndex1")
        b.end_site(f"{side}HandIndex1", FINGER_END_M * out)
    return _to_bvh(b, mid, markers.rate)


def _to_bvh(b: _Builder, root: np.ndarray, rate: float) -> BVH:
    """Local rotations ``G_parent^T G_j`` as Euler channels (degrees, unwrapped)."""
    columns, channels = [root], []
    for j, name in enumerate(b.names):
        g = b.rot[name]
        local = g if b.parents[j] < 0 else b.rot[b.names[b.parents[j]]].transpose(0, 2, 1) @ g
        order = b.orders[j]
        euler = matrix_to_euler(torch.from_numpy(np.ascontiguousarray(local)), order).numpy()
        columns.append(np.unwrap(np.degrees(euler), period=360.0, axis=0))
        rot = [f"{axis}rotation" for axis in order]
        channels.append(["Xposition", "Yposition", "Zposition", *rot] if j == 0 else rot)
    return BVH(
        path=Path("<markers>"),
        names=list(b.names),
        parents=np.array(b.parents, dtype=np.int64),
        offsets=np.stack(b.offsets),
        channels=channels,
        end_sites=dict(b.end_sites),
        frame_time=1.0 / float(rate),
        motion=np.concatenate(columns, axis=1),
    )


def reference_from_markers(
    path_or_markers: str | Path | Markers,
    out_bvh: str | Path | None = None,
    spec="pose2sim_21",
) -> Reference:
    """A registration :class:`~motion.registration.types.Reference` from a TRC file (or
    :class:`~motion.keypoints.Markers`): :func:`skeleton_bvh_from_markers`, written to
    ``out_bvh`` (a temporary file when ``None``) and read back with
    :meth:`Reference.from_bvh` (every frame kept: ``drop_reference_pose=False``).

    Raises:
        RegistrationError: as :func:`skeleton_bvh_from_markers`; also when the written
            skeleton would not be read as metres (a body whose rest leg is far from an
            adult's, see :func:`motion.kinematics.estimate_metres_per_unit`).
    """
    if isinstance(path_or_markers, Markers):
        markers, name = path_or_markers, None
    else:
        markers, name = read_trc(path_or_markers), str(path_or_markers)
    bvh = skeleton_bvh_from_markers(markers, spec)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(out_bvh) if out_bvh is not None else Path(tmp) / "markers.bvh"
        write_bvh(bvh, path)
        ref = Reference.from_bvh(path, drop_reference_pose=False)
    if ref.skeleton.metres_per_unit != 1.0:
        raise RegistrationError(
            f"{name or path}: the skeleton's rest leg reads as {ref.skeleton.units_note}, not "
            "metres; the markers' scale looks wrong (a unit other than the declared one?)"
        )
    if name is not None or out_bvh is None:
        ref = dataclasses.replace(ref, name=name or "markers")
    return ref
