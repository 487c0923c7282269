"""The body spec from a real motion, and the body graph over frames built from it."""

from __future__ import annotations

import pytest
import torch

from motion.body.graph import Connections, PosturePrior, Temporal, body_graph, relative_rotations
from motion.body.spec import BodySpecError, part_tree
from motion.bvh import read_bvh
from motion.kinematics import local_rotations
from pgm import SE3, TiledFactor, particle_bp
from pgm.rotations import qrotate
from tests.motion.body.conftest import F64, WALK


def test_part_poses_reproduce_the_body_model_within_its_rigidity(walk):
    """Landmarks rebuilt from part poses (proximal landmark + frame, mean axis) equal the
    body model's segments: exact where a part is one bone, within the reported rigidity
    where it is a chain (the walk: pelvis, torso and head, < 0.5 cm)."""
    skeleton, model, fk, spec = walk
    poses = spec.poses(model, skeleton, fk)  # (T, P, 7)
    rebuilt = spec.landmarks(poses)
    truth = model.segments(model.skeleton_points(skeleton, fk))
    err = (rebuilt - truth).norm(dim=-1).mean(0)  # (P, 2) metres
    assert (err[:, 0] < 1e-9).all()  # proximal landmarks are the poses' origins
    assert (err[:, 1] <= 2 * spec.rigidity + 1e-9).all(), (err[:, 1], spec.rigidity)
    assert spec.rigidity.max() < 0.005
    single_bone = [model.part_names.index(n) for n in ("thigh_l", "shin_r", "forearm_l")]
    assert spec.rigidity[single_bone].max() < 1e-9


def test_joints_sit_at_the_spec_offsets(walk):
    skeleton, model, fk, spec = walk
    poses = spec.poses(model, skeleton, fk)
    e = spec.edges
    joint = poses[:, e[:, 0], :3] + qrotate(
        poses[:, e[:, 0], 3:], spec.offsets[e[:, 1]].expand(len(poses), -1, -1)
    )
    gap = (joint - poses[:, e[:, 1], :3]).norm(dim=-1)  # (T, E)
    assert gap.mean() < 0.005 and gap.max() < 0.03


def test_part_tree_is_checked(tmp_path, walk):
    _, model, _, spec = walk
    assert spec.edges.shape == (14, 2)
    order = spec.topological_order().tolist()
    for parent, child in spec.edges.tolist():
        assert order.index(parent) < order.index(child)
    bad = tmp_path / "parts.yaml"
    bad.write_text(
        "parts:\n"
        + "".join(
            f"  {n}: {{parent: {'torso' if n == 'pelvis' else 'pelvis'}}}\n"
            for n in model.part_names
        )
    )
    with pytest.raises(BodySpecError, match="expected exactly one root part; got 0"):
        part_tree(model, bad)
    bad.write_text("parts:\n  pelvis: {parent: null}\n")
    with pytest.raises(BodySpecError, match="part 'torso' has no 'parent' entry"):
        part_tree(model, bad)


def test_body_graph_over_frames_tiles_the_joints_and_links_time(walk):
    spec = walk[3]
    graph = body_graph(spec, 4, temporal=Temporal())
    assert graph.num_nodes == 60
    kinematic, temporal = graph.pairwise
    assert isinstance(kinematic[1], TiledFactor) and kinematic[0].shape == (56, 2)
    assert temporal[0].shape == (45, 2) and (temporal[0][:, 1] - temporal[0][:, 0] == 15).all()
    with pytest.raises(ValueError, match="frames must be an int >= 1"):
        body_graph(spec, 0)


def test_particle_bp_on_the_body_graph_keeps_the_posture_it_is_pulled_to(walk):
    """Two frames, a posture prior at the truth (2 cm, 0.1 rad), connections centred on the
    true relative rotations: particle BP from a start 5 cm / 0.2 rad off lands within a few
    centimetres of the truth at every landmark."""
    skeleton, model, fk, spec = walk
    truth = spec.poses(model, skeleton, fk)[[40, 80]].float()  # (2, P, 7)
    rel = relative_rotations(spec, truth[0])
    graph = body_graph(
        spec,
        2,
        [(torch.arange(30), PosturePrior(truth, 0.02, 0.1))],
        Connections(rel_rot=rel, rot_std=0.3),
    )
    g = torch.Generator().manual_seed(0)
    init = SE3().perturb(truth.reshape(1, 30, 1, 7).expand(1, 30, 60, 7), (0.05, 0.2), g)
    res = particle_bp(graph, init, iterations=6, generator=g, kernel_scale=(0.02, 0.1))
    err = (spec.landmarks(res.mean[0].reshape(2, 15, 7)) - spec.landmarks(truth)).norm(dim=-1)
    start = (spec.landmarks(init[0, :, 0].reshape(2, 15, 7)) - spec.landmarks(truth)).norm(dim=-1)
    assert err.mean() < 0.03 and err.mean() < 0.5 * start.mean(), (err.mean(), start.mean())


def test_posture_fit_round_trips_part_poses(walk):
    """Part poses of a posture -> fit with the true rotations of the joints no part drives:
    the driving joints' local rotations and every landmark come back exactly; with a rest
    reference for the undriven joints the landmarks still land within the model's rigidity
    plus what those joints move (the walk: < 2 cm)."""
    from motion.body.fit import fit_posture

    skeleton, model, fk, spec = walk
    frames = [10, 70, 130]
    sub = type(fk)(fk.positions[frames], fk.rotations[frames])
    poses = spec.poses(model, skeleton, sub)
    bvh = read_bvh(WALK)
    rot, _ = local_rotations(
        skeleton, torch.from_numpy(bvh.motion_frames()[frames]).to(F64), bvh.channels
    )
    fit = fit_posture(spec, skeleton, model, poses, rot)
    driving = spec.frame_joints
    torch.testing.assert_close(fit.rotations[:, driving], rot[:, driving], atol=1e-6, rtol=0)
    truth = model.landmarks(model.skeleton_points(skeleton, sub))
    got = model.landmarks(model.skeleton_points(skeleton, fit.fk))
    torch.testing.assert_close(got, truth, atol=1e-6, rtol=0)
    rest = torch.eye(3, dtype=F64).expand_as(rot)
    loose = fit_posture(spec, skeleton, model, poses, rest)
    err = (model.landmarks(model.skeleton_points(skeleton, loose.fk)) - truth).norm(dim=-1)
    assert err.mean() < 0.02, err.mean()
    with pytest.raises(ValueError, match=r"poses must have shape \(\.\.\., 15, 7\)"):
        fit_posture(spec, skeleton, model, poses[..., :3], rot)
