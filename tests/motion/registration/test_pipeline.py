"""register(): the stages run in order on a short synthetic student; frames where the
person is out of view are carried by their neighbours; a video without the person is
refused."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from motion.body.observation import Observation, PartShapes
from motion.registration import Registration, RegistrationError, RegistrationSettings, register
from motion.registration.approximate import Stage1Result
from motion.registration.inputs import features_from_sequence
from motion.registration.pipeline import _carry_over_nonfinite, silhouette_iou
from motion.registration.refine import RefineSettings, place_poses
from motion.registration.types import Reference, frame_ranges
from motion.synth import SynthConfig, synthesize
from tests.motion.body.conftest import WALK

QUICK = RegistrationSettings(
    refine=RefineSettings(particles=16, iterations=2, restarts=1, band=6, rounds=1, window=12)
)


@pytest.fixture(scope="module")
def short():
    seq = synthesize(WALK, SynthConfig(fps=25, yaw_deg=20, seed=1))
    return seq, Reference.from_bvh(WALK), features_from_sequence(seq).cut(slice(0, 40))


def _blank(video, frames):
    obs = video.observation
    sil = obs.silhouette.clone()
    sil[:, frames] = 0.0
    return dataclasses.replace(
        video, observation=Observation(sil, obs.edge_distance, obs.image, obs.keypoints)
    )


def test_register_returns_every_frame_and_carries_unseen_ones(short):
    """Frames 10-12 blanked (the person out of view): every frame still gets C, T and A of
    the right shapes, C is monotone and the blanked frames' C lies between their
    neighbours'; the result says how many frames were unseen, and that one camera did not
    measure G."""
    seq, ref, video = short
    result = register(ref, _blank(video, slice(10, 13)), settings=QUICK)
    assert isinstance(result, Registration)
    n, j = video.num_frames, ref.skeleton.num_joints
    assert result.C.shape == (n,) and result.A.shape == (n, j, 3, 3)
    assert result.T_rotation.shape == (n, 3, 3) and result.T_translation.shape == (n, 3)
    assert bool((result.C[1:] >= result.C[:-1]).all())
    assert result.C_stage1[9] <= result.C_stage1[11] <= result.C_stage1[13]
    assert result.notes["unseen_frames"] == "3"
    # one perspective camera: G stays 1, not measured, and the note says why
    assert result.G == 1.0 and not result.G_measured
    assert result.notes["G"].startswith("G = 1.0 (not estimated)")
    eye = torch.eye(3, dtype=result.A.dtype)
    torch.testing.assert_close(result.A[:, 0], eye.expand(n, 3, 3))
    assert {"stage0", "stage1", "stages23"} <= set(result.timings)
    assert 0 <= float(result.fit.min()) and float(result.fit.mean()) > 0.5
    c_true = torch.from_numpy(seq.arrays["C_true"][:n])
    assert float((result.C - c_true).abs().float().mean()) < 12  # stage 1 alone: ~5


def test_a_video_without_the_person_is_refused(short):
    _, ref, video = short
    with pytest.raises(RegistrationError, match="never seen"):
        register(ref, _blank(video, slice(None)), settings=QUICK)
    with pytest.raises(RegistrationError, match="at least 2 video frames"):
        register(ref, video.cut(slice(0, 1)), settings=QUICK)


def test_silhouette_iou_in_chunks_is_the_same_and_high_at_the_truth(short):
    """The fit score rendered a few frames at a time (as a long video is) is the one
    rendered all at once; at the true posture (no articulation here) it is high."""
    seq, ref, video = short
    n = video.num_frames
    c = torch.from_numpy(seq.arrays["C_shown"][:n]).long()
    yaw = torch.from_numpy(seq.arrays["T_yaw_rad"][:n])
    zero = torch.zeros_like(yaw)
    r_yaw = torch.stack(
        [
            torch.stack([yaw.cos(), zero, yaw.sin()], -1),
            torch.stack([zero, zero + 1, zero], -1),
            torch.stack([-yaw.sin(), zero, yaw.cos()], -1),
        ],
        -2,
    )
    rot = r_yaw @ ref.rotations[c, 0]
    pos = torch.from_numpy(seq.arrays["joints3d"][:n, 0])
    poses = place_poses(rot, pos, ref.body_poses(c)).float()
    shapes = PartShapes(ref.spec.shapes.axis.float(), ref.spec.shapes.radii.float())
    sil = video.observation.silhouette[0]
    whole = silhouette_iou(shapes, video.cameras, sil, poses, chunk=n)
    assert torch.equal(silhouette_iou(shapes, video.cameras, sil, poses, chunk=7), whole)
    assert whole.shape == (n,) and float(whole.min()) > 0.8


def test_uint8_frames_give_the_same_registration(short):
    """Colour kept as uint8 (a long video's memory) and converted window by window: the
    same registration, bit for bit, as from float frames."""
    seq, ref, video = short
    small = features_from_sequence(seq, image_dtype=torch.uint8).cut(slice(0, 12))
    runs = [register(ref, v, settings=QUICK) for v in (video.cut(slice(0, 12)), small)]
    for name in ("C", "C_stage1", "rotations", "T_translation", "fit"):
        assert torch.equal(getattr(runs[0], name), getattr(runs[1], name)), name


def test_frame_ranges_name_runs_of_frames():
    assert frame_ranges([9, 3, 4, 5]) == "3-5, 9"
    assert frame_ranges(torch.tensor([0])) == "0"
    assert frame_ranges(list(range(0, 20, 2)), most=3) == "0, 2, 4, and 7 more"


def test_stage1_frames_that_diverged_carry_their_neighbours_c_and_t():
    """NaN on frames 2-3 of 6: they take C interpolated and T from the nearest finite
    frame (as unseen frames do), with a warning naming them; all NaN: a one-line error."""
    c = torch.tensor([0, 4, 8, 12, 16, 20])
    rot = torch.eye(3, dtype=torch.float64).repeat(6, 1, 1)
    pos = torch.arange(18, dtype=torch.float64).reshape(6, 3)
    pos[2:4] = float("nan")
    stage1 = Stage1Result(c, rot, pos, torch.zeros(6, dtype=torch.float64), 0, 0.0)
    fixed, warnings = _carry_over_nonfinite(stage1, "clip.mp4")
    assert fixed.C.tolist() == [0, 4, 8, 12, 16, 20]  # interpolated between 4 and 16
    torch.testing.assert_close(fixed.translation[2], pos[1])
    torch.testing.assert_close(fixed.translation[3], pos[4])
    assert warnings == [
        "video frames 2-3 (counted from the first registered frame): stage 1's body "
        "transform diverged (NaN); they carry their neighbours' C and T"
    ]
    same, none = _carry_over_nonfinite(
        dataclasses.replace(stage1, translation=pos.nan_to_num()), "x"
    )
    assert none == [] and same.translation is not None
    with pytest.raises(RegistrationError, match=r"^clip.mp4: stage 1 found no finite body"):
        _carry_over_nonfinite(dataclasses.replace(stage1, translation=pos * math.nan), "clip.mp4")
