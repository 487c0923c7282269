"""A new articulated object is a spec file: the robot arm of motion/data/examples.

``robot_arm.yaml`` names the arm's five parts (column, upper arm, forearm, two fingers), the
skeleton joints of ``robot_arm.bvh`` their landmarks sit on, and its joint limits; nothing
else is written for it. From these the body spec, the body graph with limited connections
and the occlusion-aware observation are built as for the human body, and particle BP
refines a perturbed start against two rendered views.
"""

from __future__ import annotations

import math

import pytest
import torch

from motion.body.graph import Connections, body_graph
from motion.body.observation import BodyObservation, Edges, Observation, PartShapes, Silhouette
from motion.body.solve import PostureSettings, solve_posture
from motion.body.spec import part_tree
from motion.bodyparts import DEFAULT_PARTS, BodyModel, BodyPartMappingError, read_parts
from motion.cameras import CameraRig
from motion.features import distance_to_edges, edges
from motion.kinematics import forward_kinematics, local_rotations
from motion.render import project_parts, silhouette
from pgm import Geometric
from tests.motion.body.conftest import F64, ROBOT_ARM

ARM = ROBOT_ARM
H, W, PX_PER_M = 120, 160, 80.0  # the arm's 1.2 m reach ~100 px; a finger 10 x 4 px


def _poses(arm, rows):
    bvh, skeleton, model, _, spec = arm
    rot, root = local_rotations(skeleton, rows, bvh.channels)
    return spec.poses(model, skeleton, forward_kinematics(skeleton, rot, root))


def test_the_spec_file_gives_parts_tree_frames_and_limits(arm):
    _, skeleton, model, motion, spec = arm
    assert model.parts_path == ARM.with_suffix(".yaml")
    assert spec.part_names == ["column", "upper_arm", "forearm", "finger_l", "finger_r"]
    assert spec.parents.tolist() == [-1, 0, 1, 2, 2]
    assert spec.rigidity.max() < 1e-9  # every part is one rigid bone over the motion
    assert [skeleton.names[j] for j in spec.frame_joints] == [
        "Base",
        "Shoulder",
        "Elbow",
        "FingerL",
        "FingerR",
    ]
    torch.testing.assert_close(spec.offsets[1], torch.tensor([0.0, 0.3, 0.0], dtype=F64))
    limits = spec.limits  # from the file's own `limits:` entry
    assert limits.exact.all() and limits.joints == [
        ["Shoulder"],
        ["Elbow"],
        ["FingerL"],
        ["FingerR"],
    ]
    torch.testing.assert_close(limits.upper[1], torch.tensor([0, 0, math.radians(145)], dtype=F64))
    assert limits.excess(spec, _poses(arm, motion)).max() < 1e-9
    # an explicit parts= is the same model; the human default stays the default
    again = BodyModel.from_skeleton(
        skeleton, ARM.with_suffix(".yaml"), parts=ARM.with_suffix(".yaml")
    )
    assert again.part_names == model.part_names and torch.equal(part_tree(again), spec.parents)
    assert BodyModel.from_keypoints().parts_path == DEFAULT_PARTS


def test_a_bad_parts_file_is_reported(tmp_path):
    bad = tmp_path / "parts.yaml"
    bad.write_text("parts:\n  link: {from: a, to: b, radii: [0.1]}\n")
    with pytest.raises(
        BodyPartMappingError, match="part 'link' needs 'from' and 'to' roles and two radii"
    ):
        read_parts(bad)
    bad.write_text("roles: {a: A}\n")
    with pytest.raises(BodyPartMappingError, match="expected a 'parts' mapping"):
        read_parts(bad)


def _rig() -> CameraRig:
    """Two orthographic views at right angles (front: along -z; side: along -x), world y up."""
    ks, rs = [], []
    for forward in ([0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]):
        fwd = torch.tensor(forward, dtype=F64)
        right = torch.linalg.cross(fwd, torch.tensor([0.0, 1.0, 0.0], dtype=F64))
        rs.append(torch.stack([right, torch.linalg.cross(fwd, right), fwd]))
        ks.append(torch.tensor([[PX_PER_M, 0, W / 2], [0, PX_PER_M, H / 2], [0, 0, 1]], dtype=F64))
    return CameraRig(
        torch.stack(ks),
        torch.stack(rs),
        torch.tensor([[0.0, 0.0, 5.0]] * 2, dtype=F64),
        torch.zeros(2, 5, dtype=F64),
        torch.tensor([[W, H]] * 2, dtype=F64),
        ["front", "side"],
        orthographic=True,
    )


def test_particle_bp_refines_the_arm_from_two_views(arm):
    """Truth: frame 6 of the motion. Start: +-20 degrees of uniform noise on every rotation
    channel of the shoulder, elbow and fingers (also the ones the limits hold at 0). Two
    rendered views (silhouette and the distance to its edges); 60 particles, 2 x 8
    iterations. The mean landmark error must fall below half the start's and below 4.5 cm
    (3.6 px at 80 px/m; a finger is 4 px wide): measured 7.6 -> 1.3 cm here, 0.9-3.9 cm
    (at most 0.37 of the start) over three noise draws x six seeds."""
    bvh, _, _, motion, spec = arm
    truth = _poses(arm, motion[6:7])
    centre = spec.landmarks(truth).reshape(-1, 3).mean(0)
    truth[..., :3] -= centre
    cols = []
    col = 0
    for name, channels in zip(bvh.names, bvh.channels, strict=True):
        if name in ("Shoulder", "Elbow", "FingerL", "FingerR"):
            cols += [col + i for i, c in enumerate(channels) if c.endswith("rotation")]
        col += len(channels)
    g = torch.Generator().manual_seed(0)
    rows = motion[6:7].clone()
    rows[0, cols] += 20 * (2 * torch.rand(len(cols), generator=g, dtype=F64) - 1)
    start = _poses(arm, rows)
    start[..., :3] -= centre

    rig = _rig()
    seg = spec.landmarks(truth.float())
    sil = silhouette(project_parts(rig, seg, spec.shapes.radii.float()), H, W).float()
    dist = distance_to_edges(edges(sil.reshape(-1, 1, H, W))).reshape(sil.shape)
    dist = torch.where(torch.isfinite(dist), dist, torch.full_like(dist, 1e3))
    shapes = PartShapes(spec.shapes.axis.float(), spec.shapes.radii.float())
    unary = BodyObservation(
        shapes, rig, Observation(sil[None], dist[None]), cues=[Silhouette(1.0, 1.0), Edges(0.2)]
    )
    p, k = spec.num_parts, 60
    graph = body_graph(
        spec,
        1,
        [(torch.arange(p), unary)],
        Connections(
            pos_std=0.02, rot_std=0.5, schedule=Geometric(1.0, 0.25, 6), limits=spec.limits
        ),
    )
    settings = PostureSettings(particles=k, iterations=8, restarts=2, kernel_end=0.03)
    poses = solve_posture(graph, start, settings, torch.Generator().manual_seed(1)).poses
    before = (spec.landmarks(start.float()) - seg).norm(dim=-1).mean()
    after = (spec.landmarks(poses) - seg).norm(dim=-1).mean()
    assert before > 0.05, before  # the start is well off
    assert after < 0.5 * before and after < 0.045, (before, after)
