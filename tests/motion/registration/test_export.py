"""Exports of a registration: flexion, joint-angle tables, the student's BVH, the result file
and the summary, each checked against answers computed another way."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from motion.angles import COORDINATES, clinical_angles
from motion.bvh import BVH, read_bvh, write_bvh
from motion.kinematics import Skeleton, euler_to_matrix, forward_kinematics, local_rotations
from motion.registration.export import (
    TRUSTED_FIT,
    FindingSettings,
    JointAngles,
    JointDifference,
    _jsonable,
    bvh_from_rotations,
    end_site_positions,
    joint_angles,
    joint_flexion,
    largest_differences,
    load_registration,
    matrix_to_bvh_euler,
    per_joint_mean_abs_deg,
    proportion_words,
    save_registration,
    student_bvh,
    student_kinematics,
    summarise,
    trusted_angles,
    write_joint_angles_csv,
    write_mot,
    write_student_bvh,
)
from motion.registration.method_error import shipped_method_error
from motion.registration.movement import MovementCheck
from motion.registration.types import Proportions, Reference, Registration, RegistrationError
from tests.motion.body.conftest import WALK

F64 = torch.float64
ORDERS = ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"]


def rodrigues(axis_angle) -> torch.Tensor:
    """``(..., 3)`` axis-angle (radians) to ``(..., 3, 3)``."""
    aa = torch.as_tensor(axis_angle, dtype=F64)
    return axis_angle_to_rotation_matrix(aa.reshape(-1, 3)).reshape(*aa.shape[:-1], 3, 3)


def random_rotations(n: int, g: torch.Generator) -> torch.Tensor:
    q = torch.randn(n, 4, generator=g, dtype=F64)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


@pytest.fixture(scope="module")
def reference() -> Reference:
    return Reference.from_bvh(WALK)


def make_registration(
    reference: Reference,
    num_frames: int = 40,
    articulation: torch.Tensor | None = None,
    scale: float = 1.0,
    seed: int = 0,
) -> Registration:
    """A registration by hand: C a monotone warp (slow, then fast), a moving root with its own
    heading, rotations = the reference's at C times ``articulation`` (identity if None)."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(num_frames, dtype=F64)
    c = (20 + 2.0 * t + 0.03 * t**2).round().long().clamp_max(reference.num_frames - 1)
    j = reference.skeleton.num_joints
    a = torch.eye(3, dtype=F64).expand(num_frames, j, 3, 3).clone()
    if articulation is not None:
        a = articulation.clone()
    a[:, 0] = torch.eye(3, dtype=F64)
    rotations = reference.rotations[c] @ a
    heading = rodrigues(torch.stack([0 * t, 0.02 * t + 0.5, 0 * t], -1))
    rotations[:, 0] = heading @ reference.rotations[c, 0]
    translation = torch.stack([0.01 * t, 0.95 + 0 * t, 3.0 - 0.02 * t], -1)
    return Registration(
        C=c,
        T_rotation=rotations[:, 0].clone(),
        T_translation=translation + 0.001 * torch.randn(num_frames, 3, generator=g, dtype=F64),
        A=a,
        G=scale,
        rotations=rotations,
        fit=torch.rand(num_frames, generator=g),
        C_stage1=(c + torch.randint(-2, 3, (num_frames,), generator=g)).clamp_min(0),
        timings={"stage0": 0.5, "stage1": 2.25},
        notes={"G": "given"},
    )


# --------------------------------------------------------------------------- flexion


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_flexion_of_a_chain_at_known_angles(dtype):
    """Root -> 1 -> 2 -> End Site, bent by theta at joint 1 and phi at joint 2, then moved,
    turned and scaled: the flexion is theta and phi wherever both bones exist."""
    theta = torch.tensor([0.0, 30.0, 90.0, 135.0, 180.0], dtype=F64)
    phi = torch.tensor([10.0, 0.0, 45.0, 170.0, 60.0], dtype=F64)
    th, ph = torch.deg2rad(theta), torch.deg2rad(phi)
    p0 = torch.zeros(5, 3, dtype=F64)
    p1 = torch.tensor([1.0, 0.0, 0.0], dtype=F64).expand(5, 3)
    d12 = torch.stack([th.cos(), th.sin(), 0 * th], -1)  # bone 1 -> 2 at theta from +x
    p2 = p1 + 2.0 * d12
    d2e = torch.stack([(th + ph).cos(), (th + ph).sin(), 0 * th], -1)  # bends on by phi
    end = p2 + 0.5 * d2e
    g = torch.Generator().manual_seed(3)
    rot, shift = random_rotations(5, g), torch.randn(5, 1, 3, generator=g, dtype=F64)

    def place(x):
        return (3.7 * (rot[:, None] @ x[..., None]).squeeze(-1) + shift).to(dtype)

    pos = place(torch.stack([p0, p1, p2], 1))
    ends = torch.full_like(pos, math.nan)
    ends[:, 2] = place(end[:, None])[:, 0]
    no_end = joint_flexion(pos, [-1, 0, 1])
    with_end = joint_flexion(pos, [-1, 0, 1], ends)
    tol = 1e-3 if dtype == torch.float32 else 1e-9
    assert no_end.dtype == dtype and no_end.shape == (5, 3)
    assert torch.isnan(no_end[:, 0]).all() and torch.isnan(no_end[:, 2]).all()
    torch.testing.assert_close(no_end[:, 1].double(), theta, atol=tol, rtol=0)
    torch.testing.assert_close(with_end[:, 1].double(), theta, atol=tol, rtol=0)
    torch.testing.assert_close(with_end[:, 2].double(), phi, atol=tol, rtol=0)


def test_flexion_zero_bones_and_several_children():
    """Joint 1 has children 2 (a zero bone, on joint 1) and 3 (at 90 degrees): the first
    non-zero child is 3. Joint 2 has a zero incoming bone: NaN. Joint 4 sits on joint 3
    with one child, 5, at 45 degrees from the 1 -> 3 bone: joint 3 sees it only through
    the zero bone."""
    pos = torch.tensor(
        [
            [0.0, 0.0, 0.0],  # 0 root
            [1.0, 0.0, 0.0],  # 1
            [1.0, 0.0, 0.0],  # 2: on 1
            [1.0, 1.0, 0.0],  # 3: 90 degrees from 0 -> 1
            [1.0, 1.0, 0.0],  # 4: on 3
            [2.0, 2.0, 0.0],  # 5: 45 degrees from 1 -> 3
        ],
        dtype=F64,
    )
    parents = [-1, 0, 1, 1, 3, 4]
    through = joint_flexion(pos, parents)
    direct = joint_flexion(pos, parents, through_zero_bones=False)
    assert through[1] == pytest.approx(90.0)
    assert direct[1] == pytest.approx(90.0)  # direct children come before grandchildren
    assert through[3] == pytest.approx(45.0)
    assert math.isnan(direct[3])
    for j in (0, 2, 4, 5):
        assert math.isnan(through[j]), j


def test_end_site_positions_on_the_walk(reference):
    """The End Site of each leaf is its joint's frame applied to the (scaled) offset."""
    skel = reference.skeleton
    fk = reference.body_frames(torch.tensor([5, 50]), 1.3)
    ends = end_site_positions(skel, fk, 1.3)
    for j in range(skel.num_joints):
        if j in skel.end_sites:
            want = fk.positions[:, j] + fk.rotations[:, j] @ (skel.end_sites[j].to(F64) * 1.3)
            torch.testing.assert_close(ends[:, j], want)
        else:
            assert torch.isnan(ends[:, j]).all()


def flex_articulation(reference: Reference, reg_c, joint: str, deg: float) -> torch.Tensor:
    """``(T', J, 3, 3)`` A that turns ``joint``'s segment by ``deg`` about its parent
    segment's lateral axis (the flexion axis of the knee and the elbow): the parent's
    anatomical frame is its joint's global frame with the rest bone turned straight down,
    whose +right is the BVH's -X (the walk faces +Z at rest)."""
    skel = reference.skeleton
    j = skel.index(joint)
    p = int(skel.parents[j])
    identity = torch.eye(3, dtype=F64).expand(1, skel.num_joints, 3, 3)
    rest = forward_kinematics(skel, identity, torch.zeros(1, 3, dtype=F64)).positions[0]
    bone, down = rest[j] - rest[p], torch.tensor([0.0, -1.0, 0.0], dtype=F64)
    bone = bone / bone.norm()
    axis = torch.linalg.cross(bone, down)
    angle = torch.atan2(axis.norm(), torch.dot(bone, down))
    turn_down = rodrigues(axis / axis.norm() * angle)  # the parent bone at neutral
    right = torch.tensor([-1.0, 0.0, 0.0], dtype=F64)
    local = reference.rotations[reg_c, j]  # (T', 3, 3)
    axis_local = local.transpose(-1, -2) @ (turn_down.T @ right)  # in the joint's frame
    a = torch.eye(3, dtype=F64).expand(len(reg_c), skel.num_joints, 3, 3).clone()
    a[:, j] = rodrigues(axis_local * math.radians(deg))
    return a


def test_joint_angles_see_a_known_flexion(reference):
    """A flexes the left knee 12 and the right elbow 20 degrees more (a turn about the
    parent segment's lateral axis): knee_angle_l and elbow_flex_r differ by exactly that,
    every other coordinate not at all, whatever T and G; the joint's whole change is the
    turn; the reference's angles are clinical_angles of its rotations at C."""
    base = make_registration(reference)
    elbow = reference.skeleton.index("RightForeArm")
    a = flex_articulation(reference, base.C, "LeftLeg", -12.0)  # knee flexion: about -right
    a[:, elbow] = flex_articulation(reference, base.C, "RightForeArm", 20.0)[:, elbow]
    reg = make_registration(reference, articulation=a, scale=1.2)
    angles = joint_angles(reg, reference, frame_rate=30.0)

    # the walk's parts turn every segment of the 21 coordinates
    assert angles.coordinates == COORDINATES
    t = reg.num_frames
    torch.testing.assert_close(angles.time_s, torch.arange(t, dtype=F64) / 30.0)
    want = torch.zeros(t, len(COORDINATES), dtype=F64)
    want[:, COORDINATES.index("knee_angle_l")] = 12.0
    want[:, COORDINATES.index("elbow_flex_r")] = 20.0
    # 1e-4 degrees: the rest hip line (the body's lateral axis) is the BVH's -X only to the
    # float32 precision of its offsets, which tilts the arm's flexion axis by ~1e-6 rad
    torch.testing.assert_close(angles.difference_deg, want, atol=1e-4, rtol=0)
    torch.testing.assert_close(angles.student_deg - angles.reference_deg, angles.difference_deg)
    change = torch.zeros_like(want)  # a joint's coordinates share its whole change
    change[:, COORDINATES.index("knee_angle_l")] = 12.0
    change[:, COORDINATES.index("elbow_flex_r")] = 20.0
    torch.testing.assert_close(angles.articulation_deg, change, atol=1e-5, rtol=0)

    want_ref = clinical_angles(reference.skeleton, reference.rotations[reg.C]).degrees
    torch.testing.assert_close(angles.reference_deg, want_ref, atol=1e-9, rtol=0)
    # the walk's knee flexes between ~0 and ~75 degrees (a sanity check on the column)
    knee_l = angles.reference_deg[:, COORDINATES.index("knee_angle_l")]
    assert -5.0 <= float(knee_l.min()) < 20.0 < float(knee_l.max()) < 80.0


def test_joint_angles_reject_a_mismatched_registration(reference):
    reg = make_registration(reference, num_frames=4)
    reg.rotations = reg.rotations[:, :5]
    with pytest.raises(RegistrationError, match="rotations"):
        joint_angles(reg, reference, 30.0)
    with pytest.raises(RegistrationError, match="frame_rate"):
        joint_angles(make_registration(reference, num_frames=4), reference, 0.0)


# --------------------------------------------------------------------------- differences


def hand_angles() -> JointAngles:
    """100 frames at 50 Hz: knee_angle_l 18 less in 1.20-1.60 s (16 more in a shorter run
    before), elbow_flex_r a steady 5 more with a peak, Bar +10 then -10 (two runs of ten
    frames), Foo no difference."""
    t = 100
    diff = torch.zeros(t, 4, dtype=F64)
    diff[:, 0] = 0.5 * torch.sin(torch.arange(t, dtype=F64))  # small, under half the max
    diff[10:15, 0] = 16.0
    diff[60:81, 0] = -18.0
    diff[:, 1] = 5.0
    diff[20:23, 1] = 9.0
    diff[30:40, 2] = 10.0
    diff[40:50, 2] = -10.0
    reference = 40.0 + torch.arange(t * 4, dtype=F64).reshape(t, 4) / 100
    return JointAngles(
        coordinates=["knee_angle_l", "elbow_flex_r", "Bar", "Foo"],
        time_s=torch.arange(t, dtype=F64) / 50.0,
        reference_deg=reference,
        student_deg=reference + diff,
        difference_deg=diff,
        articulation_deg=diff.abs() + 1.0,
    )


def test_per_joint_mean_abs():
    angles = hand_angles()
    got = per_joint_mean_abs_deg(angles)
    diff = angles.difference_deg.numpy()
    assert list(got) == angles.coordinates
    for i, name in enumerate(angles.coordinates):
        assert got[name] == pytest.approx(float(np.mean(np.abs(diff[:, i]))), abs=1e-12)
    assert got["elbow_flex_r"] == pytest.approx((97 * 5 + 3 * 9) / 100)
    assert got["Foo"] == 0.0


def test_largest_differences_runs_and_text():
    diffs = largest_differences(hand_angles(), count=3)
    # ranked by mean |difference|: elbow 5.12, knee ~4.7, Bar 2; Foo never differs
    assert [d.coordinate for d in diffs] == ["elbow_flex_r", "knee_angle_l", "Bar"]
    arm, leg, bar = diffs
    assert (leg.start_s, leg.end_s) == pytest.approx((1.2, 1.6))
    assert leg.mean_difference_deg == pytest.approx(-18.0)
    assert (
        leg.text == "Left knee flexes 18 degrees less than the reference between 1.20 s and 1.60 s"
    )
    # the elbow: max 9, half 4.5: every frame exceeds it, one run over the whole video
    assert (arm.start_s, arm.end_s) == pytest.approx((0.0, 1.98))
    assert arm.mean_difference_deg == pytest.approx(5.12)
    assert arm.text.startswith("Right elbow flexes 5 degrees more than the reference between")
    # Bar: two runs of ten frames of opposite sign: the tie goes to the earlier, +10
    assert (bar.start_s, bar.end_s) == pytest.approx((0.6, 0.78))
    assert bar.mean_difference_deg == pytest.approx(10.0)
    assert bar.text == "Bar measures 10 degrees more than the reference between 0.60 s and 0.78 s"
    assert bar.to_dict()["text"] == bar.text
    assert [d.coordinate for d in largest_differences(hand_angles(), count=1)] == ["elbow_flex_r"]


# --------------------------------------------------------------------------- tables


def test_joint_angles_csv_reads_back(tmp_path, reference):
    """Every column of every frame and coordinate, the inference's uncertainty and the
    method's error of each coordinate among them (nan where not given)."""
    reg = make_registration(reference, num_frames=6)
    reg.part_spread_deg = torch.rand(
        6, reference.spec.num_parts, generator=torch.Generator().manual_seed(0)
    )
    angles = joint_angles(reg, reference, 25.0)
    errors = {name: 1.0 + k for k, name in enumerate(angles.coordinates[:-1])}  # last: none
    path = write_joint_angles_csv(angles, tmp_path / "angles.csv", errors)
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
    assert reader.fieldnames == [
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
    k_ = len(angles.coordinates)
    assert len(rows) == 6 * k_
    for n, row in enumerate(rows):
        t, k = divmod(n, k_)
        assert int(row["frame"]) == t and row["coordinate"] == angles.coordinates[k]
        assert float(row["time_s"]) == pytest.approx(t / 25.0, rel=1e-9, abs=1e-12)
        for column in ("reference_deg", "student_deg", "difference_deg", "articulation_deg"):
            want = float(getattr(angles, column)[t, k])
            assert float(row[column]) == pytest.approx(want, rel=1e-9, abs=1e-9), column
        want = float(angles.uncertainty_deg[t, k])
        assert float(row["uncertainty_deg"]) == pytest.approx(want, rel=1e-9, abs=1e-9)
        if k < k_ - 1:
            assert float(row["method_error_deg"]) == 1.0 + k
        else:
            assert row["method_error_deg"] == "nan"


def test_joint_angles_are_on_the_source_videos_clock(tmp_path, reference):
    """Frames 10, 13, 16, ... of a 30 fps video (step 3: 10 Hz): times (10 + 3 t') / 30 s,
    frame numbers in the CSV; the angles themselves do not depend on the clock."""
    reg = make_registration(reference, num_frames=5)
    angles = joint_angles(reg, reference, 10.0, first_frame=10, frame_step=3)
    frames = [10 + 3 * t for t in range(5)]
    assert angles.video_frames == frames
    torch.testing.assert_close(angles.time_s, torch.tensor(frames, dtype=F64) / 30.0)
    plain = joint_angles(reg, reference, 10.0)
    torch.testing.assert_close(angles.difference_deg, plain.difference_deg, rtol=0, atol=0)
    with write_joint_angles_csv(angles, tmp_path / "a.csv").open(newline="") as f:
        assert sorted({int(r["frame"]) for r in csv.DictReader(f)}) == frames
    with pytest.raises(RegistrationError, match="first_frame >= 0 and frame_step >= 1"):
        joint_angles(reg, reference, 10.0, first_frame=-1)


def test_mot_reads_back(tmp_path):
    angles = hand_angles()
    path = write_mot(angles, tmp_path / "student.mot")
    lines = path.read_text().splitlines()
    end = lines.index("endheader")
    header = dict(line.split("=", 1) for line in lines[1:end])
    assert lines[0] == "student"
    assert header == {"version": "1", "nRows": "100", "nColumns": "13", "inDegrees": "yes"}
    columns = lines[end + 1].split("\t")
    # the student's angle under the coordinate's own name, as OpenSim's IK writes it
    assert columns[:4] == [
        "time",
        "knee_angle_l",
        "knee_angle_l_reference",
        "knee_angle_l_difference",
    ]
    assert len(columns) == 13 and columns[-1] == "Foo_difference"
    table = np.array([[float(x) for x in line.split("\t")] for line in lines[end + 2 :]])
    assert table.shape == (100, 13)
    np.testing.assert_allclose(table[:, 0], angles.time_s.numpy(), rtol=1e-9)
    for k, name in enumerate(angles.coordinates):
        for i, (field, suffix) in enumerate(
            (
                ("student_deg", ""),
                ("reference_deg", "_reference"),
                ("difference_deg", "_difference"),
            )
        ):
            got = table[:, columns.index(f"{name}{suffix}")]
            np.testing.assert_allclose(got, getattr(angles, field)[:, k].numpy(), rtol=1e-9)
            assert columns.index(f"{name}{suffix}") == 1 + 3 * k + i


# --------------------------------------------------------------------------- BVH


@pytest.mark.parametrize("order", ORDERS)
def test_matrix_to_bvh_euler_inverts_euler_to_matrix(order):
    """Random angles give themselves back; at and near gimbal lock (middle angle +-90
    degrees, exactly and within 1e-12..1e-6 rad) the angles reproduce the matrix."""
    g = torch.Generator().manual_seed(1)
    n = 400
    angles = (torch.rand(n, 3, generator=g, dtype=F64) * 2 - 1) * torch.tensor(
        [math.pi * 0.999, math.pi / 2 * 0.999, math.pi * 0.999], dtype=F64
    )
    back = matrix_to_bvh_euler(euler_to_matrix(angles, order), order)
    torch.testing.assert_close(back, angles, atol=1e-9, rtol=0)

    lock = angles.clone()
    near = torch.tensor([0.0, 1e-12, 1e-9, 1e-7, 1e-6], dtype=F64).repeat(n // 5)
    sign = torch.where(torch.rand(n, generator=g) < 0.5, -1.0, 1.0).to(F64)
    lock[:, 1] = sign * (math.pi / 2 - near)
    m = euler_to_matrix(lock, order)
    e = matrix_to_bvh_euler(m, order)
    torch.testing.assert_close(euler_to_matrix(e, order), m, atol=1e-12, rtol=0)
    assert float(e[:, 1].abs().max()) <= math.pi / 2
    assert float(e[:, [0, 2]].abs().max()) <= math.pi


def walk_with_hard_rotations(reference: Reference, scale: float) -> Registration:
    """The hand-made registration with some joints' rotations replaced by arbitrary ones and
    by ones at and near gimbal lock of the CMU channel order (ZYX: Y at +-90 degrees)."""
    reg = make_registration(reference, num_frames=24, scale=scale, seed=5)
    g = torch.Generator().manual_seed(7)
    rot = reg.rotations.clone()
    j = reference.skeleton.num_joints
    rot[::3, 2:] = random_rotations(8 * (j - 2), g).reshape(8, j - 2, 3, 3)
    near = torch.tensor([0.0, 1e-10, 1e-7, -1e-7, 0.0, 1e-9], dtype=F64)
    for k, d in enumerate(near.tolist()):
        abc = torch.rand(j, 3, generator=g, dtype=F64) * 2 * math.pi - math.pi
        abc[:, 1] = (1 if k % 2 else -1) * (math.pi / 2 - d)
        rot[1 + 3 * k] = euler_to_matrix(abc, "ZYX")  # every joint, the root included
    reg.rotations = rot
    reg.T_rotation = rot[:, 0].clone()
    return reg


def test_student_bvh_round_trip(tmp_path, reference):
    """read_bvh + Skeleton.from_bvh + local_rotations of the written file give back the
    rotations and the root position; the skeleton is the reference's scaled by G, in the
    reference file's units, with its channels."""
    scale = 1.15
    reg = walk_with_hard_rotations(reference, scale)
    path = write_student_bvh(reg, reference, 30.0, tmp_path / "student.bvh")
    back, ref_file = read_bvh(path), read_bvh(WALK)
    assert back.names == ref_file.names and back.channels == ref_file.channels
    np.testing.assert_array_equal(back.parents, ref_file.parents)
    np.testing.assert_allclose(back.offsets, ref_file.offsets * scale, rtol=1e-15)
    assert back.end_sites.keys() == ref_file.end_sites.keys()
    for j, off in ref_file.end_sites.items():
        np.testing.assert_allclose(back.end_sites[j], off * scale, rtol=1e-15)
    assert back.frame_time == pytest.approx(1 / 30.0, rel=1e-15)
    assert back.num_frames == reg.num_frames
    assert not back.has_reference_pose()

    mpu = reference.skeleton.metres_per_unit
    skel = Skeleton.from_bvh(back, metres_per_unit=mpu)
    rot, root = local_rotations(skel, torch.from_numpy(back.motion), back.channels)
    torch.testing.assert_close(rot, reg.rotations, atol=1e-6, rtol=0)
    assert float((rot - reg.rotations).abs().max()) < 1e-12  # in fact to rounding
    torch.testing.assert_close(root + skel.offsets[0], reg.T_translation, atol=1e-6, rtol=0)
    torch.testing.assert_close(skel.offsets, reference.skeleton.offsets * scale)
    # the student's joints through the file equal those of the registration
    fk = forward_kinematics(skel, rot, root)
    want = forward_kinematics(
        reference.skeleton,
        reg.rotations,
        reg.T_translation - reference.skeleton.offsets[0] * scale,
        reference.skeleton.offsets * scale,
    )
    torch.testing.assert_close(fk.positions, want.positions, atol=1e-9, rtol=0)


def test_student_bvh_carries_the_students_proportions(tmp_path, reference):
    """With measured proportions the file's OFFSETs are the reference's times G times each
    bone's part factor (the knee's offset: the thigh's), End Sites their joint's part's; the
    file's joints equal student_kinematics'."""
    scale = 1.1
    reg = walk_with_hard_rotations(reference, scale)
    parts = torch.ones(reference.spec.num_parts, dtype=F64)
    names = reference.spec.part_names
    parts[names.index("thigh_l")] = 0.9
    parts[names.index("head")] = 1.2
    reg.proportions = Proportions.of(reference, parts)
    path = write_student_bvh(reg, reference, 30.0, tmp_path / "student.bvh")
    back, ref_file = read_bvh(path), read_bvh(WALK)
    knee, hip = ref_file.names.index("LeftLeg"), ref_file.names.index("LeftUpLeg")
    np.testing.assert_allclose(back.offsets[knee], ref_file.offsets[knee] * scale * 0.9)
    np.testing.assert_allclose(back.offsets[hip], ref_file.offsets[hip] * scale)
    head = ref_file.names.index("Head")
    np.testing.assert_allclose(back.end_sites[head], ref_file.end_sites[head] * scale * 1.2)
    skel = Skeleton.from_bvh(back, metres_per_unit=reference.skeleton.metres_per_unit)
    rot, root = local_rotations(skel, torch.from_numpy(back.motion), back.channels)
    fk = forward_kinematics(skel, rot, root)
    want = student_kinematics(reg, reference)
    torch.testing.assert_close(fk.positions, want.positions, atol=1e-9, rtol=0)


def test_proportion_words_name_the_largest_differences():
    scales = {"pelvis": 1.0, "thigh_l": 0.93, "thigh_r": 0.93, "shin_l": 1.05}
    scales |= {"shin_r": 1.05, "head": 1.01, "upper_arm_l": 1.11, "upper_arm_r": 1.09}
    assert (
        proportion_words(scales) == "upper arms 10 % longer, thighs 7 % shorter, shins 5 % longer"
    )
    assert proportion_words(scales, most=1) == "upper arms 10 % longer"
    assert proportion_words({"pelvis": 1.01}) == ""
    assert proportion_words({"foot_l": 1.17, "foot_r": 1.17}) == "feet 17 % longer"


def test_student_bvh_needs_the_reference_file(reference):
    reg = make_registration(reference, num_frames=3)
    elsewhere = dataclasses.replace(reference, name="no/such/walk.bvh")
    with pytest.raises(RegistrationError, match=r"no/such/walk\.bvh"):
        student_bvh(reg, elsewhere, 30.0)


def test_student_bvh_unit_estimate_follows_the_scale(reference):
    """Read back without a declared unit, a G = 1 file gets the reference's unit; a G != 1
    file an estimate scaled by 1/G (the rest leg is G times longer), as documented."""
    same = student_bvh(make_registration(reference, num_frames=3), reference, 30.0)
    assert Skeleton.from_bvh(same).metres_per_unit == reference.skeleton.metres_per_unit
    big = student_bvh(make_registration(reference, num_frames=3, scale=1.2), reference, 30.0)
    estimated = Skeleton.from_bvh(big).metres_per_unit
    assert estimated == pytest.approx(reference.skeleton.metres_per_unit / 1.2)


def test_bvh_from_rotations_mixed_orders_units_and_offsets(tmp_path):
    """A hand-made hierarchy in centimetres with a root offset, three channel orders,
    position channels on a non-root joint and a joint without channels."""
    hierarchy = BVH(
        path=tmp_path / "arm.bvh",
        names=["base", "shoulder", "elbow", "tip"],
        parents=np.array([-1, 0, 1, 2]),
        offsets=np.array([[1.0, 2.0, 3.0], [0, 10, 0], [0, 0, 25], [20, 0, 0]]),
        channels=[
            ["Xposition", "Yposition", "Zposition", "Yrotation", "Xrotation", "Zrotation"],
            ["Xrotation", "Zrotation", "Yrotation"],
            ["Zrotation", "Xrotation", "Yrotation", "Xposition", "Yposition", "Zposition"],
            [],
        ],
        end_sites={3: np.array([5.0, 0.0, 0.0])},
        frame_time=1 / 120,
        motion=np.zeros((1, 15)),
    )
    g = torch.Generator().manual_seed(2)
    t = 30
    rotations = random_rotations(t * 4, g).reshape(t, 4, 3, 3)
    rotations[:, 3] = torch.eye(3, dtype=F64)
    lock = torch.tensor([0.3, math.pi / 2, -1.0], dtype=F64)  # shoulder (XZY) locked
    rotations[0, 1] = euler_to_matrix(lock, "XZY")
    root_position = torch.randn(t, 3, generator=g, dtype=F64)
    bvh = bvh_from_rotations(hierarchy, 0.01, rotations, root_position, 60.0, scale=0.8)
    back = read_bvh(write_bvh(bvh, tmp_path / "student.bvh"))
    skel = Skeleton.from_bvh(back, metres_per_unit=0.01)
    assert skel.rotation_orders == ["YXZ", "XZY", "ZXY", ""]
    rot, root = local_rotations(skel, torch.from_numpy(back.motion), back.channels)
    torch.testing.assert_close(rot, rotations, atol=1e-12, rtol=0)
    torch.testing.assert_close(root + skel.offsets[0], root_position, atol=1e-12, rtol=0)
    np.testing.assert_allclose(back.offsets, hierarchy.offsets * 0.8)
    np.testing.assert_allclose(back.motion[:, 12:15], np.tile([0.0, 0.0, 20.0], (t, 1)))
    np.testing.assert_allclose(back.end_sites[3], [4.0, 0.0, 0.0])
    assert back.frame_time == pytest.approx(1 / 60)

    rotations[2, 3] = rodrigues([0.0, 0.1, 0.0])
    with pytest.raises(RegistrationError, match="'tip' has no rotation channels"):
        bvh_from_rotations(hierarchy, 0.01, rotations, root_position, 60.0)


# --------------------------------------------------------------------------- result, summary


def test_save_and_load_registration(tmp_path, reference):
    reg = make_registration(reference, num_frames=7, scale=1.07)
    reg.T_translation = reg.T_translation.float()  # mixed dtypes survive
    path = save_registration(reg, tmp_path / "result")
    assert path.name == "result.npz"
    back = load_registration(path)
    for name in ("C", "T_rotation", "T_translation", "A", "rotations", "fit", "C_stage1"):
        want, got = getattr(reg, name), getattr(back, name)
        assert got.dtype == want.dtype, name
        assert torch.equal(got, want), name
    assert back.G == 1.07 and isinstance(back.G, float)
    assert back.G_measured is True
    reg.G_measured = False
    assert load_registration(save_registration(reg, tmp_path / "unmeasured")).G_measured is False
    assert back.timings == reg.timings and back.notes == reg.notes
    assert back.proportions is None
    parts = torch.linspace(0.9, 1.1, reference.spec.num_parts, dtype=F64)
    reg.proportions = Proportions.of(reference, parts)
    back = load_registration(save_registration(reg, tmp_path / "proportions")).proportions
    assert back.part_names == reg.proportions.part_names and back.measured
    assert torch.equal(back.joint_scales(), reg.proportions.joint_scales())

    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(RegistrationError, match="not a saved registration"):
        load_registration(tmp_path / "other.npz")


def test_summary_speed_offset_and_json(reference):
    """C = 5 + 3 t' at 30 Hz against the 120 Hz walk: 0.75 reference seconds per video
    second, starting 5 frames in."""
    t = 40
    base = make_registration(reference, num_frames=t)
    reg = make_registration(reference, num_frames=t)
    reg.C = 5 + 3 * torch.arange(t)
    bend = flex_articulation(reference, reg.C, "LeftLeg", -12.0)  # the knee flexes 12 more
    reg.rotations = reference.rotations[reg.C] @ bend
    reg.fit = base.fit.double().clamp_min(TRUSTED_FIT)  # every frame trusted but frame 3
    reg.fit[3] = math.nan
    angles = joint_angles(reg, reference, 30.0)
    settings = {"seed": 0, "stage1": {"particles": 64}, "scale": None, "weight": math.inf}
    summary = summarise(
        reg, reference, angles, 30.0, settings, findings=FindingSettings(method_error_deg=0.0)
    )
    rate = reference.frame_rate  # 1 / 0.0083333 s
    assert summary.speed_ratio == pytest.approx(3 * 30.0 / rate, rel=1e-12)
    assert summary.reference_start_s == pytest.approx(5 / rate, rel=1e-12)
    assert summary.video_frames == list(range(t)) and summary.video_start_s == 0.0
    assert summary.c_frames == reg.C.tolist()
    assert summary.num_video_frames == t and summary.video_rate_hz == 30.0
    assert summary.reference == str(WALK) and summary.reference_rate_hz == rate

    record = json.loads(summary.to_json())
    finite = [x for i, x in enumerate(reg.fit.tolist()) if i != 3]
    assert record["silhouette_iou_mean"] == pytest.approx(sum(finite) / len(finite))
    assert record["fit"][3] is None and len(record["fit"]) == t
    assert record["G"] == 1.0 and record["timings"] == {"stage0": 0.5, "stage1": 2.25}
    assert record["notes"] == {"G": "given"}
    assert record["settings"] == {
        "seed": 0,
        "stage1": {"particles": 64},
        "scale": None,
        "weight": None,
    }
    assert record["c_stage1_frames"] == reg.C_stage1.tolist()
    assert record["per_joint_mean_abs_deg"] == pytest.approx(per_joint_mean_abs_deg(angles))
    # the largest differences read the trusted frames (fit >= TRUSTED_FIT), smoothed
    trusted = trusted_angles(angles, reg.fit >= TRUSTED_FIT)
    assert torch.isnan(trusted.difference_deg[3]).all()  # fit NaN: not trusted
    found = sorted(largest_differences(trusted, 3), key=lambda d: -abs(d.mean_difference_deg))
    assert record["largest_differences"] == [
        _jsonable({**d.to_dict(), "stated": True, "why": ""}) for d in found
    ]
    assert record["largest_differences"][0]["text"] == (
        "Left knee flexes 12 degrees more than the reference between 0.13 s and 1.30 s"
    )
    for key in ("reference", "reference_rate_hz", "video_rate_hz", "speed_ratio"):
        assert key in record
    assert record["motions_match"] is True and record["warnings"] == []

    # another movement: the same differences kept, none stated, the reasons first
    reg.warnings = ["video frames 2-3 (...): carried over"]
    other = MovementCheck(False, ["the reference travels 2.0 m ... the student 0.1 m"])
    record = json.loads(summarise(reg, reference, angles, 30.0, {}, movement=other).to_json())
    assert record["motions_match"] is False
    assert record["warnings"] == [*other.reasons, *reg.warnings]
    assert record["movement"]["reasons"] == other.reasons
    # each sentence's ± now carries the method's calibrated error of its angle
    calibrated = [
        dataclasses.replace(d, method_error_deg=FindingSettings().method_error(d.coordinate, 1))
        for d in found
    ]
    assert [d["text"] for d in record["largest_differences"]] == [d.text for d in calibrated]
    assert all(
        d["stated"] is False and d["why"] == "the student does not perform the reference's movement"
        for d in record["largest_differences"]
    )
    # the same movement with a held end: its sentence after the reasons (none), before the rest
    held = MovementCheck(True, [], held_end=4, warnings=["the last 4 video frames ..."])
    record = json.loads(summarise(reg, reference, angles, 30.0, {}, movement=held).to_json())
    assert record["motions_match"] is True
    assert record["warnings"] == [*held.warnings, *reg.warnings]
    assert record["movement"]["held_end"] == 4


def test_trusted_angles_drop_untrusted_frames_and_one_frame_spikes():
    """A one-frame spike of 40 degrees is jitter, not a difference: the 0.2 s running median
    (5 frames at 25 Hz) removes it, keeps a 10-frame plateau of 15 degrees, and untrusted
    frames become NaN whatever their neighbours."""
    t = 40
    diff = torch.zeros(t, 1, dtype=F64)
    diff[5] = 40.0
    diff[20:30] = 15.0
    zeros = torch.zeros_like(diff)
    angles = JointAngles(["LeftLeg"], torch.arange(t, dtype=F64) / 25, zeros, diff, diff, zeros)
    trusted = torch.ones(t, dtype=torch.bool)
    trusted[35:] = False
    out = trusted_angles(angles, trusted, smooth_s=0.2)
    d = out.difference_deg[:, 0]
    assert d[5] == 0.0 and torch.all(d[22:28] == 15.0)
    assert torch.isnan(d[35:]).all() and torch.isfinite(d[:35]).all()
    (found,) = largest_differences(out, 1)
    assert (found.start_s, found.end_s) == (20 / 25, 29 / 25)


def test_angle_uncertainty_adds_the_two_segments_part_spreads_in_quadrature(reference):
    """The knee's uncertainty is that of the thigh and the shin parts added in quadrature,
    the lower back's that of the pelvis and the torso (Spine1 moves with the torso part,
    framed by Spine); without spreads there is none, and a spread of another shape is an
    error naming both."""
    reg = make_registration(reference, num_frames=6)
    assert joint_angles(reg, reference, 30.0).uncertainty_deg is None
    spec = reference.spec
    part = {reference.skeleton.names[int(j)]: p for p, j in enumerate(spec.frame_joints)}
    spread = torch.arange(1.0, 1.0 + spec.num_parts)[None].repeat(6, 1)
    reg.part_spread_deg = spread
    angles = joint_angles(reg, reference, 30.0)
    knee = angles.uncertainty_deg[:, angles.coordinates.index("knee_angle_l")]
    thigh, shin = spread[0, part["LeftUpLeg"]], spread[0, part["LeftLeg"]]
    torch.testing.assert_close(knee, torch.full((6,), float(math.hypot(thigh, shin)), dtype=F64))
    back = angles.uncertainty_deg[0, angles.coordinates.index("lumbar_extension")]
    pelvis, torso = spread[0, part["Hips"]], spread[0, part["Spine"]]
    assert float(back) == pytest.approx(math.hypot(pelvis, torso))
    reg.part_spread_deg = spread[:, :3]
    with pytest.raises(RegistrationError, match=r"part_spread_deg must be \(6, 15\); got \(6, 3\)"):
        joint_angles(reg, reference, 30.0)


def test_a_pelvis_framed_above_the_root_still_gives_the_lumbar_uncertainty(reference):
    """On CMU's jumps (02_04, 01_01) the lower back's rotation fits the pelvis's landmarks
    best, so the pelvis part is framed by LowerBack, not by the root: the root then turns
    with the part whose chain holds it (the pelvis), and the lumbar angles' uncertainty is
    the pelvis's and the torso's spreads as before -- where it raised "no body part moves
    joint 0" after the whole registration."""
    names = reference.skeleton.names
    frames = reference.spec.frame_joints.clone()
    pelvis = int((frames == names.index("Hips")).nonzero())
    frames[pelvis] = names.index("LowerBack")
    lifted = dataclasses.replace(
        reference, spec=dataclasses.replace(reference.spec, frame_joints=frames)
    )
    reg = make_registration(lifted, num_frames=4)
    spread = torch.arange(1.0, 1.0 + reference.spec.num_parts)[None].repeat(4, 1)
    reg.part_spread_deg = spread
    angles = joint_angles(reg, lifted, 30.0)
    torso = int((frames == names.index("Spine")).nonzero())
    back = angles.uncertainty_deg[:, angles.coordinates.index("lumbar_extension")]
    expected = math.hypot(spread[0, pelvis], spread[0, torso])
    torch.testing.assert_close(back, torch.full((4,), expected, dtype=F64))


def test_a_finding_is_stated_only_with_enough_frames_and_an_interval_clear_of_zero():
    """Each rule alone withholds a finding and says why; the sentence carries the
    uncertainty when there is one."""
    rules = FindingSettings(
        interval_z=2.0, min_trusted_s=0.2, method_error_deg=0.0, max_interval_deg=None
    )
    sure = JointDifference("knee_angle_l", -12.0, 1.0, 1.5, 6.0, uncertainty_deg=3.0, frames=13)
    assert rules.why_not(sure, 25.0) == ""
    assert sure.text == (
        "Left knee flexes 12 ± 3 degrees less than the reference between 1.00 s and 1.50 s"
    )
    vague = dataclasses.replace(sure, uncertainty_deg=7.0)  # -12 +- 14 holds 0
    assert rules.why_not(vague, 25.0) == (
        "its interval (-12 ± 14 degrees) holds 0: the inference cannot tell it from no difference"
    )
    short = dataclasses.replace(sure, frames=4)  # 0.2 s at 25 Hz: 5 frames
    assert rules.why_not(short, 25.0).startswith("only 4 trusted frame(s) show it; at least 5")
    unmeasured = dataclasses.replace(sure, uncertainty_deg=math.nan)
    assert rules.why_not(unmeasured, 25.0) == "" and "±" not in unmeasured.text
    # the method's own error joins the inference's in quadrature: -12 +- 2 hypot(3, 12)
    careful = FindingSettings(
        interval_z=2.0, min_trusted_s=0.2, method_error_deg=12.0, max_interval_deg=None
    )
    assert careful.why_not(sure, 25.0) == (
        "its interval (-12 ± 25 degrees; the inference's ± 3 and the method's error of 12 "
        "degrees) holds 0: the inference cannot tell it from no difference"
    )
    clear = dataclasses.replace(sure, mean_difference_deg=-30.0)
    assert careful.why_not(clear, 25.0) == ""
    assert careful.why_not(dataclasses.replace(unmeasured, mean_difference_deg=-20.0), 25) != ""
    # a bound on the interval's width: -12 +- 6 clears 0 but is wider than +- 5
    assert dataclasses.replace(rules, max_interval_deg=5.0).why_not(sure, 25.0) == (
        "its interval (-12 ± 6 degrees) is wider than ± 5: the method cannot place this "
        "difference finely enough"
    )
    assert dataclasses.replace(rules, max_interval_deg=6.5).why_not(sure, 25.0) == ""
    assert "its own error on this angle: 12 degrees" in dataclasses.replace(
        careful, max_interval_deg=5.0
    ).why_not(clear, 25.0)
    with pytest.raises(ValueError, match=r"^FindingSettings: interval_z must be >= 0; got -1.0"):
        FindingSettings(interval_z=-1.0)
    with pytest.raises(ValueError, match=r"method_error_deg must be a finite number; got nan"):
        FindingSettings(method_error_deg=math.nan)


def test_summary_withholds_the_findings_the_inference_cannot_tell_from_zero(reference):
    """The knee flexes 12 degrees more; with part spreads of 1 degree it is stated with its
    interval, with spreads of 10 degrees (14 on the knee) it is kept but not stated."""
    t = 40
    reg = make_registration(reference, num_frames=t)
    reg.C = 5 + 3 * torch.arange(t)
    bend = flex_articulation(reference, reg.C, "LeftLeg", -12.0)
    reg.rotations = reference.rotations[reg.C] @ bend
    reg.fit = torch.ones(t)
    for spread, stated in ((1.0, True), (10.0, False)):
        reg.part_spread_deg = torch.full((t, reference.spec.num_parts), spread)
        angles = joint_angles(reg, reference, 30.0)
        spread_only = FindingSettings(method_error_deg=0.0, max_interval_deg=None)
        top = summarise(reg, reference, angles, 30.0, {}, findings=spread_only)
        top = top.largest_differences[0]
        assert top["coordinate"] == "knee_angle_l" and top["stated"] is stated
        # the method's error also counts: 12 is not clear of 2 x 12
        careful = FindingSettings(method_error_deg=12.0, max_interval_deg=None)
        flat = summarise(reg, reference, angles, 30.0, {}, findings=careful)
        flat = flat.largest_differences[0]
        assert flat["stated"] is False and "the method's error of 12" in flat["why"]
        assert flat["method_error_deg"] == 12.0 and top["method_error_deg"] == 0.0
        # by default each coordinate's calibrated error, for the cameras that saw it
        for cameras in (1, 2):
            default = summarise(reg, reference, angles, 30.0, {}, cameras=cameras)
            default = default.largest_differences[0]
            expected = shipped_method_error().error_deg("knee_angle_l", cameras)
            assert default["method_error_deg"] == expected
        assert top["uncertainty_deg"] == pytest.approx(math.hypot(spread, spread))
        assert ("holds 0" in top["why"]) is not stated


def test_no_difference_is_stated_where_no_camera_saw_the_whole_body(reference):
    """The knee flexes 12 degrees more and is stated -- unless every camera's silhouettes miss
    parts of the body (their median background holds the person): then each difference is
    kept with that reason, and the summary says the fit was measured against partial
    silhouettes. One such camera of two leaves the findings as they were; another movement's
    reason comes first."""
    t = 40
    reg = make_registration(reference, num_frames=t)
    reg.C = 5 + 3 * torch.arange(t)
    reg.rotations = reference.rotations[reg.C] @ flex_articulation(
        reference, reg.C, "LeftLeg", -12.0
    )
    reg.fit = torch.ones(t)
    angles = joint_angles(reg, reference, 30.0)
    rules = FindingSettings(method_error_deg=0.0)

    def summary(cameras, partial, movement=None):
        return summarise(
            reg, reference, angles, 30.0, {}, findings=rules, cameras=cameras,
            partial_silhouettes=partial, movement=movement,
        )  # fmt: skip

    clear = summary(2, ["cam1.avi"])
    assert clear.whole_body_seen and clear.partial_silhouettes == ["cam1.avi"]
    assert clear.largest_differences[0]["stated"] is True
    assert clear.largest_differences == summary(2, []).largest_differences
    held = summary(2, ["cam1.avi", "cam2.avi"])
    assert not held.whole_body_seen
    assert held.largest_differences[0]["coordinate"] == "knee_angle_l"
    for d in held.largest_differences:
        assert d["stated"] is False
        assert d["why"].startswith("no camera's silhouettes show the whole body")
        assert "cam1.avi, cam2.avi" in d["why"]
    record = json.loads(held.to_json())
    assert record["whole_body_seen"] is False
    assert record["partial_silhouettes"] == ["cam1.avi", "cam2.avi"]
    other = MovementCheck(False, ["the reference travels 2.0 m ... the student 0.1 m"])
    for d in summary(1, ["cam1.avi"], other).largest_differences:
        assert d["why"] == "the student does not perform the reference's movement"
