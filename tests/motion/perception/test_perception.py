"""The person detector: its declared interface, the files :func:`detect_videos` writes (read
back by the keypoint reader, cached), the MediaPipe detector against the Pose2Sim trial's
own OpenPose keypoints, and ``motion register`` using it by default."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np
import pytest

from motion.__main__ import main
from motion.keypoints import BODY_25B, MEDIAPIPE_POSE_33
from motion.perception import (
    DETECTORS,
    DetectorUnavailable,
    PerceptionSettings,
    PerceptionSettingsError,
    PersonDetection,
    PersonDetector,
    detect_videos,
    make_detector,
    read_masks,
    register_detector,
)
from motion.perception.fusion import fuse_silhouettes
from motion.perception.run import masks_at
from motion.registration.keypoints import match_keypoints, read_openpose_people
from motion.registration.types import Reference
from tests.conftest import SHARED_DATA, requires_shared_data

WALK = Path(__file__).resolve().parents[3] / "motion" / "data" / "cmu_02_01_walk.bvh"
POSE2SIM = SHARED_DATA / "keypoints" / "pose2sim_balancing_trial" / "pose2d_openpose_body25b"
POSE2SIM_VIDEO = SHARED_DATA / "video" / "pose2sim_balancing_trial"
SPORTS2D = SHARED_DATA / "video" / "sports2d_demo" / "demo.mp4"
requires_mediapipe = pytest.mark.skipif(
    importlib.util.find_spec("mediapipe") is None, reason="mediapipe is not installed"
)

#: MediaPipe landmark -> CMU joint: the matches the mediapipe_pose33 spec must give
MEDIAPIPE_CMU = {
    "LShoulder": "LeftArm", "RShoulder": "RightArm", "LElbow": "LeftForeArm",
    "RElbow": "RightForeArm", "LWrist": "LeftHand", "RWrist": "RightHand",
    "LHip": "LeftUpLeg", "RHip": "RightUpLeg", "LKnee": "LeftLeg", "RKnee": "RightLeg",
    "LAnkle": "LeftFoot", "RAnkle": "RightFoot", "LFootIndex": "LeftToeBase",
    "RFootIndex": "RightToeBase",
}  # fmt: skip


# -- the declared interface -----------------------------------------------------------------
def test_mediapipe_landmarks_map_to_the_documented_cmu_joints():
    matches, spec = match_keypoints(list(MEDIAPIPE_POSE_33), Reference.from_bvh(WALK))
    assert spec == "mediapipe_pose33"  # chosen over BODY_25B's spec, which shares names
    assert {m.keypoint: m.joint for m in matches} == MEDIAPIPE_CMU
    assert [m.column for m in matches] == sorted(MEDIAPIPE_POSE_33.index(k) for k in MEDIAPIPE_CMU)


def test_the_settings_name_the_registered_detectors():
    choices = PerceptionSettings.__dataclass_fields__["detector"].metadata
    assert set(DETECTORS) == {"mediapipe"}
    assert "mediapipe" in str(choices)
    assert PerceptionSettings(detector=None).detector is None
    with pytest.raises(PerceptionSettingsError, match="detector must be one of"):
        PerceptionSettings(detector="openpose")
    with pytest.raises(PerceptionSettingsError, match="width"):
        PerceptionSettings(width=10)
    with pytest.raises(PerceptionSettingsError, match="no detector"):
        make_detector(PerceptionSettings(detector=None))


def _detector_class(**declared) -> type[PersonDetector]:
    base = {"name": "probe", "keypoint_set": "mediapipe33", "spec": "mediapipe_pose33"}
    body = {**base, **declared, "detect": lambda self, rgb: []}
    return type("Probe", (PersonDetector,), body)


@pytest.mark.parametrize(
    ("declared", "message"),
    [
        ({"name": "mediapipe"}, "is taken"),
        ({"keypoint_set": "body99"}, "keypoint_set 'body99' is not one of"),
        ({"spec": "openpose_body25b"}, "not in the mediapipe33 keypoints"),
        ({"name": ""}, "declares name"),
    ],
)
def test_a_detector_declaring_what_it_cannot_give_is_refused_when_registered(declared, message):
    before = dict(DETECTORS)
    with pytest.raises(TypeError, match=message):
        register_detector(_detector_class(**declared))
    assert before == DETECTORS


# -- the files detect_videos writes ---------------------------------------------------------
class SquareFinder(PersonDetector):
    """Finds the bright square of :func:`_square_video`: every keypoint at its centre,
    confidence 0.9, its pixels as the mask; counts its calls."""

    name: ClassVar[str] = "squares"
    keypoint_set: ClassVar[str] = "mediapipe33"
    spec: ClassVar[str] = "mediapipe_pose33"
    gives_mask: ClassVar[bool] = True
    version: ClassVar[str] = "squares 1"

    def __init__(self):
        self.calls = 0
        self.sizes = set()

    def detect(self, rgb):
        self.calls += 1
        self.sizes.add(rgb.shape[:2])
        bright = rgb.mean(-1) > 128
        if not bright.any():
            return []
        v, u = np.nonzero(bright)
        point = [u.mean(), v.mean(), 0.9]
        return [PersonDetection(np.tile(point, (33, 1)), bright.astype(np.float32))]


def _square_video(path: Path, frames: int = 12, size=(320, 160)) -> list[tuple[float, float]]:
    """A video whose frame ``i`` shows a 40 px white square at ``x = 20 + 20 i`` (frame 5
    empty); returns the squares' centres in the video's pixels (NaN: none)."""
    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h))
    centres = []
    for i in range(frames):
        image = np.zeros((h, w, 3), np.uint8)
        if i == 5:
            centres.append((np.nan, np.nan))
        else:
            x, y = 20 + 20 * i, 60
            image[y : y + 40, x : x + 40] = 255
            centres.append((x + 19.5, y + 19.5))
        writer.write(image)
    writer.release()
    return centres


def test_detections_read_back_in_the_videos_pixels_one_file_per_video_frame(tmp_path):
    """Frames 1, 3, ... detected at half size: each kept frame's file holds the square's
    centre in the video's pixels (within 0.5 px: the half-size frame's centre, mapped back),
    every other frame an empty file; the masks are the kept frames' at half size."""
    video = tmp_path / "squares.avi"
    centres = _square_video(video)
    kept = list(range(1, 12, 2))
    finder = SquareFinder()
    run = detect_videos(
        [video], tmp_path / "det", kept, PerceptionSettings(width=160), detector=finder
    )
    assert finder.sizes == {(80, 160)}
    (cam,) = run.cameras
    assert (cam.frames_total, cam.detected) == (12, 5)  # frame 5 shows nobody
    read = read_openpose_people(cam.folder)
    assert read.names == MEDIAPIPE_POSE_33 and read.num_frames == 12
    for i, people in enumerate(read.people):
        if i in kept and i != 5:
            assert people.shape == (1, 33, 3)
            np.testing.assert_allclose(people[0, :, :2], np.tile(centres[i], (33, 1)), atol=0.5)
            np.testing.assert_allclose(people[0, :, 2], 0.9)
        else:
            assert people.shape[0] == 0
    frames, masks = read_masks(cam.masks)
    assert frames.tolist() == kept and masks.shape == (6, 80, 160)
    assert masks[kept.index(5)].max() == 0
    assert abs(masks[0].sum() - 20 * 20) <= 20  # the 40 px square at half size
    assert run.summary()["detected"] == {"squares.avi": 5}
    assert run.frames_per_second > 0 and not run.reused


def test_a_rerun_with_the_same_inputs_reuses_the_files_and_a_change_detects_again(tmp_path):
    video = tmp_path / "squares.avi"
    _square_video(video)
    out = tmp_path / "det"
    first = SquareFinder()
    detect_videos([video], out, [0, 1, 2], detector=first)
    again = SquareFinder()
    run = detect_videos([video], out, [0, 1, 2], detector=again)
    assert again.calls == 0 and run.reused and run.frames_per_second is None
    assert run.cameras[0].detected == 3
    for change in (
        {"frames": [0, 1, 2, 3]},
        {"settings": PerceptionSettings(min_tracking_confidence=0.7)},
        {"settings": PerceptionSettings(cache=False)},
    ):
        finder = SquareFinder()
        detect_videos(
            [video], out, change.get("frames", [0, 1, 2]), change.get("settings"), detector=finder
        )
        assert finder.calls == len(change.get("frames", [0, 1, 2])), change
    _square_video(video, frames=10)  # the video itself changed
    finder = SquareFinder()
    detect_videos([video], out, [0, 1, 2], detector=finder)
    assert finder.calls == 3
    assert len(list((out / "01_squares_json").glob("*.json"))) == 10


def test_frames_must_increase():
    with pytest.raises(ValueError, match="increasing frame indices"):
        detect_videos(["x.avi"], "out", [3, 2], detector=SquareFinder())


def test_a_missing_mediapipe_says_how_to_install_it(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_mediapipe(name, *args, **kwargs):
        if name.startswith("mediapipe"):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_mediapipe)
    with pytest.raises(
        DetectorUnavailable, match=r"not installed.*mediapipe==0\.10\.14.*detector=none"
    ):
        make_detector(PerceptionSettings())


def test_masks_at_the_working_size_are_the_videos_frames_resized_and_padded(tmp_path):
    video = tmp_path / "squares.avi"
    _square_video(video)
    run = detect_videos([video], tmp_path / "det", [0, 4, 5], detector=SquareFinder())
    masks, found = masks_at(run.cameras[0], [4, 5, 0, 7], 0.25, (100, 50))
    assert masks.shape == (4, 50, 100) and found.tolist() == [True, False, True, False]
    assert masks[:, :, 80:].max() == 0 and masks[:, 40:].max() == 0  # padding (80 x 40 frames)
    # frame 4's square: x 100..139, y 60..99 in the video -> 25..35, 15..25 at 1/4
    on = np.argwhere(masks[0] > 0.5)
    assert on.min(0).tolist() == [15, 25] and on.max(0).tolist() == [24, 34]


# -- fusing the detector's mask with background subtraction ---------------------------------
def _box(shape, top, left, bottom, right, value=1.0):
    image = np.zeros(shape, np.float32)
    image[top:bottom, left:right] = value
    return image


def test_fusion_drops_the_shadow_and_a_bystander_and_keeps_what_subtraction_lost():
    """A person 20-60 x 30-40 px; background subtraction sees their upper half and a shadow
    beside it (frame 0), or only the shadow-free upper half (frame 1); the mask holds the
    whole person (0.9) and a bystander far away: the fused silhouette is the person's mask.
    Frame 2's mask is only the bystander's and frame 3 detected nobody: the subtraction's."""
    shape = (80, 100)
    person = _box(shape, 20, 30, 60, 40, 0.9)
    bystander = _box(shape, 20, 80, 60, 90, 0.9)
    upper = _box(shape, 20, 30, 40, 40) > 0
    shadow = _box(shape, 20, 40, 60, 55) > 0
    foreground = np.stack([upper | shadow, upper, upper, upper])
    masks = np.stack([person + bystander, person + bystander, bystander, person])
    fused, used = fuse_silhouettes(foreground, masks, np.array([1, 1, 1, 0], bool), reach_px=3)
    assert used.tolist() == [True, True, False, False]
    for t in (0, 1):
        np.testing.assert_array_equal(fused[t], person)
    for t in (2, 3):
        np.testing.assert_array_equal(fused[t], foreground[t].astype(np.float32))
    with pytest.raises(ValueError, match=r"must be \(T, H, W\)"):
        fuse_silhouettes(foreground, masks[:, :10], np.ones(4, bool), 3)


# -- MediaPipe on real frames ---------------------------------------------------------------
#: joints both detectors place on the same anatomical point (hips differ by convention)
SHARED_JOINTS = ["LShoulder", "RShoulder", "LElbow", "RElbow", "LWrist", "RWrist", "LKnee",
                 "RKnee", "LAnkle", "RAnkle"]  # fmt: skip


@requires_shared_data()
@requires_mediapipe
@pytest.mark.slow
@pytest.mark.shared_data
def test_mediapipe_joints_near_the_trials_openpose_keypoints(tmp_path):
    """30 frames of the Pose2Sim trial's cam01 against its shipped OpenPose BODY_25B (an
    independent detector), the nearest OpenPose person, both confident: the median distance
    within 22 px (measured 13.7 px for these joints over 4 cameras x 100 frames, 1.7 % of the
    person's 780 px height, cam01 alone 15: benchmarks/bench_perception.py --accuracy; the
    <= 8 px target of issue 36 is not met by this detector), and the mask holds the torso's
    keypoints."""
    frames = list(range(30))
    run = detect_videos([POSE2SIM_VIDEO / "cam01.mp4"], tmp_path / "det", frames)
    ours = read_openpose_people(run.cameras[0].folder)
    theirs = read_openpose_people(POSE2SIM / "cam01_json")
    assert run.cameras[0].detected == 30
    mp_cols = [MEDIAPIPE_POSE_33.index(k) for k in SHARED_JOINTS]
    op_cols = [BODY_25B.index(k) for k in SHARED_JOINTS]
    gaps = []
    for f in frames:
        mine = ours.people[f][0, mp_cols]
        people = theirs.people[f][:, op_cols]
        person = people[
            np.nanargmin(np.nanmedian(np.linalg.norm(people[..., :2] - mine[:, :2], axis=-1), 1))
        ]
        ok = (mine[:, 2] > 0.5) & (person[:, 2] > 0.3)
        gaps += np.linalg.norm(mine[ok, :2] - person[ok, :2], axis=-1).tolist()
    assert len(gaps) >= 0.8 * 30 * len(SHARED_JOINTS)
    assert np.median(gaps) < 22.0, np.median(gaps)
    _, masks = read_masks(run.cameras[0].masks)
    scale = masks.shape[2] / 1080
    torso = [MEDIAPIPE_POSE_33.index(k) for k in ("LShoulder", "RShoulder", "LHip", "RHip")]
    inside = [
        masks[j, round((v + 0.5) * scale - 0.5), round((u + 0.5) * scale - 0.5)] > 0.5
        for j, f in enumerate(frames)
        for u, v, _ in ours.people[f][0, torso]
    ]
    assert np.mean(inside) >= 0.9


@requires_shared_data()
@requires_mediapipe
@pytest.mark.slow
@pytest.mark.shared_data
def test_register_uses_the_detector_by_default_and_a_rerun_reuses_it(tmp_path):
    """``motion register`` on 12 frames of the Sports2D walk without --keypoints: the
    detector's joints are the keypoint observation (the note names them), summary.json has
    its frames per second, and a second run into the same folder reuses the detections."""
    argv = [
        "register", "--reference", str(WALK), "--video", str(SPORTS2D), "--out",
        str(tmp_path / "out"), "--person", "1190,660", "--quiet", "video.start=75",
        "video.count=12", "video.width=160", "refine.particles=12", "refine.band=4",
        "refine.iterations=1", "refine.restarts=1", "refine.rounds=1",
    ]  # fmt: skip
    summaries = []
    for _ in range(2):
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            assert main(argv) == 0
        summaries.append(json.loads((tmp_path / "out" / "summary.json").read_text()))
    first, second = (s["detection"] for s in summaries)
    assert first["detector"].startswith("mediapipe") and first["frames"] == 12
    assert first["frames_per_second"] > 0 and not first["reused"]
    assert first["detected"]["demo.mp4"] >= 10
    assert second["reused"] and second["frames_per_second"] is None
    assert "mediapipe_pose33 names" in summaries[0]["notes"]["cameras"]
    assert (tmp_path / "out" / "detections" / "manifest.json").is_file()
