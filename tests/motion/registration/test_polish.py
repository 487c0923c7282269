"""The posture polish (motion.registration.polish) against independent answers: the synthetic
renderer's own joints and silhouettes (motion.synth), the capsules' signed distance, and
bilinear interpolation written out by hand."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from motion.body.observation import PartShapes
from motion.bvh import read_bvh, write_bvh
from motion.geometry import rotation_vector_to_matrix
from motion.registration import Reference
from motion.registration.inputs import features_from_sequence
from motion.registration.pipeline import silhouette_iou
from motion.registration.polish import (
    PosturePolishSettings,
    PosturePolishSettingsError,
    _Posture,
    _sample_map,
    capsule_outline,
    part_groups,
    polish_posture,
)
from motion.registration.refine import place_poses
from motion.registration.types import Proportions, scaled_spec
from motion.render import capsule_sdf
from motion.synth import SynthConfig, synthesize

from .conftest import REFERENCE

FRAMES = 8


@dataclasses.dataclass
class Scene:
    reference: Reference
    video: object  # VideoFeatures
    C: torch.Tensor  # (T',) the reference frames shown
    rotations: torch.Tensor  # (T', J, 3, 3) true local rotations (root: T's)
    translation: torch.Tensor  # (T', 3) true root position
    joints: torch.Tensor  # (T', J, 3) the renderer's joints
    height: float


@pytest.fixture(scope="module")
def scene() -> Scene:
    """The reference itself rendered by motion.synth from 2 cameras (no time warp, no
    articulation, a quarter turn about the vertical), its exact 2-D joints, 8 frames."""
    cfg = SynthConfig(fps=12, warp=0.0, yaw_deg=90.0, cameras=2, size=[160, 120], focal_px=200)
    seq = synthesize(REFERENCE, cfg)
    reference = Reference.from_bvh(REFERENCE)
    video = features_from_sequence(seq, keypoints=True, noisy=False, image=False)
    video = video.cut(slice(0, FRAMES))
    shown = torch.from_numpy(seq.arrays["C_shown"]).long()[:FRAMES]
    yaw = torch.from_numpy(seq.arrays["T_yaw_rad"])[:FRAMES]
    turn = rotation_vector_to_matrix(torch.stack([0 * yaw, yaw, 0 * yaw], -1))
    rotations = reference.rotations[shown].clone()
    rotations[:, 0] = turn @ rotations[:, 0]
    joints = torch.from_numpy(seq.arrays["joints3d"])[:FRAMES].double()
    height = float((joints[..., 1].amax(-1) - joints[..., 1].amin(-1)).mean())
    return Scene(reference, video, shown, rotations, joints[:, 0].clone(), joints, height)


def _driven(reference: Reference) -> list[int]:
    return sorted(set(reference.spec.frame_joints.tolist()) - {0})


def _e3d(scene: Scene, rotations, translation) -> float:
    posture = _Posture(scene.reference, 1.0, rotations, _driven(scene.reference))
    joints = posture.world_joints(rotations.double(), translation.double())
    return float((joints - scene.joints).norm(dim=-1).mean() / scene.height)


def _iou(scene: Scene, rotations, translation) -> float:
    ref = scene.reference
    spec = scaled_spec(ref.spec, 1.0)
    shapes = PartShapes(spec.shapes.axis.float(), spec.shapes.radii.float())
    poses = place_poses(rotations[:, 0], translation, ref.posture_poses(rotations)).float()
    sil = scene.video.observation.silhouette[0]
    return float(silhouette_iou(shapes, scene.video.cameras, sil, poses).mean())


def _without_joints(scene: Scene):
    """The scene's video with its 2-D joints taken out (the silhouettes alone)."""
    obs = dataclasses.replace(scene.video.observation, keypoints=None)
    return dataclasses.replace(scene.video, observation=obs, keypoint_joints=None)


def _polish_from_truth(scene: Scene, settings=None, video=None, reference=None):
    """The polish started at the scene's true C, T and A (G 1), on ``video`` and
    ``reference`` (default: the scene's)."""
    return polish_posture(
        scene.reference if reference is None else reference,
        scene.video if video is None else video,
        scene.C,
        scene.rotations,
        scene.translation,
        1.0,
        *([] if settings is None else [settings]),
    )


def _perturbed(scene: Scene, degrees: float, shift_m: float):
    """The truth with every driven joint turned by ``degrees`` about a random axis and the
    root moved by ``shift_m``."""
    g = torch.Generator().manual_seed(1)
    rotations = scene.rotations.clone()
    for j in _driven(scene.reference):
        axis = torch.nn.functional.normalize(torch.randn(FRAMES, 3, generator=g), dim=-1)
        axis = axis[:1].expand(FRAMES, 3)  # the same error on every frame: a style, not noise
        rotations[:, j] = rotations[:, j] @ rotation_vector_to_matrix(
            axis.double() * math.radians(degrees)
        )
    translation = scene.translation + torch.tensor([shift_m, 0.0, -shift_m], dtype=torch.float64)
    return rotations, translation


def test_the_posture_reproduces_the_renderers_joints(scene):
    """_Posture's forward kinematics at the true rotations and root puts every joint where
    motion.synth put it (an independent implementation)."""
    assert _e3d(scene, scene.rotations, scene.translation) < 1e-6


def test_started_at_the_truth_the_polish_stays(scene):
    out = _polish_from_truth(scene)
    assert _e3d(scene, out.rotations, out.translation) < 0.004
    assert out.loss_end <= out.loss_start + 1e-6


def test_the_polish_recovers_turned_joints_from_two_cameras(scene):
    """Every driven joint turned 12 degrees and the root moved 4 cm: with the silhouettes
    and 2-D joints of two cameras the polish takes the joints back within a fifth of the
    error and the silhouettes' overlap up."""
    rotations, translation = _perturbed(scene, 12.0, 0.04)
    before = _e3d(scene, rotations, translation)
    out = polish_posture(scene.reference, scene.video, scene.C, rotations, translation, 1.0)
    after = _e3d(scene, out.rotations, out.translation)
    assert after < before / 5, (before, after)
    assert _iou(scene, out.rotations, out.translation) > _iou(scene, rotations, translation)


def test_the_joints_first_take_back_a_posture_beyond_the_polishs_reach(scene):
    """Every driven joint turned 35 degrees: the polish (its silhouettes hold a posture near
    where it starts) leaves the joints some 1 % of the height off; a descent on the 2-D joints
    alone first (exact joints of two cameras, the skeleton's own) takes them back to within
    0.2 %, and the silhouettes' overlap to nearly 1."""
    rotations, translation = _perturbed(scene, 35.0, 0.04)
    start = _e3d(scene, rotations, translation)
    alone = polish_posture(scene.reference, scene.video, scene.C, rotations, translation, 1.0)
    first = PosturePolishSettings(joints_first_steps=150)
    out = polish_posture(scene.reference, scene.video, scene.C, rotations, translation, 1.0, first)
    assert _e3d(scene, alone.rotations, alone.translation) > 0.005, start
    assert _e3d(scene, out.rotations, out.translation) < 0.002
    assert _iou(scene, out.rotations, out.translation) > 0.99
    # without 2-D joints there is nothing to descend first: the polish as it was
    video = _without_joints(scene)
    plain = polish_posture(scene.reference, video, scene.C, rotations, translation, 1.0)
    same = polish_posture(scene.reference, video, scene.C, rotations, translation, 1.0, first)
    assert torch.equal(plain.rotations, same.rotations)
    assert torch.equal(plain.translation, same.translation)


def test_silhouettes_alone_improve_the_posture(scene):
    video = _without_joints(scene)
    rotations, translation = _perturbed(scene, 12.0, 0.04)
    out = polish_posture(scene.reference, video, scene.C, rotations, translation, 1.0)
    assert _e3d(scene, out.rotations, out.translation) < 0.6 * _e3d(scene, rotations, translation)
    assert _iou(scene, out.rotations, out.translation) > _iou(scene, rotations, translation) + 0.05


def test_no_steps_returns_the_start(scene):
    rotations, translation = _perturbed(scene, 5.0, 0.01)
    out = polish_posture(
        scene.reference,
        scene.video,
        scene.C,
        rotations,
        translation,
        1.0,
        PosturePolishSettings(steps=0),
    )
    assert torch.equal(out.rotations, rotations) and torch.equal(out.translation, translation)


def test_chunks_give_about_the_whole_answer(scene):
    """Solved in chunks of 4 frames (each tied to the last) the polish lands within a
    fraction of the error of solving all frames together."""
    rotations, translation = _perturbed(scene, 12.0, 0.04)
    whole = polish_posture(scene.reference, scene.video, scene.C, rotations, translation, 1.0)
    parts = polish_posture(
        scene.reference,
        scene.video,
        scene.C,
        rotations,
        translation,
        1.0,
        PosturePolishSettings(frames_per_chunk=4),
    )
    e_whole = _e3d(scene, whole.rotations, whole.translation)
    e_parts = _e3d(scene, parts.rotations, parts.translation)
    assert e_parts < e_whole + 0.005


def test_bad_shapes_and_settings_are_one_line_errors(scene):
    with pytest.raises(ValueError, match="expected C"):
        polish_posture(
            scene.reference, scene.video, scene.C[:3], scene.rotations, scene.translation, 1.0
        )
    with pytest.raises(PosturePolishSettingsError, match="steps"):
        PosturePolishSettings(steps=-1)
    with pytest.raises(PosturePolishSettingsError, match="keypoint_px"):
        PosturePolishSettings(keypoint_px=0.0)


@pytest.mark.parametrize("radii", [(5.0, 5.0), (6.0, 3.0)])
def test_outline_points_lie_on_the_capsule(radii):
    """Side points of an even capsule and every cap point lie on the boundary: the
    capsule's own signed distance is 0 there; an uneven capsule's side points (the normals
    at the axis approximate its tangents) lie within the radii's difference of it."""
    ends = torch.tensor([[10.0, 20.0], [40.0, 28.0]], dtype=torch.float64)
    r = torch.tensor(radii, dtype=torch.float64)
    points = capsule_outline(ends, r, 6)
    sdf, _ = capsule_sdf(points, ends, r)
    assert points.shape == (16, 2)
    slack = abs(radii[0] - radii[1]) * 0.2 + 1e-9
    assert sdf.abs().max() <= slack
    assert sdf[-4:-2].abs().max() < 1e-9  # the two caps along the axis


def test_map_reads_are_bilinear():
    maps = torch.arange(12.0).reshape(1, 1, 3, 4) ** 1.5
    uv = torch.tensor([[[[0.0, 0.0], [3.0, 2.0], [1.25, 0.5], [-5.0, 1.0]]]])
    got = _sample_map(maps, uv)[0, 0]
    m = maps[0, 0]
    by_hand = (
        0.75 * 0.5 * m[0, 1] + 0.25 * 0.5 * m[0, 2] + 0.75 * 0.5 * m[1, 1] + 0.25 * 0.5 * m[1, 2]
    )
    expected = torch.stack([m[0, 0], m[2, 3], by_hand, m[1, 0]])  # outside: the border
    torch.testing.assert_close(got, expected, rtol=1e-6, atol=1e-5)


def test_progress_wraps_the_chunks(scene):
    seen = []

    def progress(items, description, total):
        seen.append((description, total))
        return items

    polish_posture(
        scene.reference,
        scene.video,
        scene.C,
        scene.rotations,
        scene.translation,
        1.0,
        PosturePolishSettings(steps=1, frames_per_chunk=4),
        progress,
    )
    assert seen == [("polish (T, A)", 2)]


def test_keypoint_columns_that_name_no_joint_of_the_skeleton_are_left_out(scene):
    """A keypoint column named after no joint of the reference's skeleton (another body
    model's landmark) is ignored, not an error: the result equals that without it."""
    obs = scene.video.observation
    extra = torch.cat([obs.keypoints, obs.keypoints[..., :1, :]], dim=-2)
    video = dataclasses.replace(
        scene.video,
        observation=dataclasses.replace(obs, keypoints=extra),
        keypoint_joints=[*scene.video.keypoint_joints, "nose_tip"],
    )
    rotations, translation = _perturbed(scene, 8.0, 0.02)
    settings = PosturePolishSettings(steps=5, silhouette=0.0)
    plain = polish_posture(
        scene.reference, scene.video, scene.C, rotations, translation, 1.0, settings
    )
    more = polish_posture(scene.reference, video, scene.C, rotations, translation, 1.0, settings)
    torch.testing.assert_close(more.rotations, plain.rotations)


# -- the student's proportions -------------------------------------------------------------

#: bone offsets (the joint's offset from its parent) lengthened in the reshaped reference
#: below, and the part whose length that is: the knee's offset is the thigh, and so on
RESHAPED = {
    "LeftLeg": ("thigh_l", 1.10),
    "RightLeg": ("thigh_r", 1.10),
    "LeftFoot": ("shin_l", 0.92),
    "RightFoot": ("shin_r", 0.92),
    "LeftForeArm": ("upper_arm_l", 0.93),
    "RightForeArm": ("upper_arm_r", 0.93),
    "LeftHand": ("forearm_l", 1.06),
    "RightHand": ("forearm_r", 1.06),
}


def _reshaped_reference(tmp_path_factory) -> Reference:
    """The bundled walk with the bones of :data:`RESHAPED` scaled in the file itself (its
    unit kept), read as an independent reference."""
    bvh = read_bvh(REFERENCE)
    offsets = bvh.offsets.copy()
    for joint, (_, factor) in RESHAPED.items():
        offsets[bvh.names.index(joint)] *= factor
    path = tmp_path_factory.mktemp("reshaped") / "reshaped.bvh"
    write_bvh(dataclasses.replace(bvh, offsets=offsets), path)
    unit = Reference.from_bvh(REFERENCE).skeleton.metres_per_unit
    return Reference.from_bvh(path, metres_per_unit=unit)


def _reshaped_scales(reference: Reference, invert: bool) -> torch.Tensor:
    """``(P,)`` the part factors of :data:`RESHAPED` (``invert``: their inverses)."""
    scales = torch.ones(reference.spec.num_parts, dtype=torch.float64)
    for part, factor in RESHAPED.values():
        scales[reference.spec.part_names.index(part)] = 1 / factor if invert else factor
    return scales


def test_part_scales_lengthen_the_bones_as_the_file_would(scene, tmp_path_factory):
    """The reference's posture with part factors (Proportions.joint_scales, scaled_spec)
    equals that of a BVH file whose offsets were scaled by hand: every joint, and every
    capsule axis (one bone per limb part, so exactly)."""
    reshaped = _reshaped_reference(tmp_path_factory)
    reference = scene.reference
    proportions = Proportions.of(reference, _reshaped_scales(reference, invert=False))
    rotations = reference.rotations[:5]
    ours = reference.posture_frames(rotations, 1.0, proportions.joint_scales())
    theirs = reshaped.posture_frames(rotations)
    torch.testing.assert_close(ours.positions, theirs.positions, atol=1e-9, rtol=0)
    spec = scaled_spec(reference.spec, 1.0, proportions.part_scales)
    torch.testing.assert_close(
        spec.shapes.axis.norm(dim=-1), reshaped.spec.shapes.axis.norm(dim=-1), atol=1e-9, rtol=0
    )
    joint = reference.skeleton.names.index
    scales = proportions.joint_scales()
    assert float(scales[joint("LeftLeg")]) == pytest.approx(1.10)  # the knee: the thigh
    assert float(scales[joint("LeftUpLeg")]) == 1.0  # the hip joint: the pelvis


@pytest.fixture(scope="module")
def large_scene() -> Scene:
    """As :func:`scene`, at 320 x 240 pixels (focal 400), 16 frames."""
    cfg = SynthConfig(fps=12, warp=0.0, yaw_deg=90.0, cameras=2, size=[320, 240], focal_px=400)
    seq = synthesize(REFERENCE, cfg)
    reference = Reference.from_bvh(REFERENCE)
    video = features_from_sequence(seq, keypoints=True, noisy=False, image=False)
    video = video.cut(slice(0, 16))
    shown = torch.from_numpy(seq.arrays["C_shown"]).long()[:16]
    yaw = torch.from_numpy(seq.arrays["T_yaw_rad"])[:16]
    turn = rotation_vector_to_matrix(torch.stack([0 * yaw, yaw, 0 * yaw], -1))
    rotations = reference.rotations[shown].clone()
    rotations[:, 0] = turn @ rotations[:, 0]
    joints = torch.from_numpy(seq.arrays["joints3d"])[:16].double()
    height = float((joints[..., 1].amax(-1) - joints[..., 1].amin(-1)).mean())
    return Scene(reference, video, shown, rotations, joints[:, 0].clone(), joints, height)


def test_a_students_other_proportions_are_recovered(large_scene, tmp_path_factory):
    """The video shows the bundled walker; the reference is the same walk with thighs 10 %
    longer, shins 8 % shorter, upper arms 7 % shorter and forearms 6 % longer. From 2
    cameras' silhouettes and 2-D joints, at the polish's defaults, every part's factor comes
    out within 3 % of the truth (the inverse factors; 1 for the others)."""
    reshaped = _reshaped_reference(tmp_path_factory)
    s = large_scene
    fit = PosturePolishSettings(steps=0, proportion_steps=100)
    out = polish_posture(reshaped, s.video, s.C, s.rotations, s.translation, 1.0, fit)
    truth = _reshaped_scales(reshaped, invert=True)
    assert out.proportions.measured
    error = (out.proportions.part_scales / truth - 1).abs()
    assert float(error.max()) < 0.03, dict(
        zip(reshaped.spec.part_names, error.tolist(), strict=True)
    )
    # the default (proportion_steps=0): the reference's proportions, not measured
    none = polish_posture(
        reshaped, s.video, s.C, s.rotations, s.translation, 1.0, PosturePolishSettings(steps=0)
    )
    assert not none.proportions.measured
    assert torch.equal(none.proportions.part_scales, torch.ones_like(truth))


def test_without_2d_joints_the_proportions_are_not_measured(scene):
    video = _without_joints(scene)
    out = _polish_from_truth(scene, PosturePolishSettings(steps=1, proportion_steps=100), video)
    assert not out.proportions.measured
    assert out.proportions.as_dict() == {n: 1.0 for n in scene.reference.spec.part_names}


def test_part_groups_pair_left_and_right():
    names = ["pelvis", "thigh_l", "thigh_r", "head", "hand_r"]
    groups, index = part_groups(names, symmetric=True)
    assert groups == ["pelvis", "thigh", "head", "hand"]
    assert index.tolist() == [0, 1, 1, 2, 3]
    groups, index = part_groups(names, symmetric=False)
    assert groups == names and index.tolist() == [0, 1, 2, 3, 4]


def test_the_silhouettes_never_move_the_proportions(scene, tmp_path_factory):
    """With the 2-D joints' weight at 0 the proportions' fit sees only the silhouettes and
    the prior: the silhouettes move the posture, not the part lengths (a coat lengthens no
    trunk), so every factor stays exactly 1, even against a reshaped reference."""
    reshaped = _reshaped_reference(tmp_path_factory)
    settings = PosturePolishSettings(steps=0, keypoints=0.0, proportion_steps=20)
    out = _polish_from_truth(scene, settings, reference=reshaped)
    assert torch.equal(out.proportions.part_scales, torch.ones(reshaped.spec.num_parts).double())


def test_started_at_the_truth_the_silhouettes_alone_keep_it(scene):
    """Without 2-D joints, read as a rasteriser draws them (``rasterised``), the silhouettes
    alone hold the truth: a pixel is in the silhouette when its centre is inside the body, so
    the outline pays only beyond a pixel from the outer pixels' centres, and the ring just
    outside pays where the body covers it; the true outline costs nothing. Read to the
    centres (the default) the body shrinks into them: IoU 0.998 -> 0.958, the joints 0.8 %
    of the height off."""
    video = _without_joints(scene)
    s = PosturePolishSettings(steps=100, rasterised=True)
    out = _polish_from_truth(scene, s, video)
    truth = _iou(scene, scene.rotations, scene.translation)
    assert _iou(scene, out.rotations, out.translation) > truth - 0.005
    assert _e3d(scene, out.rotations, out.translation) < 0.002
    centres = _polish_from_truth(scene, dataclasses.replace(s, rasterised=False), video)
    assert _iou(scene, centres.rotations, centres.translation) < truth - 0.02
