"""Body-part mapping across naming conventions, spec files, and part geometry."""

import pytest
import torch

from motion.bodyparts import BodyModel, BodyPartMappingError, load_spec, map_roles
from motion.bvh import read_bvh
from motion.kinematics import Skeleton, forward_kinematics, local_rotations
from tests.conftest import SHARED_DATA, requires_shared_data
from tests.motion.test_bvh import BUNDLED, SHARED_FILES

MAX_NAMES = [
    "Hips",
    "LeftHip",
    "LeftKnee",
    "LeftAnkle",
    "LeftToe",
    "RightHip",
    "RightKnee",
    "RightAnkle",
    "RightToe",
    "Chest",
    "Chest2",
    "Neck",
    "Head",
    "LeftCollar",
    "LeftShoulder",
    "LeftElbow",
    "LeftWrist",
    "RightCollar",
    "RightShoulder",
    "RightElbow",
    "RightWrist",
]
MIXAMO = [
    "mixamorig:" + n
    for n in [
        "Hips",
        "Spine",
        "Spine1",
        "Spine2",
        "Neck",
        "Head",
        "HeadTop_End",
        "LeftShoulder",
        "LeftArm",
        "LeftForeArm",
        "LeftHand",
        "LeftHandMiddle1",
        "RightShoulder",
        "RightArm",
        "RightForeArm",
        "RightHand",
        "RightHandMiddle1",
        "LeftUpLeg",
        "LeftLeg",
        "LeftFoot",
        "LeftToeBase",
        "RightUpLeg",
        "RightLeg",
        "RightFoot",
        "RightToeBase",
    ]
]


def _skeleton_and_points(path, frame=1):
    bvh = read_bvh(path)
    skel = Skeleton.from_bvh(bvh)
    fk = forward_kinematics(
        skel, *local_rotations(skel, torch.from_numpy(bvh.motion[frame]), bvh.channels)
    )
    return skel, fk


def test_bundled_cmu_maps_automatically_like_its_spec():
    skel, _ = _skeleton_and_points(BUNDLED)
    auto = BodyModel.from_skeleton(skel)
    explicit = BodyModel.from_skeleton(skel, "cmu_cgspeed")
    assert auto.mapping == explicit.mapping
    assert auto.num_parts == 15


@requires_shared_data()
@pytest.mark.shared_data
@pytest.mark.parametrize("name", [f for f, *_ in SHARED_FILES])
def test_every_shared_file_maps_with_plausible_part_lengths(name):
    skel, fk = _skeleton_and_points(SHARED_DATA / "bvh" / name)
    model = BodyModel.from_skeleton(skel)
    convention = "cmu_cgspeed" if "cgspeed" in name else "cmu_daz"
    assert model.mapping == BodyModel.from_skeleton(skel, convention).mapping
    seg = model.segments(model.skeleton_points(skel, fk))
    length = (seg[:, 1] - seg[:, 0]).norm(dim=-1)
    lengths = dict(zip(model.part_names, length.tolist(), strict=True))
    for part in ("thigh_l", "thigh_r", "shin_l", "shin_r"):
        assert 0.25 < lengths[part] < 0.6, (part, lengths[part])
    for part in ("upper_arm_l", "forearm_r"):
        assert 0.1 < lengths[part] < 0.45, (part, lengths[part])


@pytest.mark.parametrize("names", [MAX_NAMES, MIXAMO], ids=["3dsmax", "mixamo"])
def test_other_naming_conventions_map(names):
    end_joints = ["LeftWrist", "RightWrist", "Head"] if names is MAX_NAMES else []
    mapping = map_roles(names, end_joints)
    assert mapping["knee_l"] == [names[2] if names is MAX_NAMES else "mixamorig:LeftLeg"]
    assert len(mapping) == 20


def test_unmappable_parts_are_listed():
    names = ["Hips", "Spine", "Neck", "Head", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"]
    with pytest.raises(
        BodyPartMappingError,
        match=r"could not map 9 body parts: upper_arm_l \(no shoulder_l, elbow_l\)",
    ):
        map_roles(names, ["Head"])


def test_spec_overrides_and_bad_spec():
    names = ["root", "spineA", "neckA", "skull"] + [
        f"{s}{j}" for s in "LR" for j in ("sh", "el", "wr", "fi", "hp", "kn", "an", "to")
    ]
    spec = {"hips": "root", "spine": "spineA", "neck": "neckA", "head_top": "skull"}
    for side, s in (("l", "L"), ("r", "R")):
        spec.update(
            {
                f"shoulder_{side}": f"{s}sh",
                f"elbow_{side}": f"{s}el",
                f"wrist_{side}": f"{s}wr",
                f"hand_end_{side}": f"{s}fi",
                f"hip_{side}": f"{s}hp",
                f"knee_{side}": f"{s}kn",
                f"ankle_{side}": f"{s}an",
                f"toe_{side}": f"{s}to",
            }
        )
    assert map_roles(names, [], spec)["knee_r"] == ["Rkn"]
    with pytest.raises(BodyPartMappingError, match="spec maps role 'hips' to 'pelvis', not found"):
        map_roles(names, [], {**spec, "hips": "pelvis"})


def test_pose2sim_keypoint_spec_builds_parts():
    model = BodyModel.from_keypoints("pose2sim_21")
    assert model.num_parts == 15
    assert load_spec("pose2sim_21")["hips"] == ["LHip", "RHip"]
    pts = torch.zeros(21, 3, dtype=torch.float64)
    pts[6] = torch.tensor([1.0, 0, 0], dtype=torch.float64)  # LHip
    pts[0] = torch.tensor([-1.0, 0, 0], dtype=torch.float64)  # RHip
    hips = model.landmarks(pts)[model.roles.index("hips")]
    torch.testing.assert_close(hips, torch.zeros(3, dtype=torch.float64))
