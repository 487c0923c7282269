"""A registration reference from 3-D keypoints (motion/registration/markers.py).

Synthetic: markers taken from the bundled CMU walk's joints come back through forward
kinematics of the built skeleton; real: the Pose2Sim balancing trial's triangulated TRC.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from motion.bodyparts import BodyModel, end_site_positions, load_spec
from motion.bvh import read_bvh
from motion.keypoints import Markers, read_trc
from motion.kinematics import Skeleton, forward_kinematics, local_rotations
from motion.registration.markers import (
    MARKER_JOINTS,
    PLANE_STRONG_DEG,
    reference_from_markers,
    skeleton_bvh_from_markers,
)
from motion.registration.types import RegistrationError
from tests.conftest import SHARED_DATA, requires_shared_data

WALK = "motion/data/cmu_02_01_walk.bvh"
POSE3D = SHARED_DATA / "keypoints" / "pose2sim_balancing_trial" / "pose3d"
# pose2sim_21 marker -> the CMU cgspeed point it is taken from in the synthetic walk. "Neck"
# is CMU's Neck joint (the top of Spine1, where the clavicles start: the clavicle bones are
# then rigid); "Head" the head's End Site (the head top).
FROM_CMU = {
    "LHip": "LeftUpLeg",
    "LKnee": "LeftLeg",
    "LAnkle": "LeftFoot",
    "LBigToe": "LeftToeBase",
    "RHip": "RightUpLeg",
    "RKnee": "RightLeg",
    "RAnkle": "RightFoot",
    "RBigToe": "RightToeBase",
    "Neck": "Neck",
    "Head": "Head.end",
    "LShoulder": "LeftArm",
    "LElbow": "LeftForeArm",
    "LWrist": "LeftHand",
    "RShoulder": "RightArm",
    "RElbow": "RightForeArm",
    "RWrist": "RightHand",
}
LEGS = ["LHip", "LKnee", "LAnkle", "LBigToe", "RHip", "RKnee", "RAnkle", "RBigToe"]
ROLES = load_spec("pose2sim_21")
ROLE_OF = {names[0]: role for role, names in ROLES.items() if role in MARKER_JOINTS}


def _points(bvh, metres_per_unit=None):
    """Skeleton, FK and ``{point name: (F, 3) metres}`` (joints and ``NAME.end``)."""
    skeleton = Skeleton.from_bvh(bvh, metres_per_unit)
    rot, root = local_rotations(skeleton, torch.from_numpy(bvh.motion), bvh.channels)
    fk = forward_kinematics(skeleton, rot, root)
    points = {n: fk.positions[:, j].numpy() for j, n in enumerate(skeleton.names)}
    ends = end_site_positions(skeleton, fk).numpy()
    for k, j in enumerate(skeleton.end_sites):
        points[skeleton.names[j] + ".end"] = ends[:, k]
    return skeleton, fk, points


def _walk_markers(freeze=()):
    """Markers at the walk's joints (``freeze``: CMU joints held at their first pose), a
    ``Nose`` 10 cm ahead of and 3 cm above the Head joint, and the source points."""
    walk = read_bvh(WALK)
    walk.motion = walk.motion_frames().copy()
    cols = walk.channel_slices()
    for name in freeze:
        j = walk.names.index(name)
        walk.motion[:, cols[j]] = walk.motion[:1, cols[j]]
    skeleton, fk, points = _points(walk)
    head = skeleton.index("Head")
    nose = points["Head"] + fk.rotations[:, head].numpy() @ np.array([0.0, 0.03, 0.10])
    pos = np.stack([points[p] for p in FROM_CMU.values()] + [nose], 1)
    return Markers([*FROM_CMU, "Nose"], pos, walk.frame_rate, "m"), points


def _errors(bvh, markers) -> dict[str, np.ndarray]:
    """Per marker, ``(F,)`` distance (metres) of its skeleton point from it."""
    _, _, points = _points(bvh, 1.0)
    return {
        m: np.linalg.norm(
            points[MARKER_JOINTS[ROLE_OF[m]]] - markers.positions[:, markers.names.index(m)],
            axis=-1,
        )
        for m in ROLE_OF
        if m in markers.names
    }


def _deviation(a, b) -> float:
    """Largest deviation (metres) over frames of the distance |a - b| from its median."""
    d = np.linalg.norm(a - b, axis=-1)
    return float(np.abs(d - np.median(d)).max())


def test_rigid_walk_round_trips_exactly():
    """With the walk's spine and neck joints held still every marker-to-marker distance the
    skeleton uses is rigid, so the median bone lengths are exact and forward kinematics of
    the built skeleton lands on every marker on every frame (1 micrometre; seen: 1e-15 m)."""
    markers, _ = _walk_markers(freeze=("LowerBack", "Spine", "Spine1", "Neck", "Neck1", "Head"))
    bvh = skeleton_bvh_from_markers(markers)
    errors = _errors(bvh, markers)
    assert len(errors) == 16
    worst = max(float(e.max()) for e in errors.values())
    assert worst < 1e-6, {m: float(e.max()) for m, e in errors.items()}


def test_recorded_walk_round_trips_within_its_own_non_rigidity():
    """The walk as recorded: legs and hips are rigid chains (within 1 micrometre). CMU's
    trunk bends over LowerBack, Spine and Spine1 and its neck over Neck, Neck1 and Head, so
    the mid-hip-to-neck and neck-to-head-top distances change by up to 1.5 and 0.6 mm over
    the walk, which no rigid bone can follow: the neck stays within that change (+0.25 mm
    for the spine joint sitting off the mid-hip-neck line when the trunk leans sideways on
    the pelvis), the head top within both, the arms (whose clavicles start at the neck)
    within 1 mm; every joint's mean error is under 1 mm."""
    markers, src = _walk_markers()
    bvh = skeleton_bvh_from_markers(markers)
    errors = _errors(bvh, markers)
    mid = 0.5 * (src["LeftUpLeg"] + src["RightUpLeg"])
    trunk = _deviation(mid, src["Neck"])
    head = _deviation(src["Neck"], src["Head.end"])
    assert 1e-4 < trunk < 2e-3 and head < 1e-3  # the source's own non-rigidity
    for m, e in errors.items():
        bound = {"Neck": trunk + 2.5e-4, "Head": trunk + head + 2.5e-4}.get(m, 1e-3)
        if m in LEGS:
            bound = 1e-6
        assert e.max() < bound, (m, float(e.max()), bound)
        assert e.mean() < 1e-3, (m, float(e.mean()))


def test_built_skeleton_layout_and_hinges():
    """The skeleton: CMU cgspeed names, T-pose rest offsets along the axes, 6 root channels,
    End Sites at the head, toes and fingers; frame time from the rate. Where a knee or an
    elbow bends more than PLANE_STRONG_DEG the thigh's / upper arm's twist comes from that
    plane, so the knee and the elbow are pure hinges (knee: ZYX, only X; elbow: ZXY, only
    Y); angles are continuous (the walk at 120 Hz changes no channel by more than 5
    degrees a frame)."""
    markers, src = _walk_markers()
    bvh = skeleton_bvh_from_markers(markers)
    assert bvh.names[:5] == ["Hips", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"]
    assert {"Spine", "Neck", "Head", "LeftShoulder", "RightHandIndex1"} <= set(bvh.names)
    assert bvh.channels[0][:3] == ["Xposition", "Yposition", "Zposition"]
    assert all(len(c) == 3 for c in bvh.channels[1:])
    assert bvh.frame_time == pytest.approx(1 / markers.rate)
    assert {bvh.names[j] for j in bvh.end_sites} == {
        "Head",
        "LeftToeBase",
        "RightToeBase",
        "LeftHandIndex1",
        "RightHandIndex1",
    }
    off = dict(zip(bvh.names, bvh.offsets, strict=True))
    assert off["LeftLeg"][1] < 0 and off["LeftFoot"][1] < 0 and off["LeftToeBase"][2] > 0
    assert off["LeftArm"][0] > 0 > off["RightArm"][0] and off["Spine"][1] > 0
    assert (np.count_nonzero(bvh.offsets, axis=1) <= 1).all()  # along one axis each
    # the root follows the mid-hip
    mid = 0.5 * (src["LeftUpLeg"] + src["RightUpLeg"])
    np.testing.assert_allclose(bvh.motion[:, :3], mid, atol=1e-12)
    cols = bvh.channel_slices()
    for side in ("Left", "Right"):
        s = side[0]

        def bend(a, b, c):
            u, v = src[b] - src[a], src[c] - src[b]
            cos = (u * v).sum(-1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)
            return np.degrees(np.arccos(np.clip(cos, -1, 1)))

        knee = bend(f"{side}UpLeg", f"{side}Leg", f"{side}Foot")
        elbow = bend(f"{side}Arm", f"{side}ForeArm", f"{side}Hand")
        assert bvh.channels[bvh.names.index(f"{side}Leg")] == [
            "Zrotation",
            "Yrotation",
            "Xrotation",
        ]
        assert (knee > PLANE_STRONG_DEG).sum() > 50 and (elbow > PLANE_STRONG_DEG).sum() > 50, s
        k = bvh.motion[knee > PLANE_STRONG_DEG][:, cols[bvh.names.index(f"{side}Leg")]]
        np.testing.assert_allclose(k[:, :2], 0, atol=1e-6)
        assert (k[:, 2] > 0).all()  # the knee flexes backward: +X
        e = bvh.motion[elbow > PLANE_STRONG_DEG][:, cols[bvh.names.index(f"{side}ForeArm")]]
        np.testing.assert_allclose(e[:, :2], 0, atol=1e-6)
    assert np.abs(np.diff(bvh.motion[:, 3:], axis=0)).max() < 5.0
    # the pelvis takes the trunk's lean: the spine (ZXY) bends sideways and twists only
    np.testing.assert_allclose(bvh.motion[:, cols[bvh.names.index("Spine")]][:, 1], 0, atol=1e-9)


def test_reference_from_markers_builds_a_reference(tmp_path):
    """The written BVH reads back with the same numbers, Reference.from_bvh builds on it
    (metres, all 15 parts mapped from the joint names without synthesized ends, and with the
    cmu_cgspeed spec too), and the reference's forward kinematics is the skeleton's."""
    markers, _ = _walk_markers()
    markers = Markers(markers.names, markers.positions[::8], markers.rate / 8, "m")
    out = tmp_path / "walk_markers.bvh"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no SynthesizedEndWarning
        ref = reference_from_markers(markers, out)
    bvh = skeleton_bvh_from_markers(markers)
    back = read_bvh(out)
    np.testing.assert_array_equal(back.motion, bvh.motion)
    np.testing.assert_array_equal(back.offsets, bvh.offsets)
    assert ref.num_frames == len(markers.positions)
    assert ref.frame_rate == pytest.approx(markers.rate)
    assert ref.skeleton.metres_per_unit == 1.0
    assert ref.model.num_parts == 15 and ref.spec.num_parts == 15
    assert ref.model.mapping["head_top"] == ["Head.end"]
    assert ref.model.mapping["hand_end_l"] == ["LeftHandIndex1"]
    assert BodyModel.from_skeleton(ref.skeleton, "cmu_cgspeed").num_parts == 15
    fk = forward_kinematics(ref.skeleton, ref.rotations, ref.root)
    _, _, points = _points(bvh, 1.0)
    np.testing.assert_allclose(fk.positions[:, 0].numpy(), points["Hips"], atol=1e-12)
    # without a file: a temporary one, the reference named after the markers
    assert reference_from_markers(markers).name == "markers"


def test_units_gaps_and_missing_markers():
    """Millimetres give the same skeleton as metres; a NaN gap is interpolated (the joint
    lands on the line between its neighbours' frames); a role without a marker is named."""
    markers, _ = _walk_markers()
    markers = Markers(markers.names, markers.positions[:60], markers.rate, "m")
    ref = skeleton_bvh_from_markers(markers)
    mm = skeleton_bvh_from_markers(Markers(markers.names, markers.positions * 1000, 120.0, "mm"))
    np.testing.assert_allclose(mm.offsets, ref.offsets, atol=1e-12)
    np.testing.assert_allclose(mm.motion, ref.motion, atol=1e-8)
    gap = markers.positions.copy()
    wrist = markers.names.index("LWrist")
    gap[20:23, wrist] = np.nan
    with pytest.warns(UserWarning, match="LWrist: 3 of 60 frames interpolated"):
        filled = skeleton_bvh_from_markers(Markers(markers.names, gap, 120.0, "m"))
    assert np.isfinite(filled.motion).all()
    _, _, points = _points(filled, 1.0)
    line = np.linspace(gap[19, wrist], gap[23, wrist], 5)[1:4]
    assert np.linalg.norm(points["LeftHand"][20:23] - line, axis=-1).max() < 2e-3
    drop = [n for n in markers.names if n != "RKnee"]
    pos = markers.positions[:, [markers.names.index(n) for n in drop]]
    with pytest.raises(RegistrationError, match=r"knee_r \(RKnee absent\)"):
        skeleton_bvh_from_markers(Markers(drop, pos, 120.0, "m"))
    with pytest.raises(RegistrationError, match="unit 'inch'"):
        skeleton_bvh_from_markers(Markers(markers.names, markers.positions, 120.0, "inch"))


@requires_shared_data()
@pytest.mark.shared_data
@pytest.mark.parametrize(
    "name",
    ["S00_P00_T01_BalancingTrial_0-100", "S00_P00_T01_BalancingTrial_0-100_filt_butterworth"],
)
def test_pose2sim_trial(name, tmp_path):
    """The Pose2Sim balancing trial (21 markers, metres, Y up, 60 Hz, 100 frames): the
    triangulated marker-to-marker distances vary by centimetres (the right shin from 0.36
    to 0.54 m in the raw file), so constant bones leave errors: seen mean 14.2 mm, max
    101 mm (a wrist/ankle at the end of a chain) raw; 11.9 and 61 mm filtered. The BVH
    writes and reads back, Reference.from_bvh builds (metres), and the reference's joints
    are the built skeleton's."""
    markers = read_trc(POSE3D / f"{name}.trc")
    assert (markers.unit, markers.rate, markers.positions.shape) == ("m", 60.0, (100, 21, 3))
    bvh = skeleton_bvh_from_markers(markers)
    errors = _errors(bvh, markers)
    assert len(errors) == 16
    every = np.stack(list(errors.values()))
    summary = {m: (round(1000 * e.mean(), 1), round(1000 * e.max(), 1)) for m, e in errors.items()}
    assert 0.005 < every.mean() < 0.02, summary  # metres
    assert every.max() < 0.15, summary
    # the hips are one rigid pair about the mid-hip: only the hip width varies
    assert errors["LHip"] == pytest.approx(errors["RHip"])
    out = tmp_path / f"{name}.bvh"
    ref = reference_from_markers(POSE3D / f"{name}.trc", out)
    back = read_bvh(out)
    np.testing.assert_array_equal(back.motion, bvh.motion)
    assert ref.num_frames == 100 and ref.frame_rate == pytest.approx(60.0)
    assert ref.skeleton.metres_per_unit == 1.0 and ref.model.num_parts == 15
    assert ref.name.endswith(f"{name}.trc")
    fk = forward_kinematics(ref.skeleton, ref.rotations, ref.root)
    _, _, points = _points(bvh, 1.0)
    for joint in ("LeftHand", "RightFoot", "Head"):
        np.testing.assert_allclose(
            fk.positions[:, ref.skeleton.index(joint)].numpy(), points[joint], atol=1e-9
        )
    # continuity: no half-turn twist flips (the raw file's noisiest frame turns 84 degrees)
    assert np.abs(np.diff(bvh.motion[:, 3:], axis=0)).max() < 90.0


def test_heel_markers_slope_the_rest_foot_so_that_its_sole_is_flat():
    """With heel markers (rigid on the foot: 6 cm below and 4 cm behind the ankle in the
    foot's frame) the rest ankle-to-toe bone slopes down by the angle between the
    ankle-to-toe and heel-to-toe lines, so the rest sole is horizontal (the clinical ankle
    angle's neutral); the legs still land on their markers; without heels the foot is
    horizontal."""
    markers, src = _walk_markers()
    walk = read_bvh(WALK)
    walk.motion = walk.motion_frames().copy()
    skeleton, fk, _ = _points(walk)
    heels, want = [], {}
    for side in ("Left", "Right"):
        foot = skeleton.index(f"{side}Foot")
        toe_local = skeleton.offsets[skeleton.index(f"{side}ToeBase")].double().numpy()
        toe_dir = toe_local / np.linalg.norm(toe_local)
        # the heel below and behind the ankle: -0.06 along the foot frame's "down" (the
        # component of -Y orthogonal to the foot bone), -0.04 along the bone
        down = np.array([0.0, -1.0, 0.0]) - toe_dir * -toe_dir[1]
        heel_local = 0.06 * down / np.linalg.norm(down) - 0.04 * toe_dir
        heels.append(src[f"{side}Foot"] + fk.rotations[:, foot].numpy() @ heel_local)
        toe_to_ankle, toe_to_heel = -toe_local, heel_local - toe_local
        cos = (
            toe_to_ankle @ toe_to_heel / np.linalg.norm(toe_to_ankle) / np.linalg.norm(toe_to_heel)
        )
        want[side] = np.arccos(cos)
    with_heels = Markers(
        [*markers.names, "LHeel", "RHeel"],
        np.concatenate([markers.positions, np.stack(heels, 1)], 1),
        markers.rate,
        "m",
    )
    bvh = skeleton_bvh_from_markers(with_heels)
    for side in ("Left", "Right"):
        toe = bvh.offsets[bvh.names.index(f"{side}ToeBase")]
        slope = np.arctan2(-toe[1], toe[2])
        assert toe[0] == 0 and slope == pytest.approx(want[side], abs=1e-9), side
        assert 0.2 < slope < 0.6
    errors = _errors(bvh, with_heels)
    assert max(float(errors[m].max()) for m in LEGS) < 1e-6
    flat = skeleton_bvh_from_markers(markers).offsets[bvh.names.index("LeftToeBase")]
    assert flat[1] == 0 and flat[2] > 0
