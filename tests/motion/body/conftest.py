"""A real posture (the bundled CMU walk) as body parts, and a camera that sees it."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from motion.body.observation import PartShapes, poses_from_segments
from motion.bodyparts import BodyModel
from motion.bvh import read_bvh
from motion.cameras import CameraRig
from motion.kinematics import Skeleton, forward_kinematics, local_rotations

F64 = torch.float64
WALK = Path(__file__).resolve().parents[3] / "motion" / "data" / "cmu_02_01_walk.bvh"
ROBOT_ARM = WALK.parent / "examples" / "robot_arm"  # .bvh and its one spec file, .yaml


def walk_segments(frames) -> tuple[torch.Tensor, BodyModel]:
    """Part end points ``(T, P, 2, 3)`` metres of the bundled walk at ``frames``, centred."""
    bvh = read_bvh(WALK)
    skeleton = Skeleton.from_bvh(bvh)
    model = BodyModel.from_skeleton(skeleton)
    motion = torch.from_numpy(bvh.motion_frames()[frames]).to(F64)
    rot, root = local_rotations(skeleton, motion, bvh.channels)
    fk = forward_kinematics(skeleton, rot, root)
    seg = model.segments(model.skeleton_points(skeleton, fk)).to(F64)
    centre = seg.reshape(len(frames), -1, 3).mean(1)
    return seg - centre[:, None, None, :], model


def side_camera(width=160, height=120, px_per_m=57.0) -> CameraRig:
    """An orthographic camera looking along -z (world y up), ~100 px for a 1.75 m body."""
    k = torch.tensor([[[px_per_m, 0, width / 2], [0, px_per_m, height / 2], [0, 0, 1]]], dtype=F64)
    r = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64))[None]
    return CameraRig(
        k,
        r,
        torch.tensor([[0.0, 0.0, 5.0]], dtype=F64),
        torch.zeros(1, 5, dtype=F64),
        torch.tensor([[width, height]], dtype=F64),
        ["side"],
        orthographic=True,
    )


@pytest.fixture(scope="module")
def walk_body():
    """Segments (T=3, P, 2, 3), poses (T, P, 7), shapes, model, rig."""
    seg, model = walk_segments([30, 60, 90])
    shapes = PartShapes.from_segments(seg[0], model.radii)
    return seg, poses_from_segments(seg), shapes, model, side_camera()


@pytest.fixture(scope="module")
def arm():
    """The bundled robot arm (``motion/data/examples``): bvh, skeleton, model, motion
    ``(T, channels)`` float64, and its BodySpec from the spec file."""
    from motion.body.spec import BodySpec

    bvh = read_bvh(ROBOT_ARM.with_suffix(".bvh"))
    skeleton = Skeleton.from_bvh(bvh, metres_per_unit=1.0)
    model = BodyModel.from_skeleton(skeleton, ROBOT_ARM.with_suffix(".yaml"))
    motion = torch.from_numpy(bvh.motion_frames()).to(F64)
    rot, root = local_rotations(skeleton, motion, bvh.channels)
    spec = BodySpec.from_motion(skeleton, model, forward_kinematics(skeleton, rot, root))
    return bvh, skeleton, model, motion, spec


@pytest.fixture(scope="module")
def walk():
    """The whole walk: skeleton, body model, forward kinematics ``(T, J, ...)`` and its
    BodySpec."""
    from motion.body.spec import BodySpec

    bvh = read_bvh(WALK)
    skeleton = Skeleton.from_bvh(bvh)
    model = BodyModel.from_skeleton(skeleton)
    rot, root = local_rotations(
        skeleton, torch.from_numpy(bvh.motion_frames()).to(F64), bvh.channels
    )
    fk = forward_kinematics(skeleton, rot, root)
    return skeleton, model, fk, BodySpec.from_motion(skeleton, model, fk)
