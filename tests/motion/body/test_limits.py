"""Joint-angle limits on the body graph's kinematic edges, from the bundled CMU limits.

Independent answers: a joint's own Euler box applied to its BVH angles
(:func:`motion.limits.limit_violation`) for the edges that one joint drives; postures built
by forward kinematics from joint angles drawn inside the joints' boxes for the composite
(several-joint) edges; and particle BP's result against the same limits.
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from motion.body.graph import Connections, PosturePrior, body_graph
from motion.body.limits import edge_limits
from motion.body.solve import PostureSettings, solve_posture
from motion.body.spec import BodySpec
from motion.bodyparts import BodyModel
from motion.bvh import read_bvh
from motion.kinematics import Skeleton, forward_kinematics, local_rotations
from motion.limits import limit_violation, limits_tensor, load_limits
from pgm import Geometric, LimitedConnection, RigidConnection
from tests.motion.body.conftest import F64, ROBOT_ARM, WALK

ARM = ROBOT_ARM


@pytest.fixture(scope="module")
def walk():
    bvh = read_bvh(WALK)
    skeleton = Skeleton.from_bvh(bvh)
    model = BodyModel.from_skeleton(skeleton)
    motion = torch.from_numpy(bvh.motion_frames()).to(F64)
    rot, root = local_rotations(skeleton, motion, bvh.channels)
    spec = BodySpec.from_motion(
        skeleton, model, forward_kinematics(skeleton, rot, root), limits="cmu_cgspeed"
    )
    return bvh, skeleton, model, motion, spec


def _columns(bvh, joint: str) -> list[int]:
    col = 0
    for name, channels in zip(bvh.names, bvh.channels, strict=True):
        if name == joint:
            return [col + i for i, c in enumerate(channels) if c.endswith("rotation")]
        col += len(channels)
    raise KeyError(joint)


def _poses(bvh, skeleton, model, spec, rows):
    rot, root = local_rotations(skeleton, rows, bvh.channels)
    return spec.poses(model, skeleton, forward_kinematics(skeleton, rot, root))


def _edge(spec, child: str) -> int:
    return spec.edges[:, 1].tolist().index(spec.part_names.index(child))


def test_the_walk_lies_inside_its_limits_and_single_joints_keep_their_box(walk):
    """Every frame of the walk (one of the recordings the limits were estimated from) is
    inside every edge's limits; the edges one joint drives carry that joint's box exactly,
    the spine, neck, shoulders and wrists a composite."""
    bvh, skeleton, model, motion, spec = walk
    limits = spec.limits
    assert limits.num_edges == 14 and limits.orders == ["ZYX"] * 14
    assert limits.excess(spec, _poses(bvh, skeleton, model, spec, motion)).max() < 1e-9
    joints = limits_tensor(skeleton, load_limits("cmu_cgspeed"))
    for child, joint in (
        ("shin_l", "LeftLeg"),
        ("thigh_r", "RightUpLeg"),
        ("forearm_l", "LeftForeArm"),
    ):
        e = _edge(spec, child)
        assert limits.exact[e] and limits.joints[e] == [joint]
        box = joints[skeleton.index(joint)]
        torch.testing.assert_close(limits.lower[e], box[:, 0])
        torch.testing.assert_close(limits.upper[e], box[:, 1])
    assert limits.joints[_edge(spec, "torso")] == ["LowerBack", "Spine"]
    assert not limits.exact[_edge(spec, "torso")]


def test_excess_of_a_single_joint_edge_is_the_joints_own_violation(walk):
    """Random knee angles within 40 degrees of the box (so the stored triple is the closer
    one): the knee edge's excess from part poses equals limit_violation of the angles."""
    bvh, skeleton, model, motion, spec = walk
    cols = _columns(bvh, "LeftLeg")
    box = limits_tensor(skeleton, load_limits("cmu_cgspeed"))[skeleton.index("LeftLeg")]
    g = torch.Generator().manual_seed(0)
    rows = motion[torch.randint(0, len(motion), (200,), generator=g)].clone()
    lo, hi = box[:, 0].rad2deg() - 40, box[:, 1].rad2deg() + 40
    rows[:, cols] = lo + (hi - lo) * torch.rand(200, 3, generator=g, dtype=F64)
    rows[:, cols[1]] = rows[:, cols[1]].clamp(-85, 85)  # the middle angle's canonical range
    got = spec.limits.excess(spec, _poses(bvh, skeleton, model, spec, rows))[
        :, _edge(spec, "shin_l")
    ]
    want = limit_violation(torch.deg2rad(rows[:, cols])[:, None], box[None])[:, 0]
    torch.testing.assert_close(got, want, atol=1e-7, rtol=0)
    assert 0.3 < (want.amax(-1) > 0).double().mean() < 0.95


def test_composite_boxes_contain_every_posture_the_joints_allow(walk):
    """Postures with every joint's angles uniform in its own box (free channels anywhere):
    no edge -- composite or not -- sees them outside."""
    bvh, skeleton, model, motion, spec = walk
    joints = limits_tensor(skeleton, load_limits("cmu_cgspeed"))
    g = torch.Generator().manual_seed(1)
    rows = motion[torch.randint(0, len(motion), (300,), generator=g)].clone()
    for j, name in enumerate(skeleton.names[1:], start=1):
        cols = _columns(bvh, name)
        if not cols:
            continue
        lo = torch.where(torch.isfinite(joints[j, :, 0]), joints[j, :, 0], -math.pi).rad2deg()
        hi = torch.where(torch.isfinite(joints[j, :, 1]), joints[j, :, 1], math.pi).rad2deg()
        rows[:, cols] = lo + (hi - lo) * torch.rand(300, 3, generator=g, dtype=F64)
    excess = spec.limits.excess(spec, _poses(bvh, skeleton, model, spec, rows))
    assert excess.max() < 1e-6, excess.amax((0, 2))


def test_a_joint_on_the_parents_side_gives_the_inverse_box(arm):
    """The robot arm with the forearm's frame moved to the right finger: the edge
    forearm -> finger_l then runs up through FingerR and down through FingerL (held fixed),
    so its relative rotation is FingerR's local rotation inverted -- reversed order,
    negated bounds -- and its excess is FingerR's own violation."""
    bvh, skeleton, model, motion, spec = arm
    frames = spec.frame_joints.clone()
    frames[spec.part_names.index("forearm")] = skeleton.index("FingerR")
    moved = dataclasses.replace(spec, frame_joints=frames)
    table = {
        **load_limits(ARM.with_suffix(".yaml")),
        "FingerL": {"Z": [0, 0], "Y": [0, 0], "X": [0, 0]},
    }
    limits = edge_limits(moved, skeleton, table)
    e = _edge(moved, "finger_l")
    assert limits.exact[e] and limits.joints[e] == ["FingerR"] and limits.orders[e] == "XYZ"
    torch.testing.assert_close(limits.lower[e], torch.tensor([0.0, 0.0, -math.pi / 4], dtype=F64))
    torch.testing.assert_close(limits.upper[e], torch.zeros(3, dtype=F64))
    rows = motion[:1].repeat(50, 1)
    rows[:, _columns(bvh, "FingerL")] = 0.0
    z = torch.linspace(-30, 80, 50, dtype=F64)
    rows[:, _columns(bvh, "FingerR")] = torch.stack([z, 0 * z, 0 * z], -1)
    got = limits.excess(moved, _poses(bvh, skeleton, model, moved, rows))[:, e]
    want = torch.deg2rad((-z).clamp_min(0) + (z - 45).clamp_min(0))
    torch.testing.assert_close(got.amax(-1), want, atol=1e-7, rtol=0)


def test_connections_use_the_limits_only_when_given(walk):
    spec = walk[4]
    assert type(Connections().factor(spec)) is RigidConnection  # the default is unchanged
    factor = Connections(limits=spec.limits, limit_softness=0.05).factor(spec, torch.float64)
    assert isinstance(factor, LimitedConnection) and factor.limits.softness == 0.05
    assert factor.num_edges == 14
    short = dataclasses.replace(spec.limits, lower=spec.limits.lower[:3])
    with pytest.raises(ValueError, match="limits are for 3 joints; the spec has 14"):
        Connections(limits=short).factor(spec)


@pytest.mark.parametrize("limited", [True, False], ids=["limits", "no-limits"])
def test_particle_bp_brings_a_backwards_knee_inside_the_limits(walk, limited):
    """The walk at frame 236 with the left knee bent backwards (-60 degrees, 45 outside its
    box): a posture prior holds every other part there (2 cm, 0.1 rad) and the shin and foot
    only loosely (30 cm, 1 rad), so nothing but the limits argues with the bent knee. With
    limits particle BP ends inside them to within 8.6 degrees (1.5 softness: a penalty
    below 1.2 nats; measured <= 6 over ten seeds); without, the knee stays > 25 outside
    (measured 35-64)."""
    bvh, skeleton, model, motion, spec = walk
    rows = motion[236:237].clone()
    rows[0, _columns(bvh, "LeftLeg")[2]] = -60.0
    start = _poses(bvh, skeleton, model, spec, rows).float()
    start[..., :3] -= start[0, :, :3].mean(0)
    knee = _edge(spec, "shin_l")
    assert spec.limits.excess(spec, start.double())[0, knee, 2] == pytest.approx(math.radians(45))
    p = spec.num_parts
    loose = torch.tensor([spec.part_names.index(n) for n in ("shin_l", "foot_l")])
    tight = torch.tensor([i for i in range(p) if i not in loose.tolist()])
    priors = [(tight, PosturePrior(start, 0.02, 0.1)), (loose, PosturePrior(start, 0.3, 1.0))]
    connections = Connections(
        pos_std=0.02,
        rot_std=1.0,
        schedule=Geometric(1.0, 0.25, 10),
        limits=spec.limits if limited else None,
    )
    graph = body_graph(spec, 1, priors, connections)
    settings = PostureSettings(
        particles=60,
        iterations=10,
        restarts=1,
        kernel_scale=(0.02, 0.3),
        kernel_end=0.1,
        proposal_centres=None,
    )
    poses = solve_posture(graph, start, settings, torch.Generator().manual_seed(0)).poses
    excess = spec.limits.excess(spec, poses.double())[0]
    if limited:
        assert excess.max() < 0.15, excess.rad2deg()
    else:
        assert excess[knee].norm() > math.radians(25), excess[knee].rad2deg()
