"""Forward kinematics against an independent per-frame matrix chain (SciPy), invariants,
Euler round trips and gradients."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from motion.bvh import read_bvh
from motion.geometry import RotationOrderError
from motion.kinematics import (
    Skeleton,
    SkeletonError,
    end_site_positions,
    end_site_positions_by_joint,
    euler_to_matrix,
    forward_kinematics,
    local_from_global,
    local_rotations,
    matrix_to_euler,
)
from tests.conftest import SHARED_DATA, requires_shared_data
from tests.motion.test_bvh import BUNDLED, SHARED_FILES

ORDERS = ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"]
F64 = torch.float64


def _walk(frames=slice(1, 40)):
    bvh = read_bvh(BUNDLED)
    skel = Skeleton.from_bvh(bvh)
    motion = torch.from_numpy(bvh.motion[frames])
    return bvh, skel, motion


def _scipy_fk(bvh, skel, row):
    """Plain per-frame chain: SciPy intrinsic Euler matrices, NumPy products, joint by joint."""
    j = skel.num_joints
    glob_r = [None] * j
    glob_p = [None] * j
    col = 0
    for joint, chans in enumerate(bvh.channels):
        vals = dict(zip(chans, row[col : col + len(chans)], strict=True))
        col += len(chans)
        order = "".join(c[0] for c in chans if c.endswith("rotation"))
        local = Rotation.from_euler(
            order, [vals[a + "rotation"] for a in order], degrees=True
        ).as_matrix()
        off = bvh.offsets[joint] * skel.metres_per_unit
        p = bvh.parents[joint]
        if p < 0:
            t = np.array([vals.get(a + "position", 0.0) for a in "XYZ"]) * skel.metres_per_unit
            glob_r[joint], glob_p[joint] = local, t + off
        else:
            glob_r[joint] = glob_r[p] @ local
            glob_p[joint] = glob_p[p] + glob_r[p] @ off
    return np.stack(glob_p)


def test_fk_matches_an_independent_matrix_chain():
    bvh, skel, motion = _walk()
    rot, root = local_rotations(skel, motion, bvh.channels)
    fk = forward_kinematics(skel, rot, root)
    for f in [0, 10, 38]:
        expected = _scipy_fk(bvh, skel, motion[f].numpy())
        np.testing.assert_allclose(fk.positions[f].numpy(), expected, atol=1e-10)


@requires_shared_data()
@pytest.mark.shared_data
@pytest.mark.parametrize(
    "name", ["cmu_lawrennd_mocap/10_01.bvh", "cmu_salsa_scaled/60_10_scaled.bvh"]
)
def test_fk_matches_on_the_zxy_skeletons(name):
    bvh = read_bvh(SHARED_DATA / "bvh" / name)
    skel = Skeleton.from_bvh(bvh)
    motion = torch.from_numpy(bvh.motion[100:103])
    fk = forward_kinematics(skel, *local_rotations(skel, motion, bvh.channels))
    np.testing.assert_allclose(
        fk.positions[1].numpy(), _scipy_fk(bvh, skel, motion[1].numpy()), atol=1e-10
    )


def test_bone_lengths_are_preserved_in_every_pose():
    bvh, skel, motion = _walk()
    fk = forward_kinematics(skel, *local_rotations(skel, motion, bvh.channels))
    child = torch.arange(1, skel.num_joints)
    bones = (fk.positions[:, child] - fk.positions[:, skel.parents[child]]).norm(dim=-1)
    rest = skel.offsets[child].norm(dim=-1)
    torch.testing.assert_close(bones, rest.expand_as(bones))


def test_fk_commutes_with_a_global_rigid_transform():
    bvh, skel, motion = _walk(slice(5, 9))
    rot, root = local_rotations(skel, motion, bvh.channels)
    g = torch.from_numpy(Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix())
    t = torch.tensor([0.5, -0.1, 2.0], dtype=torch.float64)
    moved_rot = rot.clone()
    moved_rot[:, 0] = g @ rot[:, 0]
    # the root sits at root_translation + offset_root: move that point rigidly
    root_point = root + skel.offsets[0]
    moved_root = (g @ root_point.unsqueeze(-1)).squeeze(-1) + t - skel.offsets[0]
    a = forward_kinematics(skel, rot, root)
    b = forward_kinematics(skel, moved_rot, moved_root)
    expected = (g @ a.positions.unsqueeze(-1)).squeeze(-1) + t
    torch.testing.assert_close(b.positions, expected)
    torch.testing.assert_close(b.rotations, g @ a.rotations)


@pytest.mark.parametrize("order", ORDERS)
def test_euler_matches_scipy_and_round_trips(order):
    g = torch.Generator().manual_seed(0)
    angles = (torch.rand(500, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor(
        [2 * math.pi, math.pi, 2 * math.pi]
    )
    m = euler_to_matrix(angles, order)
    expected = Rotation.from_euler(order, angles.numpy()).as_matrix()
    np.testing.assert_allclose(m.numpy(), expected, atol=1e-12)
    back = matrix_to_euler(m, order)
    torch.testing.assert_close(euler_to_matrix(back, order), m)
    torch.testing.assert_close(back, angles)  # middle angle within (-pi/2, pi/2): unique


@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize("middle", [math.pi / 2, -math.pi / 2, math.pi / 2 - 1e-5, 1e-9, 0.0])
def test_euler_round_trip_near_gimbal_lock_and_identity(order, middle):
    angles = torch.tensor([[0.4, middle, -0.7], [0.0, middle, 0.0]], dtype=torch.float64)
    m = euler_to_matrix(angles, order)
    torch.testing.assert_close(
        euler_to_matrix(matrix_to_euler(m, order), order), m, atol=1e-6, rtol=0
    )


def test_fk_gradcheck_float64():
    _bvh, skel, _motion = _walk(slice(3, 4))
    small = Skeleton(skel.names[:6], skel.parents[:6], skel.offsets[:6], skel.rotation_orders[:6])
    angles = torch.randn(2, 6, 3, dtype=torch.float64, requires_grad=True)
    root = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    offsets = small.offsets.clone().requires_grad_(True)

    def fn(a, r, o):
        return forward_kinematics(small, euler_to_matrix(a, "ZYX"), r, o).positions

    assert torch.autograd.gradcheck(fn, (angles, root, offsets))


def test_units_are_estimated_and_explicit():
    bvh = read_bvh(BUNDLED)
    skel = Skeleton.from_bvh(bvh)
    assert 0.045 < skel.metres_per_unit < 0.065  # CMU's ~5.6 cm units
    assert skel.units_note.startswith("estimated")
    declared = Skeleton.from_bvh(bvh, metres_per_unit=0.056)
    assert declared.units_note.startswith("declared")
    torch.testing.assert_close(declared.offsets, torch.from_numpy(bvh.offsets) * 0.056)


@requires_shared_data()
@pytest.mark.shared_data
@pytest.mark.parametrize(
    ("name", "unit"),
    [("cmu_lawrennd_mocap/10_01.bvh", 0.01), ("cmu_salsa_scaled/60_10_scaled.bvh", 1.0)],
)
def test_units_snap_to_centimetres_and_metres(name, unit):
    assert Skeleton.from_bvh(read_bvh(SHARED_DATA / "bvh" / name)).metres_per_unit == unit


def test_skeleton_errors():
    with pytest.raises(SkeletonError, match="parents must come before their children"):
        Skeleton(["a", "b", "c"], torch.tensor([-1, 2, 0]), torch.zeros(3, 3), ["", "", ""])
    with pytest.raises(SkeletonError, match=r"repeated: \['a'\]"):
        Skeleton(["a", "a"], torch.tensor([-1, 0]), torch.zeros(2, 3), ["", ""])
    with pytest.raises(SkeletonError, match="permutation of 'XYZ'"):
        Skeleton(["a", "b"], torch.tensor([-1, 0]), torch.zeros(2, 3), ["", "XXY"])
    # the Euler conversions (motion.geometry, re-exported here) raise their own ValueError
    with pytest.raises(RotationOrderError, match="permutation of 'XYZ'"):
        euler_to_matrix(torch.zeros(3), "XXY")
    _, skel, _ = _walk()
    with pytest.raises(SkeletonError, match=r"rotations must be \(\.\.\., 31, 3, 3\)"):
        forward_kinematics(skel, torch.zeros(2, 30, 3, 3), torch.zeros(2, 3))
    with pytest.raises(KeyError, match="no joint 'Tail'"):
        skel.index("Tail")


def test_global_to_local_round_trip_and_euler_angles():
    bvh, skel, motion = _walk(slice(1, 20))
    rot, root = local_rotations(skel, motion, bvh.channels)
    fk = forward_kinematics(skel, rot, root)
    local = local_from_global(skel, fk.rotations)
    torch.testing.assert_close(local, rot)
    # back to the file's own angles (degrees) for a ZYX joint
    j = skel.index("LeftLeg")
    angles = torch.rad2deg(matrix_to_euler(local[:, j], skel.rotation_orders[j]))
    col = sum(len(c) for c in bvh.channels[:j])
    torch.testing.assert_close(angles, motion[:, col : col + 3])


@requires_shared_data()
@pytest.mark.shared_data
@pytest.mark.parametrize("name", [f for f, *_ in SHARED_FILES])
def test_every_shared_file_animates(name):
    """All frames through FK: finite, bone lengths preserved, a plausible body height."""
    bvh = read_bvh(SHARED_DATA / "bvh" / name)
    skel = Skeleton.from_bvh(bvh)
    fk = forward_kinematics(
        skel, *local_rotations(skel, torch.from_numpy(bvh.motion), bvh.channels)
    )
    assert torch.isfinite(fk.positions).all()
    child = torch.arange(1, skel.num_joints)
    bones = (fk.positions[:, child] - fk.positions[:, skel.parents[child]]).norm(dim=-1)
    torch.testing.assert_close(bones, skel.offsets[child].norm(dim=-1).expand_as(bones))
    span = (fk.positions[..., 1].amax(-1) - fk.positions[..., 1].amin(-1)).median()
    assert 0.9 < span < 2.2, span


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_end_sites_in_both_layouts(dtype):
    """``p_j + G_j (scale o)`` per End Site, in ``end_sites`` order (any dict order) and by
    joint (NaN rows elsewhere); the old names in bodyparts and export are these functions."""
    from motion import bodyparts
    from motion.registration import export

    names = ["root", "a", "b", "c", "d"]
    g = torch.Generator().manual_seed(2)
    ends = {4: torch.randn(3, generator=g, dtype=F64), 2: torch.randn(3, generator=g, dtype=F64)}
    skel = Skeleton(
        names,
        torch.tensor([-1, 0, 1, 0, 3]),
        torch.randn(5, 3, generator=g, dtype=F64),
        ["ZYX"] * 5,
        end_sites=ends,
    )
    rot = euler_to_matrix(torch.randn(6, 5, 3, generator=g, dtype=F64), "ZYX").to(dtype)
    fk = forward_kinematics(skel, rot, torch.randn(6, 3, generator=g, dtype=dtype))
    got = end_site_positions(skel, fk, 1.5)
    assert got.shape == (6, 2, 3) and got.dtype == dtype
    for row, (j, off) in enumerate(ends.items()):
        want = fk.positions[:, j] + (fk.rotations[:, j] @ (off.to(dtype) * 1.5)[:, None])[..., 0]
        torch.testing.assert_close(got[:, row], want)
    by_joint = end_site_positions_by_joint(skel, fk, 1.5)
    assert by_joint.shape == (6, 5, 3)
    torch.testing.assert_close(by_joint[:, [4, 2]], got, atol=0, rtol=0)
    assert by_joint[:, [0, 1, 3]].isnan().all()
    bare = Skeleton(names, skel.parents, skel.offsets, skel.rotation_orders)
    assert end_site_positions(bare, fk).shape == (6, 0, 3)
    assert end_site_positions_by_joint(bare, fk).isnan().all()
    assert bodyparts.end_site_positions is end_site_positions
    assert export.end_site_positions is end_site_positions_by_joint
    assert export.matrix_to_bvh_euler is matrix_to_euler
