"""A real posture (the bundled CMU walk) as body parts, and a camera that sees it."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from motion.body.observation import (
    BodyObservation,
    Edges,
    Intensity,
    Joints2D,
    NonPenetration,
    Observation,
    PartShapes,
    Silhouette,
    poses_from_segments,
)
from motion.bodyparts import BodyModel
from motion.bvh import read_bvh
from motion.cameras import CameraRig
from motion.kinematics import Skeleton, forward_kinematics, local_rotations
from motion.render import project_parts, silhouette
from pgm import SE3

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


def every_cue_scene():
    """A scene for every cue with occlusion on: two walk frames seen from the side, their
    rendered silhouettes, random image, edge distances and 2-D joints, 40 hypotheses per part
    about the true poses. Returns ``(hypotheses (1, 30, 40, 7), rest poses (1, 30, 7),
    score)``, ``score(hypotheses, rest, device)`` giving the factor's ``(1, 30, 40)`` log
    potentials (every input moved to ``device``)."""
    seg, model = walk_segments([30, 60])
    poses = poses_from_segments(seg)  # (2, P, 7)
    shapes = PartShapes.from_segments(seg[0], model.radii)
    rig = side_camera()
    sil = torch.stack(
        [silhouette(project_parts(rig, s, model.radii), 120, 160)[0] for s in seg]
    ).to(F64)
    g = torch.Generator().manual_seed(0)
    image = torch.rand(1, 2, 1, 3, 120, 160, generator=g, dtype=F64)
    dist = 10 * torch.rand(1, 2, 1, 120, 160, generator=g, dtype=F64)
    keypoints = torch.cat(
        [
            100 * torch.rand(1, 2, 1, 30, 2, generator=g, dtype=F64),
            torch.ones(1, 2, 1, 30, 1, dtype=F64),
        ],
        -1,
    )
    x = SE3().perturb(poses.reshape(1, 30, 1, 7).expand(1, 30, 40, 7), (0.03, 0.3), g)
    colours = torch.rand(15, 3, generator=torch.Generator().manual_seed(1), dtype=F64)

    def score(hypotheses, rest, device="cpu"):
        cues = [
            Silhouette(),
            Edges(),
            Intensity(colours.to(device)),
            Joints2D(torch.arange(30).reshape(15, 2).to(device)),
            NonPenetration(torch.eye(15, dtype=torch.bool, device=device)),
        ]
        obs = Observation(
            sil[None, :, None].to(device), dist.to(device), image.to(device), keypoints.to(device)
        )
        factor = BodyObservation(
            PartShapes(shapes.axis.to(device), shapes.radii.to(device)),
            rig.to(device),
            obs,
            cues,
        )
        nodes = torch.arange(30, device=device)
        return factor.log_potential(hypotheses.to(device), nodes, rest.to(device))

    return x, poses.reshape(1, 30, 7), score
