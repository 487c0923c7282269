"""Bone proportions from 2-D joints: a synthetic student whose segments are scaled by known
factors, posed by the walk's own rotations and seen by calibrated cameras, is recovered --
exactly from exact projections (2 cameras, and 1 camera up to the anchored size), within 3 %
from noisy detections; unobservable bones keep their length."""

from __future__ import annotations

import pytest
import torch

from motion.body.proportions import ProportionsError, bone_scales, segments
from motion.kinematics import forward_kinematics
from motion.registration import Reference
from motion.synth import SynthConfig, _rig
from tests.motion.body.conftest import WALK

KEYPOINTS = [
    "LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightLeg", "RightFoot",
    "Neck1", "LeftArm", "LeftForeArm", "LeftHand", "RightArm", "RightForeArm", "RightHand",
]  # fmt: skip
#: the student: thighs longer, shins shorter, one forearm longer (segment -> factor)
TRUE = {"LeftLeg": 1.08, "RightLeg": 1.06, "LeftFoot": 0.95, "RightFoot": 0.97, "LeftHand": 1.1}


@pytest.fixture(scope="module")
def walk():
    return Reference.from_bvh(WALK)


def _student(walk, frames, cameras, noise_px=0.0, seed=0):
    sk = walk.skeleton
    observed = [sk.index(n) for n in KEYPOINTS]
    names, seg = segments(sk, observed)
    factor = torch.ones(sk.num_joints, dtype=torch.float64)
    for name, f in TRUE.items():
        factor[seg == names.index(name)] = f
    rot = walk.rotations[frames]
    fk = forward_kinematics(sk, rot, walk.root[frames], offsets=sk.offsets * factor[:, None])
    centre = fk.positions[:, 0].mean(0)
    rig = _rig(SynthConfig(cameras=cameras, size=[640, 480], focal_px=600.0), centre, 4.0)
    uv, _ = rig.project(fk.positions[:, observed])  # (T, C, O, 2)
    g = torch.Generator().manual_seed(seed)
    uv = uv + noise_px * torch.randn(uv.shape, generator=g, dtype=uv.dtype)
    kp = torch.cat([uv, torch.ones(*uv.shape[:-1], 1, dtype=uv.dtype)], -1)
    return rot, rig, kp, names, seg, factor


def test_segments_follow_the_observed_joints(walk):
    sk = walk.skeleton
    names, seg = segments(sk, [sk.index(n) for n in KEYPOINTS])
    # the thigh's bone ends at the knee's keypoint; the hand's fingers lie below no keypoint
    assert names[int(seg[sk.index("LeftLeg")])] == "LeftLeg"
    assert int(seg[sk.index("LeftToeBase")]) == -1 and int(seg[sk.index("Hips")]) == -1
    # the trunk leads to the neck and both shoulders: one shared segment
    trunk = names[int(seg[sk.index("Spine")])]
    assert set(trunk.split("+")) == {"Neck1", "LeftArm", "RightArm"}


@pytest.mark.parametrize("cameras", [1, 2])
def test_exact_projections_give_the_true_scales(walk, cameras):
    frames = torch.arange(0, 300, 15)
    rot, rig, kp, names, _seg, factor = _student(walk, frames, cameras)
    anchor = "LeftArm" if cameras == 1 else None  # an unscaled upper arm fixes the size
    out = bone_scales(walk.skeleton, rot, rig, kp, KEYPOINTS, anchor=anchor)
    assert out.segments == names and out.anchor == anchor
    torch.testing.assert_close(out.joint_scales, factor, atol=1e-6, rtol=0)
    assert float(out.residual_px.max()) < 1e-4
    assert torch.allclose(out.offsets(walk.skeleton), walk.skeleton.offsets * factor[:, None])


def test_noisy_detections_within_3_percent(walk):
    frames = torch.arange(0, 300, 6)
    rot, rig, kp, _names, seg, factor = _student(walk, frames, 2, noise_px=2.0)
    out = bone_scales(walk.skeleton, rot, rig, kp, KEYPOINTS)
    observed = seg >= 0
    err = (out.joint_scales[observed] / factor[observed] - 1).abs()
    assert float(err.max()) < 0.03, dict(
        zip(out.segments, out.segment_scales.tolist(), strict=False)
    )
    assert 1.0 < float(out.residual_px.mean()) < 3.0  # about the noise's 2 px (1.4 per axis)


def test_undetected_joints_count_for_nothing(walk):
    frames = torch.arange(0, 300, 15)
    rot, rig, kp, _names, _seg, _factor = _student(walk, frames, 2)
    wrong = kp.clone()
    knee = KEYPOINTS.index("LeftLeg")
    wrong[:, :, knee, :2] += 50.0  # far off, but confidence 0: not detected
    wrong[:, :, knee, 2] = 0.0
    out = bone_scales(walk.skeleton, rot, rig, wrong, KEYPOINTS)
    sk = walk.skeleton
    # without the knee the thigh and the shin are one segment, ending at the ankle, scaled
    # between the two true factors; the other side is still exact
    assert "LeftLeg" not in out.segments
    left = out.joint_scales[[sk.index("LeftLeg"), sk.index("LeftFoot")]]
    assert float(left[0]) == float(left[1])
    assert TRUE["LeftFoot"] < float(left[0]) < TRUE["LeftLeg"]
    # (the merged segment cannot fit both true factors, so the roots, and through them the
    # other segments, absorb a little: 0.03 % measured)
    assert abs(float(out.joint_scales[sk.index("RightLeg")]) / TRUE["RightLeg"] - 1) < 0.003


def test_bad_input_says_what_is_wrong(walk):
    frames = torch.arange(0, 40, 10)
    rot, rig, kp, *_ = _student(walk, frames, 1)
    with pytest.raises(ProportionsError, match="keypoint joint names for"):
        bone_scales(walk.skeleton, rot, rig, kp, KEYPOINTS[:-1])
    with pytest.raises(ProportionsError, match="anchor must be one of"):
        bone_scales(walk.skeleton, rot, rig, kp, KEYPOINTS, anchor="Nose")
    with pytest.raises(ProportionsError, match="no keypoint column names a detected joint"):
        bone_scales(walk.skeleton, rot, rig, kp, [None] * len(KEYPOINTS))
    with pytest.raises(ProportionsError, match="rotations must be"):
        bone_scales(walk.skeleton, rot[:, :3], rig, kp, KEYPOINTS)
