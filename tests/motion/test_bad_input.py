"""Malformed input to the motion readers: each case pinned to its one-line message.

The corpus is generated here (small BVH, TOML and video files written to ``tmp_path``): the
BVH reader and unit estimate, body-part mapping across the naming conventions found in public
BVH collections (with synthesized hand/foot ends where a skeleton has none), Pose2Sim
calibration files, and video reading. Hypothesis fuzzes the BVH reader and the calibration
reader with truncations and byte flips of valid files: the result is either valid or one of
the documented exception types, never another exception.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from motion.bodyparts import (
    FOOT_END_M,
    HAND_END_M,
    BodyModel,
    BodyPartMappingError,
    SynthesizedEndWarning,
    canonical_name,
    map_roles,
)
from motion.bvh import BVHError, read_bvh, write_bvh
from motion.cameras import CameraFileError, load_pose2sim_calibration
from motion.features import VideoError, read_camera_videos, read_video
from motion.kinematics import Skeleton, SkeletonError, forward_kinematics, local_rotations
from tests.conftest import SHARED_DATA, requires_shared_data
from tests.motion.test_bvh import BUNDLED

# ---------------------------------------------------------------------------------------------
# BVH files
# ---------------------------------------------------------------------------------------------

GOOD = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 20 0
    }
  }
  JOINT LeftUpLeg
  {
    OFFSET 9 -5 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 -85 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0333333
1 2 3 4 5 6 7 8 9 10 11 12
1 2 3 4 5 6 7 8 9 10 11 12
"""


def _write(tmp_path: Path, text: str | bytes, name: str = "m.bvh") -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode() if isinstance(text, str) else text)
    return path


def test_the_corpus_base_file_is_valid(tmp_path):
    bvh = read_bvh(_write(tmp_path, GOOD))
    assert bvh.names == ["Hips", "Spine", "LeftUpLeg"] and bvh.motion.shape == (2, 12)
    assert Skeleton.from_bvh(bvh).metres_per_unit == 0.01


def test_a_utf8_byte_order_mark_and_leading_blank_lines_are_accepted(tmp_path):
    bvh = read_bvh(_write(tmp_path, b"\xef\xbb\xbf\n\n" + GOOD.encode()))
    assert bvh.names == ["Hips", "Spine", "LeftUpLeg"]


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            lambda t: t.replace("0.0333333", "1e308"),
            r"m\.bvh:27: 'Frame Time:' needs seconds per frame between 1e-05 and 60; got '1e308'",
        ),
        (lambda t: t.replace("0.0333333", "0"), r"m\.bvh:27: 'Frame Time:' .*; got '0'"),
        (lambda t: t.replace("0.0333333", "-0.01"), r"m\.bvh:27: 'Frame Time:' .*; got '-0.01'"),
        (lambda t: t.replace("0.0333333", "nan"), r"m\.bvh:27: 'Frame Time:' .*; got 'nan'"),
        (lambda t: t.replace("0.0333333", "inf"), r"m\.bvh:27: 'Frame Time:' .*; got 'inf'"),
        (lambda t: t.replace("0.0333333", "1e-9"), r"m\.bvh:27: 'Frame Time:' .*; got '1e-9'"),
        (lambda t: t.replace("0.0333333", "fast"), r"m\.bvh:27: 'Frame Time:' .*; got 'fast'"),
        (
            lambda t: t.replace("Frames: 2", "Frames: 0"),
            r"m\.bvh:26: 'Frames:' needs a whole number >= 1; got '0'",
        ),
        (lambda t: t.replace("Frames: 2", "Frames: -3"), r"m\.bvh:26: 'Frames:' .*; got '-3'"),
        (lambda t: t.replace("Frames: 2", "Frames: 2.5"), r"m\.bvh:26: 'Frames:' .*; got '2\.5'"),
        (lambda t: t.replace("Frames: 2", "Frames:"), r"m\.bvh:26: 'Frames:' .*; got ''"),
        (
            lambda t: t.replace("JOINT LeftUpLeg", "JOINT Spine"),
            r"m\.bvh:15: joint name 'Spine' is already used at line 6; joint names must be unique",
        ),
        (
            lambda t: t.replace("JOINT Spine\n  {\n", "JOINT Spine\n"),
            r"m\.bvh:7: expected '\{' after the joint 'Spine' of line 6; got 'OFFSET'",
        ),
        (
            lambda t: t.replace("    OFFSET 0 10 0\n", ""),
            r"m\.bvh:13: joint 'Spine' \(line 6\) has no OFFSET",
        ),
        (
            lambda t: t.replace("      OFFSET 0 20 0\n", ""),
            r"m\.bvh:12: the End Site of line 10 \('Spine'\) has no OFFSET",
        ),
        (
            lambda t: t.replace("OFFSET 0 10 0", "OFFSET 0 10 0\n    OFFSET 0 10 0"),
            r"m\.bvh:9: a second OFFSET in the same block",
        ),
        (
            lambda t: t.replace(
                "CHANNELS 3 Zrotation Xrotation Yrotation\n    End",
                "CHANNELS 3 Zrotation Xrotation Yrotation\n    CHANNELS 1 Zrotation\n    End",
            ),
            r"m\.bvh:10: a second CHANNELS line in the same joint block",
        ),
        (
            lambda t: t.replace(
                "CHANNELS 3 Zrotation Xrotation Yrotation", "CHANNELS 2 Zrotation Zrotation", 1
            ),
            r"m\.bvh:9: CHANNELS names a channel twice: Zrotation Zrotation",
        ),
        (
            lambda t: t.replace("End Site", "End Sight", 1),
            r"m\.bvh:10: expected 'End Site'; got 'End Sight'",
        ),
        (
            lambda t: t.replace("ROOT Hips\n{", "ROOT Hips\n{ OFFSET 0 0 0"),
            r"m\.bvh:3: unexpected 'OFFSET' after '\{' \(one keyword per line\)",
        ),
        (
            lambda t: t.split("JOINT LeftUpLeg")[0],
            r"m\.bvh:\d+: no MOTION block: the file ends inside",
        ),
        (lambda t: "", r"m\.bvh:1: empty file; expected 'HIERARCHY'"),
        (
            lambda t: t.replace("HIERARCHY", "HIERARCHY:"),
            r"m\.bvh:1: expected 'HIERARCHY' as the first line; got 'HIERARCHY:'",
        ),
        (lambda t: t.replace("ROOT Hips", "MOTION"), r"m\.bvh:2: MOTION before any ROOT joint"),
    ],
    ids=[
        "frame-time-1e308",
        "frame-time-0",
        "frame-time-negative",
        "frame-time-nan",
        "frame-time-inf",
        "frame-time-tiny",
        "frame-time-text",
        "frames-0",
        "frames-negative",
        "frames-fraction",
        "frames-empty",
        "duplicate-joint",
        "no-brace",
        "joint-without-offset",
        "end-site-without-offset",
        "second-offset",
        "second-channels",
        "repeated-channel",
        "end-sight",
        "text-after-brace",
        "truncated-hierarchy",
        "empty",
        "header",
        "motion-first",
    ],
)
def test_malformed_bvh_is_one_line_naming_file_and_line(tmp_path, edit, message):
    with pytest.raises(BVHError, match=message) as info:
        read_bvh(_write(tmp_path, edit(GOOD)))
    assert "\n" not in str(info.value)


def test_utf16_is_named(tmp_path):
    with pytest.raises(BVHError, match=r"m\.bvh:1: UTF-16 text is not supported"):
        read_bvh(_write(tmp_path, GOOD.encode("utf-16")))


def test_all_zero_offsets_cannot_give_a_unit(tmp_path):
    text = GOOD.replace("OFFSET 0 10 0", "OFFSET 0 0 0").replace("OFFSET 9 -5 0", "OFFSET 0 0 0")
    text = text.replace("OFFSET 0 20 0", "OFFSET 0 0 0").replace("OFFSET 0 -85 0", "OFFSET 0 0 0")
    bvh = read_bvh(_write(tmp_path, text, "z.bvh"))  # legal BVH: the reader accepts it
    with pytest.raises(
        SkeletonError,
        match=r"z\.bvh: cannot estimate the length unit: every OFFSET and End Site offset is "
        r"zero, so the rest pose has no size; pass metres_per_unit explicitly",
    ):
        Skeleton.from_bvh(bvh)
    assert Skeleton.from_bvh(bvh, metres_per_unit=0.01).offsets.abs().max() == 0


def test_an_implausibly_small_rest_pose_cannot_give_a_unit(tmp_path):
    text = GOOD.replace("OFFSET 0 -85 0", "OFFSET 0 -1e-12 0").replace("9 -5 0", "0 0 0")
    text = text.replace("0 10 0", "0 0 0").replace("0 20 0", "0 0 0")
    with pytest.raises(SkeletonError, match=r"m\.bvh: .*would make 8\.5e\+11 m per unit"):
        Skeleton.from_bvh(read_bvh(_write(tmp_path, text)))


BVH_ERRORS = (BVHError, SkeletonError)


@settings(
    max_examples=300,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    drop=st.sets(st.integers(0, GOOD.count("\n") - 1), max_size=2),
    cut=st.integers(0, len(GOOD)),
    flips=st.lists(st.tuples(st.integers(0, len(GOOD) - 1), st.integers(0, 255)), max_size=4),
)
def test_fuzzed_bvh_gives_a_clean_error_or_a_valid_result(tmp_path, drop, cut, flips):
    """Lines dropped, then a truncation, then bytes overwritten: BVHError or SkeletonError
    (one line, naming the file), or a file that reads into consistent arrays."""
    lines = GOOD.splitlines(keepends=True)
    data = bytearray("".join(x for i, x in enumerate(lines) if i not in drop).encode())
    for pos, byte in flips:
        if pos < len(data):
            data[pos] = byte
    path = _write(tmp_path, bytes(data[:cut]))
    try:
        bvh = read_bvh(path)
        skeleton = Skeleton.from_bvh(bvh)
    except BVH_ERRORS as err:
        assert str(path) in str(err) and "\n" not in str(err)
        return
    assert bvh.motion.shape == (bvh.num_frames, sum(len(c) for c in bvh.channels))
    assert np.isfinite(bvh.motion).all() and np.isfinite(bvh.offsets).all()
    assert 1e-5 <= bvh.frame_time <= 60 and math.isfinite(skeleton.metres_per_unit)


@requires_shared_data()
@pytest.mark.shared_data
def test_a_shared_file_with_a_byte_order_mark_reads_the_same(tmp_path):
    path = SHARED_DATA / "bvh" / "cmu_cgspeed" / "09_01.bvh"
    copy = _write(tmp_path, b"\xef\xbb\xbf" + path.read_bytes())
    a, b = read_bvh(path), read_bvh(copy)
    assert a.names == b.names and np.array_equal(a.motion, b.motion)


# ---------------------------------------------------------------------------------------------
# Body-part mapping across naming conventions
# ---------------------------------------------------------------------------------------------

# A template body in centimetres (Y up, facing +Z, the character's left at +X): slot, parent
# slot, offset. "*" slots are end points (an End Site, or a joint where a convention names
# one). A convention names some slots; unnamed slots collapse into their nearest named
# ancestor (offsets summed), as zero-offset helpers do in real files.
_TEMPLATE = [
    ("hips", None, (0, 95, 0)),
    ("lowerback", "hips", (0, 0, 0)),
    ("spine", "lowerback", (0, 10, 0)),
    ("chest", "spine", (0, 15, 0)),
    ("chest2", "chest", (0, 15, 0)),
    ("lowerneck", "chest2", (0, 0, 0)),
    ("neck", "lowerneck", (0, 10, 0)),
    ("head", "neck", (0, 10, 0)),
    ("*head", "head", (0, 15, 0)),
]
for _s, _x in (("l", 1), ("r", -1)):
    _TEMPLATE += [
        (f"clavicle_{_s}", "chest2", (3 * _x, 5, 0)),
        (f"shoulder_{_s}", f"clavicle_{_s}", (15 * _x, 0, 0)),
        (f"elbow_{_s}", f"shoulder_{_s}", (28 * _x, 0, 0)),
        (f"wrist_{_s}", f"elbow_{_s}", (25 * _x, 0, 0)),
        (f"handbase_{_s}", f"wrist_{_s}", (0, 0, 0)),
        (f"fingers_{_s}", f"handbase_{_s}", (9 * _x, 0, 0)),
        (f"*fingers_{_s}", f"fingers_{_s}", (4 * _x, 0, 0)),
        (f"thumb_{_s}", f"handbase_{_s}", (2 * _x, 0, 3)),
        (f"*thumb_{_s}", f"thumb_{_s}", (3 * _x, 0, 3)),
        (f"hipjoint_{_s}", "hips", (0, 0, 0)),
        (f"hip_{_s}", f"hipjoint_{_s}", (9 * _x, -5, 0)),
        (f"knee_{_s}", f"hip_{_s}", (0, -42, 0)),
        (f"ankle_{_s}", f"knee_{_s}", (0, -42, 0)),
        (f"toe_{_s}", f"ankle_{_s}", (0, -6, 12)),
        (f"*toe_{_s}", f"toe_{_s}", (0, 0, 6)),
    ]


def _template_bvh(names: dict[str, str], ends: bool | set[str] = True) -> str:
    """A one-frame BVH of the template with these slot names. ``ends``: which ``*`` slots
    become End Sites (True: all whose joint is named or collapsed into a named one)."""
    parent = {s: p for s, p, _ in _TEMPLATE}
    offset = {s: np.array(o, dtype=float) for s, _, o in _TEMPLATE}
    joints: dict[str, tuple[str | None, np.ndarray]] = {}  # name -> (parent name, offset)
    end_sites: dict[str, np.ndarray] = {}
    for slot, _, _ in _TEMPLATE:
        total, up = offset[slot].copy(), parent[slot]
        while up is not None and up not in names:
            total, up = total + offset[up], parent[up]
        if slot in names:
            joints[names[slot]] = (names[up] if up else None, total)
        elif slot.startswith("*") and up is not None and (ends is True or slot in ends):
            end_sites.setdefault(names[up], total)
    children: dict[str | None, list[str]] = {}
    for name, (p, _) in joints.items():
        children.setdefault(p, []).append(name)
    lines = ["HIERARCHY"]

    def block(name: str, depth: int) -> None:
        pad = "  " * depth
        lines.append(f"{pad}{'JOINT' if depth else 'ROOT'} {name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {' '.join(f'{v:g}' for v in joints[name][1])}")
        pos = "Xposition Yposition Zposition " if depth == 0 else ""
        lines.append(f"{pad}  CHANNELS {6 if depth == 0 else 3} {pos}Zrotation Xrotation Yrotation")
        for child in children.get(name, []):
            block(child, depth + 1)
        if name in end_sites:
            lines.extend([f"{pad}  End Site", f"{pad}  {{"])
            lines.extend(
                [
                    f"{pad}    OFFSET {' '.join(f'{v:g}' for v in end_sites[name])}",
                    f"{pad}  }}",
                ]
            )
        lines.append(f"{pad}}}")

    (root,) = children[None]
    block(root, 0)
    channels = 3 * len(joints) + 3
    lines += ["MOTION", "Frames: 1", "Frame Time: 0.0333333", " ".join(["0"] * channels)]
    return "\n".join(lines) + "\n"


def _names(central: str, side: str, sides: tuple[str, str]) -> dict[str, str]:
    """Slot names from ``"slot=Name; ..."`` strings. In ``side``, ``{s}`` is the side as given
    (``sides``: left, right), ``{c}`` its initial in upper case, ``{i}`` in lower case."""

    def parse(text: str) -> dict[str, str]:
        return dict(item.split("=", 1) for item in text.split("; ") if item)

    names = parse(central)
    for suffix, s in zip(("_l", "_r"), sides, strict=True):
        fill = {"s": s, "c": s[0].upper(), "i": s[0].lower()}
        names |= {k + suffix: v.format(**fill) for k, v in parse(side).items()}
    return names


# convention: (slot names, which "*" slots become End Sites, expected role -> point)
CONVENTIONS = {
    # cgspeed MotionBuilder-friendly CMU (../shared/data/bvh/cmu_cgspeed)
    "cgspeed-motionbuilder": (
        _names(
            "hips=Hips; lowerback=LowerBack; spine=Spine; chest=Spine1; neck=Neck; head=Head",
            "clavicle={s}Shoulder; shoulder={s}Arm; elbow={s}ForeArm; wrist={s}Hand; "
            "handbase={s}FingerBase; fingers={s}HandIndex1; thumb={c}Thumb; "
            "hipjoint={c}HipJoint; hip={s}UpLeg; knee={s}Leg; ankle={s}Foot; toe={s}ToeBase",
            ("Left", "Right"),
        ),
        True,
        "wrist_l=LeftHand; hand_end_l=LeftHandIndex1; shoulder_l=LeftArm",
    ),
    # cgspeed 3ds Max-friendly CMU, later subjects: LeftWrist -> lhand -> LFingers (issue 11)
    "cgspeed-3dsmax": (
        _names(
            "hips=Hips; lowerback=lowerback; spine=Chest; chest=Chest2; lowerneck=lowerneck; "
            "neck=Neck; head=Head",
            "clavicle={s}Collar; shoulder={s}Shoulder; elbow={s}Elbow; wrist={s}Wrist; "
            "handbase={i}hand; fingers={c}Fingers; thumb={c}Thumb; hipjoint={c}HipJoint; "
            "hip={s}Hip; knee={s}Knee; ankle={s}Ankle; toe={s}Toe",
            ("Left", "Right"),
        ),
        True,
        "wrist_l=LeftWrist; hand_end_r=RFingers; spine=Chest; neck=lowerneck; "
        "shoulder_l=LeftShoulder; toe_l=LeftToe",
    ),
    # cgspeed Daz-friendly CMU (../shared/data/bvh/cmu_lawrennd_mocap)
    "cgspeed-daz": (
        _names(
            "hips=hip; spine=abdomen; chest=chest; neck=neck; head=head",
            "clavicle={s}Collar; shoulder={s}Shldr; elbow={s}ForeArm; wrist={s}Hand; "
            "fingers={s}Mid1; thumb={s}Thumb1; hipjoint={s}Buttock; hip={s}Thigh; "
            "knee={s}Shin; ankle={s}Foot",
            ("l", "r"),
        ),
        True,
        "wrist_l=lHand; hand_end_l=lMid1; toe_r=rFoot.end",
    ),
    # Mixamo (prefix "mixamorig:"; HeadTop_End and LeftToe_End are joints)
    "mixamo": (
        _names(
            "hips=mixamorig:Hips; spine=mixamorig:Spine; chest=mixamorig:Spine1; "
            "chest2=mixamorig:Spine2; neck=mixamorig:Neck; head=mixamorig:Head; "
            "*head=mixamorig:HeadTop_End",
            "clavicle=mixamorig:{s}Shoulder; shoulder=mixamorig:{s}Arm; "
            "elbow=mixamorig:{s}ForeArm; wrist=mixamorig:{s}Hand; "
            "fingers=mixamorig:{s}HandMiddle1; thumb=mixamorig:{s}HandThumb1; "
            "hip=mixamorig:{s}UpLeg; knee=mixamorig:{s}Leg; ankle=mixamorig:{s}Foot; "
            "toe=mixamorig:{s}ToeBase; *toe=mixamorig:{s}Toe_End",
            ("Left", "Right"),
        ),
        set(),
        "head_top=mixamorig:HeadTop_End; hand_end_l=mixamorig:LeftHandMiddle1",
    ),
    # 3ds Max Biped (Truebones and many game exports): names with spaces, "Bip01 " prefix
    "3dsmax-biped": (
        _names(
            "hips=Bip01 Pelvis; spine=Bip01 Spine; chest=Bip01 Spine1; neck=Bip01 Neck; "
            "head=Bip01 Head; *head=Bip01 HeadNub",
            "clavicle=Bip01 {s} Clavicle; shoulder=Bip01 {s} UpperArm; "
            "elbow=Bip01 {s} Forearm; wrist=Bip01 {s} Hand; fingers=Bip01 {s} Finger2; "
            "thumb=Bip01 {s} Finger0; hip=Bip01 {s} Thigh; knee=Bip01 {s} Calf; "
            "ankle=Bip01 {s} Foot; toe=Bip01 {s} Toe0; *toe=Bip01 {s} Toe0Nub",
            ("L", "R"),
        ),
        set(),
        "hips=Bip01 Pelvis; hand_end_l=Bip01 L Finger2; knee_r=Bip01 R Calf",
    ),
    # Bandai-Namco Research Motiondataset (Shoulder_L is the clavicle)
    "bandai-namco": (
        _names(
            "hips=Hips; spine=Spine; chest=Chest; neck=Neck; head=Head",
            "clavicle=Shoulder_{s}; shoulder=UpperArm_{s}; elbow=LowerArm_{s}; wrist=Hand_{s}; "
            "hip=UpperLeg_{s}; knee=LowerLeg_{s}; ankle=Foot_{s}; toe=Toes_{s}",
            ("L", "R"),
        ),
        True,
        "shoulder_l=UpperArm_L; hand_end_l=Hand_L.end; toe_r=Toes_R",
    ),
    # Unity humanoid / Xsens MVN (LeftShoulder is the clavicle)
    "unity-mvn": (
        _names(
            "hips=Hips; spine=Spine; chest=Chest; neck=Neck; head=Head",
            "clavicle={s}Shoulder; shoulder={s}UpperArm; elbow={s}LowerArm; wrist={s}Hand; "
            "hip={s}UpperLeg; knee={s}LowerLeg; ankle={s}Foot; toe={s}Toes",
            ("Left", "Right"),
        ),
        True,
        "shoulder_l=LeftUpperArm; elbow_r=RightLowerArm; hand_end_l=LeftHand.end",
    ),
    # Unreal mannequin
    "unreal": (
        _names(
            "hips=pelvis; spine=spine_01; chest=spine_02; neck=neck_01; head=head",
            "clavicle=clavicle_{s}; shoulder=upperarm_{s}; elbow=lowerarm_{s}; wrist=hand_{s}; "
            "fingers=middle_01_{s}; hip=thigh_{s}; knee=calf_{s}; ankle=foot_{s}; toe=ball_{s}",
            ("l", "r"),
        ),
        True,
        "shoulder_l=upperarm_l; hand_end_r=middle_01_r; toe_l=ball_l",
    ),
    # SMPL (L_Hand is the hand's end, L_Foot the toe; no End Sites)
    "smpl": (
        _names(
            "hips=Pelvis; spine=Spine1; chest=Spine2; chest2=Spine3; neck=Neck; head=Head",
            "clavicle={s}_Collar; shoulder={s}_Shoulder; elbow={s}_Elbow; wrist={s}_Wrist; "
            "fingers={s}_Hand; hip={s}_Hip; knee={s}_Knee; ankle={s}_Ankle; toe={s}_Foot",
            ("L", "R"),
        ),
        set(),
        "wrist_l=L_Wrist; hand_end_l=L_Hand; ankle_r=R_Ankle; toe_r=R_Foot",
    ),
    # Kinect v2 exporters
    "kinect-v2": (
        _names(
            "hips=SpineBase; spine=SpineMid; neck=Neck; head=Head",
            "shoulder=Shoulder{s}; elbow=Elbow{s}; wrist=Wrist{s}; fingers=Hand{s}; "
            "hip=Hip{s}; knee=Knee{s}; ankle=Ankle{s}; toe=Foot{s}",
            ("Left", "Right"),
        ),
        set(),
        "wrist_l=WristLeft; hand_end_l=HandLeft; toe_r=FootRight",
    ),
}


def _model(tmp_path: Path, text: str, name: str = "c.bvh"):
    skeleton = Skeleton.from_bvh(read_bvh(_write(tmp_path, text, name)))
    return skeleton, BodyModel.from_skeleton(skeleton)


def _rest_segments(skeleton: Skeleton, model: BodyModel, motion=None) -> dict[str, torch.Tensor]:
    """Part end points ``{part: (2, 3)}`` metres for one frame (all zeros: the rest pose)."""
    channels = _channels(skeleton)
    if motion is None:
        motion = torch.zeros(sum(len(c) for c in channels), dtype=torch.float64)
    fk = forward_kinematics(skeleton, *local_rotations(skeleton, motion, channels))
    seg = model.segments(model.skeleton_points(skeleton, fk))
    return dict(zip(model.part_names, seg, strict=True))


def _channels(skeleton: Skeleton) -> list[list[str]]:
    rot = ["Zrotation", "Xrotation", "Yrotation"]
    return [["Xposition", "Yposition", "Zposition", *rot]] + [rot] * (skeleton.num_joints - 1)


@pytest.mark.parametrize("convention", list(CONVENTIONS))
def test_naming_conventions_map_without_fallbacks(tmp_path, convention):
    names, ends, expected = CONVENTIONS[convention]
    expected = dict(item.split("=", 1) for item in expected.split("; "))
    with warnings.catch_warnings():
        warnings.simplefilter("error", SynthesizedEndWarning)
        skeleton, model = _model(tmp_path, _template_bvh(names, ends))
    for role, point in expected.items():
        assert model.mapping[role] == [point], role
    length = {p: float((s[1] - s[0]).norm()) for p, s in _rest_segments(skeleton, model).items()}
    for part in ("thigh_l", "thigh_r", "shin_l", "shin_r", "upper_arm_l", "forearm_r"):
        assert 0.2 < length[part] < 0.5, (part, length[part])
    for part in ("hand_l", "hand_r", "foot_l", "foot_r", "pelvis", "torso"):
        assert length[part] > 0.02, (part, length[part])


@pytest.mark.parametrize(
    ("name", "key"),
    [
        ("Bip01 L Thigh", "lthigh"),
        ("Bip001 R Forearm", "rforearm"),
        ("ValveBiped.Bip01_L_Thigh", "lthigh"),
        ("mixamorig:LeftHand", "lefthand"),
        ("mixamorigLeftHand", "lefthand"),
        ("UpperArm_L", "upperarml"),
        ("Bip01", "bip01"),
        ("LeftHand.end", "lefthand.end"),
    ],
)
def test_canonical_names(name, key):
    assert canonical_name(name) == key


def _warned_model(tmp_path: Path, text: str):
    """Skeleton, body model and the messages of its SynthesizedEndWarnings."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        skeleton, model = _model(tmp_path, text)
    return skeleton, model, [str(w.message) for w in caught if w.category is SynthesizedEndWarning]


def test_a_leaf_hand_gets_a_synthesized_end_that_moves_with_the_wrist(tmp_path):
    """LAFAN1-style: LeftHand is a leaf without End Site. The synthesized end lies
    HAND_END_M beyond the wrist along the forearm at rest (+X for the left arm), and turns
    with the wrist: 90 degrees about Z puts it HAND_END_M above the wrist."""
    names = _names(
        "hips=Hips; spine=Spine; chest=Spine1; neck=Neck; head=Head",
        "clavicle={s}Shoulder; shoulder={s}Arm; elbow={s}ForeArm; wrist={s}Hand; "
        "hip={s}UpLeg; knee={s}Leg; ankle={s}Foot; toe={s}Toe",
        ("Left", "Right"),
    )
    skeleton, model, messages = _warned_model(
        tmp_path, _template_bvh(names, {"*head", "*toe_l", "*toe_r"})
    )
    assert messages == [
        f"hand_end_{s}: no joint or End Site for the hand's end; using a synthesized point "
        f"0.09 m beyond '{side}Hand' along the forearm (name one in a spec to choose it)"
        for s, side in (("l", "Left"), ("r", "Right"))
    ]
    assert model.mapping["hand_end_l"] == ["LeftHand.tip"]
    assert model.mapping["hand_end_r"] == ["RightHand.tip"]
    rest = _rest_segments(skeleton, model)["hand_l"]
    torch.testing.assert_close(
        rest[1] - rest[0], torch.tensor([HAND_END_M, 0, 0], dtype=torch.float64)
    )
    motion = torch.zeros(3 * skeleton.num_joints + 3, dtype=torch.float64)
    wrist = skeleton.index("LeftHand")
    motion[3 + 3 * wrist] = 90.0  # Zrotation of LeftHand
    bent = _rest_segments(skeleton, model, motion)["hand_l"]
    torch.testing.assert_close(
        bent[1] - bent[0], torch.tensor([0, HAND_END_M, 0], dtype=torch.float64)
    )
    hand_r = _rest_segments(skeleton, model)["hand_r"]
    assert float(hand_r[1, 0] - hand_r[0, 0]) == pytest.approx(-HAND_END_M)


def test_a_foot_without_toe_gets_a_synthesized_end_ahead_and_below(tmp_path):
    names = _names(
        "hips=Hips; spine=Spine; neck=Neck; head=Head",
        "shoulder={s}Arm; elbow={s}ForeArm; wrist={s}Hand; fingers={s}HandIndex1; "
        "hip={s}UpLeg; knee={s}Leg; ankle={s}Foot",
        ("Left", "Right"),
    )
    skeleton, model, messages = _warned_model(tmp_path, _template_bvh(names, {"*head"}))
    assert messages == [
        f"toe_{s}: no joint or End Site for the foot's end; using a synthesized point 0.12 m "
        f"ahead of and 0.03 m below '{side}Foot' (name one in a spec to choose it)"
        for s, side in (("l", "Left"), ("r", "Right"))
    ]
    assert model.mapping["toe_l"] == ["LeftFoot.tip"]
    foot = _rest_segments(skeleton, model)["foot_l"]
    expected = torch.tensor([0, -FOOT_END_M[1], FOOT_END_M[0]], dtype=torch.float64)
    torch.testing.assert_close(foot[1] - foot[0], expected)


def test_a_wrist_end_site_is_the_hand_end_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error", SynthesizedEndWarning)
        mapping = map_roles(
            "Hips Spine Neck Head L_Shoulder L_Elbow L_Wrist R_Shoulder R_Elbow R_Wrist L_Hip "
            "L_Knee L_Ankle L_Foot R_Hip R_Knee R_Ankle R_Foot".split(),
            ["Head", "L_Wrist", "R_Wrist"],
        )
    assert mapping["hand_end_l"] == ["L_Wrist.end"] and mapping["toe_l"] == ["L_Foot"]


def test_a_synthesized_hand_needs_a_forearm(tmp_path):
    names = _names(
        "hips=Hips; spine=Spine; neck=Neck; head=Head",
        "shoulder={s}Arm; elbow={s}ForeArm; wrist={s}Hand; hip={s}UpLeg; knee={s}Leg; "
        "ankle={s}Foot; toe={s}ToeBase",
        ("Left", "Right"),
    )
    text = _template_bvh(names, ends={"*head", "*toe_l", "*toe_r"})
    text = text.replace("OFFSET 25 0 0", "OFFSET 0 0 0")  # left wrist on the elbow
    with (
        warnings.catch_warnings(),
        pytest.raises(
            BodyPartMappingError, match=r"cannot synthesize hand_end_l \(the forearm\): zero length"
        ),
    ):
        warnings.simplefilter("ignore", SynthesizedEndWarning)
        _model(tmp_path, text)


def test_a_part_still_missing_its_start_is_refused():
    with pytest.raises(BodyPartMappingError, match=r"hand_l \(no wrist_l, hand_end_l\)"):
        map_roles(["Hips", "Spine", "Neck", "Head", "LeftArm", "LeftForeArm"], ["Head"])


# ---------------------------------------------------------------------------------------------
# Pose2Sim calibration files
# ---------------------------------------------------------------------------------------------

CALIB = """[cam_01]
name = "cam_01"
size = [ 1088.0, 1920.0]
matrix = [ [ 1681.2, 0.0, 533.0], [ 0.0, 1681.1, 948.1], [ 0.0, 0.0, 1.0]]
distortions = [ -0.0007, 0.0022, 9.5e-06, 1.1e-05]
rotation = [ 1.69, 1.05, -0.42]
translation = [ 0.32, 0.96, 2.89]
fisheye = false

[metadata]
adjusted = false
"""


def _calib(tmp_path: Path, old: str = "", new: str = "", data: bytes | None = None) -> Path:
    path = tmp_path / "c.toml"
    path.write_bytes(data if data is not None else CALIB.replace(old, new).encode())
    return path


def test_the_calibration_corpus_base_is_valid(tmp_path):
    rig = load_pose2sim_calibration(_calib(tmp_path))
    assert rig.names == ["cam_01"] and rig.size.tolist() == [[1088.0, 1920.0]]
    five = "distortions = [ -0.0007, 0.0022, 9.5e-06, 1.1e-05, 0.01]"
    rig = load_pose2sim_calibration(
        _calib(tmp_path, "distortions = [ -0.0007, 0.0022, 9.5e-06, 1.1e-05]", five)
    )
    assert rig.dist[0, 4] == 0.01


_WHERE = r"c\.toml: camera \[cam_01\] "


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            "[ 0.0, 1681.1, 948.1]",
            "[ 0.0, 1681.1]",
            _WHERE
            + r"'matrix' must be numbers of shape \(3, 3\); got a ragged list \(rows of 3, 2, 3 values\)",
        ),
        (
            "[ 0.0, 1681.1, 948.1]",
            "1.0",
            _WHERE + r"'matrix' .*; got a list mixing numbers and lists",
        ),
        (
            "[ 1.69, 1.05, -0.42]",
            '[ "1.69", "1.05", "-0.42"]',
            _WHERE + r"'rotation' .*; got a list holding the string '1\.69'",
        ),
        (
            "[ 0.32, 0.96, 2.89]",
            '"0.32 0.96 2.89"',
            _WHERE
            + r"'translation' must be numbers of shape \(3,\); got the string '0\.32 0\.96 2\.89'",
        ),
        ("[ 0.32, 0.96, 2.89]", "[ 0.32, 0.96]", _WHERE + r"'translation' .*; got shape \(2,\)"),
        (
            "[ 1088.0, 1920.0]",
            "[ true, 1920.0]",
            _WHERE + r"'size' .*; got a list holding the boolean true",
        ),
        ("[ 1088.0, 1920.0]", "{ w = 1088 }", _WHERE + r"'size' .*; got a table"),
        (
            "[ -0.0007, 0.0022, 9.5e-06, 1.1e-05]",
            "[ -0.0007]",
            _WHERE
            + r"'distortions' must be numbers of shape \(4,\) or shape \(5,\); got shape \(1,\)",
        ),
        (
            "[ 1.69, 1.05, -0.42]",
            "[ nan, 1.05, -0.42]",
            _WHERE + r"'rotation' must be finite; got \[nan, 1\.05, -0\.42\]$",
        ),
        (
            "[ 0.32, 0.96, 2.89]",
            "[ 0.32, inf, 2.89]",
            _WHERE + r"'translation' must be finite; got \[0\.32, inf, 2\.89\]",
        ),
        (
            "[ [ 1681.2, 0.0, 533.0], [ 0.0, 1681.1, 948.1], [ 0.0, 0.0, 1.0]]",
            "[ [ 0.0, 0.0, 0.0], [ 0.0, 0.0, 0.0], [ 0.0, 0.0, 0.0]]",
            _WHERE
            + r"'matrix' must be \[\[fx, s, cx\], \[0, fy, cy\], \[0, 0, 1\]\] with fx, fy > 0; got \[\[0\.0, 0\.0, 0\.0\]",
        ),
        ("[ 0.0, 0.0, 1.0]]", "[ 0.0, 0.0, 2.0]]", _WHERE + r"'matrix' must be \[\[fx, s, cx\]"),
        ("[ 1681.2, 0.0, 533.0]", "[ -1681.2, 0.0, 533.0]", _WHERE + r"'matrix' .* fx, fy > 0"),
        (
            "[ 1088.0, 1920.0]",
            "[ 0.0, 0.0]",
            _WHERE + r"'size' must be \[width, height\] of at least 1 pixel; got \[0\.0, 0\.0\]",
        ),
        (
            "[ 1088.0, 1920.0]",
            "[ 1088.0, -5]",
            _WHERE + r"'size' must be \[width, height\] of at least 1 pixel",
        ),
        (
            "fisheye = false",
            'fisheye = "false"',
            _WHERE
            + r"'fisheye' must be a TOML boolean \(true or false, unquoted\); got the string 'false'",
        ),
        (
            "fisheye = false",
            "fisheye = 0",
            _WHERE + r"'fisheye' must be a TOML boolean .*; got the number 0",
        ),
        ("fisheye = false", "fisheye = true", _WHERE + r"is fisheye, which is not supported"),
        ('name = "cam_01"', "name = 3", _WHERE + r"'name' must be a string; got the number 3"),
        ("rotation = [ 1.69, 1.05, -0.42]\n", "", _WHERE + r"has no 'rotation'"),
        ("[cam_01]", "[cam_01", r"c\.toml: not valid TOML \("),
    ],
    ids=[
        "ragged",
        "mixed",
        "string-items",
        "string",
        "short",
        "boolean-item",
        "table",
        "short-distortions",
        "nan-rotation",
        "inf-translation",
        "zero-K",
        "K-bottom-row",
        "negative-fx",
        "zero-size",
        "negative-size",
        "fisheye-string",
        "fisheye-number",
        "fisheye-true",
        "name-number",
        "missing-key",
        "not-toml",
    ],
)
def test_malformed_calibration_is_one_line_naming_camera_and_key(tmp_path, old, new, message):
    assert old in CALIB
    with pytest.raises(CameraFileError, match=message) as info:
        load_pose2sim_calibration(_calib(tmp_path, old, new))
    assert "\n" not in str(info.value)


def test_a_binary_calibration_file_is_named(tmp_path):
    with pytest.raises(
        CameraFileError, match=r"c\.toml: not a text file \(not valid UTF-8 at byte 0\)"
    ):
        load_pose2sim_calibration(_calib(tmp_path, data=b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR"))


def test_a_calibration_without_cameras_is_named(tmp_path):
    with pytest.raises(CameraFileError, match=r"c\.toml: no camera tables found"):
        load_pose2sim_calibration(_calib(tmp_path, data=b"[metadata]\nadjusted = false\n"))


@settings(
    max_examples=100,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    cut=st.integers(0, len(CALIB)),
    flips=st.lists(st.tuples(st.integers(0, len(CALIB) - 1), st.integers(0, 255)), max_size=3),
)
def test_fuzzed_calibration_gives_a_clean_error_or_a_valid_rig(tmp_path, cut, flips):
    data = bytearray(CALIB.encode())
    for pos, byte in flips:
        data[pos] = byte
    path = _calib(tmp_path, data=bytes(data[:cut]))
    try:
        rig = load_pose2sim_calibration(path)
    except CameraFileError as err:
        assert str(path) in str(err)
        return
    assert torch.isfinite(rig.K).all() and (rig.K[:, 0, 0] > 0).all() and (rig.size >= 1).all()


@requires_shared_data()
@pytest.mark.shared_data
def test_the_shared_calibration_passes_the_checks():
    path = (
        SHARED_DATA / "video" / "pose2sim_balancing_trial" / "calibration" / "Calib_qualisys.toml"
    )
    assert load_pose2sim_calibration(path).num_cameras == 4


# ---------------------------------------------------------------------------------------------
# Videos
# ---------------------------------------------------------------------------------------------

FRAMES = 12


def _video(path: Path, frames: int = FRAMES, size: tuple[int, int] = (32, 24)) -> Path:
    """An MJPG AVI whose frame i is uniformly grey 20 * i (to check which frames are read)."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, size)
    assert writer.isOpened()
    for i in range(frames):
        writer.write(np.full((size[1], size[0], 3), 20 * i, dtype=np.uint8))
    writer.release()
    return path


@pytest.fixture
def video(tmp_path) -> Path:
    return _video(tmp_path / "v.avi")


def test_the_video_corpus_base_reads_the_requested_frames(video):
    frames = read_video(video, start=1, count=3, step=4, scale=0.5)
    assert frames.shape == (3, 12, 16, 3)
    np.testing.assert_allclose(frames.mean(axis=(1, 2, 3)), [20, 100, 180], atol=4)
    assert len(read_video(video, count=FRAMES + 5)) == FRAMES


_V = r"v\.avi: "


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"step": 0}, _V + r"step must be a whole number >= 1; got 0"),
        ({"step": -1}, _V + r"step must be a whole number >= 1; got -1"),
        ({"step": 1.5}, _V + r"step must be a whole number >= 1; got 1\.5"),
        ({"step": True}, _V + r"step must be a whole number >= 1; got True"),
        ({"start": -5}, _V + r"start must be a whole number >= 0; got -5"),
        ({"count": 0}, _V + r"count must be None \(every frame\) or a whole number >= 1; got 0"),
        ({"count": -2}, _V + r"count must be None .*; got -2"),
        ({"scale": 0}, _V + r"scale must be in \(0, 8\]; got 0"),
        ({"scale": -1.0}, _V + r"scale must be in \(0, 8\]; got -1\.0"),
        ({"scale": float("nan")}, _V + r"scale must be in \(0, 8\]; got nan"),
        ({"scale": 100}, _V + r"scale must be in \(0, 8\]; got 100"),
        ({"scale": "2"}, _V + r"scale must be a number in \(0, 8\]; got '2'"),
        ({"scale": 0.001}, _V + r"scale 0\.001 shrinks the 32 x 24 frames to nothing"),
        ({"start": 50}, _V + r"no frames at or after frame 50: the file has 12 frames"),
    ],
    ids=lambda v: ",".join(f"{k}={v[k]}" for k in v) if isinstance(v, dict) else None,
)
def test_bad_video_arguments_are_named(video, kwargs, message):
    with pytest.raises(VideoError, match=message) as info:
        read_video(video, **kwargs)
    assert "\n" not in str(info.value)


def test_an_empty_or_unreadable_video_is_named(tmp_path):
    with pytest.raises(VideoError, match=r"e\.avi: OpenCV (cannot open|decoded no frames)"):
        read_video(_write(tmp_path, b"RIFF\x00\x00\x00\x00AVI ", "e.avi"))


def test_camera_video_lists_are_checked(tmp_path):
    a = _video(tmp_path / "a.avi")
    b = _video(tmp_path / "b.avi", size=(48, 32))
    with pytest.raises(VideoError, match=r"needs at least one video path; got an empty list"):
        read_camera_videos([])
    with pytest.raises(
        VideoError, match=r"needs a list of video paths, one per camera; got the single path"
    ):
        read_camera_videos(str(a))
    with pytest.raises(
        VideoError,
        match=r"cameras have different frame sizes \(a\.avi: 32 x 24, b\.avi: 48 x 32\); pass "
        r"expected_sizes",
    ):
        read_camera_videos([a, b], count=2)
    with pytest.raises(
        VideoError,
        match=r"expected_sizes must be \(2, 2\), a \(width, height\) per camera; got shape \(1, 2\)",
    ):
        read_camera_videos([a, b], expected_sizes=[[32, 24]])
    with pytest.raises(
        VideoError, match=r"size_tolerance must be a whole number of pixels >= 0; got -1"
    ):
        read_camera_videos([a, b], size_tolerance=-1)
    with pytest.raises(VideoError, match=r"a\.avi: count must be None"):
        read_camera_videos([a, b], count=0)
    # different sizes are accepted when each matches its own calibration
    videos = read_camera_videos([a, b], expected_sizes=[[32, 24], [48, 32]], count=2)
    assert [v.shape for v in videos] == [(2, 24, 32, 3), (2, 32, 48, 3)]


@requires_shared_data()
@pytest.mark.shared_data
def test_the_shared_cameras_of_two_sizes_need_their_calibration():
    folder = SHARED_DATA / "video" / "pose2sim_balancing_trial"
    paths = [folder / f"cam0{c}.mp4" for c in (1, 3)]
    with pytest.raises(VideoError, match=r"cam01\.mp4: 1080 x 1920, cam03\.mp4: 1088 x 1920"):
        read_camera_videos(paths, count=1)
    rig = load_pose2sim_calibration(folder / "calibration" / "Calib_qualisys.toml")
    assert len(read_camera_videos(paths, expected_sizes=rig.size[[0, 2]], count=1)) == 2


# cgspeed's MotionBuilder names -> its 3ds Max-friendly names for the same CMU skeleton
MB_TO_MAX = {
    "LeftUpLeg": "LeftHip",
    "LeftLeg": "LeftKnee",
    "LeftFoot": "LeftAnkle",
    "LeftToeBase": "LeftToe",
    "LowerBack": "lowerback",
    "Spine": "Chest",
    "Spine1": "Chest2",
    "Neck": "lowerneck",
    "Neck1": "Neck",
    "LeftShoulder": "LeftCollar",
    "LeftArm": "LeftShoulder",
    "LeftForeArm": "LeftElbow",
    "LeftHand": "LeftWrist",
    "LeftFingerBase": "lhand",
    "LeftHandIndex1": "LFingers",
}
MB_TO_MAX |= {k.replace("Left", "Right"): v.replace("Left", "Right") for k, v in MB_TO_MAX.items()}
MB_TO_MAX |= {"RightFingerBase": "rhand", "RightHandIndex1": "RFingers"}


def test_the_bundled_walk_renamed_to_3dsmax_names_gives_the_same_landmarks(tmp_path):
    """The issue's case on real data: the CMU walk with the 3ds Max-friendly hand chain
    (LeftWrist -> lhand -> LFingers, LThumb) maps to the renamed joints of the
    MotionBuilder-named original, and every landmark of every frame is unchanged."""
    original = read_bvh(BUNDLED)
    renamed = dataclasses.replace(original, names=[MB_TO_MAX.get(n, n) for n in original.names])
    path = write_bvh(renamed, tmp_path / "max.bvh")
    models, landmarks = [], []
    for bvh in (original, read_bvh(path)):
        skeleton = Skeleton.from_bvh(bvh)
        fk = forward_kinematics(
            skeleton, *local_rotations(skeleton, torch.from_numpy(bvh.motion), bvh.channels)
        )
        models.append(BodyModel.from_skeleton(skeleton))
        landmarks.append(models[-1].landmarks(models[-1].skeleton_points(skeleton, fk)))
    expected = {r: [MB_TO_MAX.get(n, n) for n in p] for r, p in models[0].mapping.items()}
    assert models[1].mapping == expected
    assert expected["hand_end_l"] == ["LFingers"] and expected["wrist_r"] == ["RightWrist"]
    torch.testing.assert_close(landmarks[1], landmarks[0], rtol=0, atol=1e-12)


@pytest.mark.parametrize("value", [0, -1.0, float("nan"), 1e9, True, "0.01"])
def test_declared_units_are_checked(value):
    from motion.bvh import read_bvh
    from motion.kinematics import Skeleton, SkeletonError

    bvh = read_bvh(Path(__file__).resolve().parents[2] / "motion" / "data" / "cmu_02_01_walk.bvh")
    with pytest.raises(
        SkeletonError, match=r"metres_per_unit must be a number in \[1e-06, 100\]; got"
    ):
        Skeleton.from_bvh(bvh, metres_per_unit=value)
