"""2-D joints from files attached to a video: OpenPose JSON (BODY_25B, with a distracting
second person) and Sports2D pixel TRC written from a synthetic sequence's true joints, the
Pose2Sim demo's detections, and every bad input."""

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from motion.body.observation import Observation
from motion.bodyparts import BodyModel
from motion.keypoints import BODY_25B, KeypointFileError
from motion.registration.inputs import features_from_sequence
from motion.registration.keypoints import (
    BODY_25,
    HALPE_26,
    KeypointInputError,
    attach_keypoints,
    match_keypoints,
    read_openpose_people,
)
from motion.registration.types import Reference, RegistrationError, VideoFeatures
from motion.registration.video import VideoInput, default_camera
from motion.synth import SynthConfig, synthesize
from tests.conftest import SHARED_DATA, requires_shared_data

WALK = Path(__file__).resolve().parents[3] / "motion" / "data" / "cmu_02_01_walk.bvh"
SCALE = 0.5  # working pixels per file pixel
SHIFT = 70.0  # working pixels between the person and the distracting one
CONF = 0.8

#: BODY_25B keypoint -> CMU joint, the documented matches (in BODY_25B column order)
BODY25B_CMU = {
    "LShoulder": "LeftArm", "RShoulder": "RightArm", "LElbow": "LeftForeArm",
    "RElbow": "RightForeArm", "LWrist": "LeftHand", "RWrist": "RightHand",
    "LHip": "LeftUpLeg", "RHip": "RightUpLeg", "LKnee": "LeftLeg", "RKnee": "RightLeg",
    "LAnkle": "LeftFoot", "RAnkle": "RightFoot", "LBigToe": "LeftToeBase",
    "RBigToe": "RightToeBase",
}  # fmt: skip
#: Sports2D's HALPE_26 names in its TRC column order (its skeleton tree's)
SPORTS2D = [
    "Hip", "RHip", "RKnee", "RAnkle", "RBigToe", "RSmallToe", "RHeel", "LHip", "LKnee",
    "LAnkle", "LBigToe", "LSmallToe", "LHeel", "Neck", "Head", "Nose", "RShoulder", "RElbow",
    "RWrist", "LShoulder", "LElbow", "LWrist",
]  # fmt: skip


@pytest.fixture(scope="module")
def synthetic():
    """A 2-camera synthetic walk (8 fps, 160 x 120) as a VideoInput whose files were twice
    the working size, and the reference."""
    seq = synthesize(WALK, SynthConfig(fps=8, size=[160, 120], focal_px=120, cameras=2, seed=0))
    uv = seq.arrays["joints2d"]
    assert uv.min() > 2 and uv[..., 0].max() < 158 and uv[..., 1].max() < 118  # all in view
    features = features_from_sequence(seq, image=False)
    frames = list(seq.arrays["frames"])
    video = VideoInput(features, frames, SCALE, "", [Path("cam1.avi"), Path("cam2.avi")])
    return seq, video, Reference.from_bvh(WALK)


def _one_camera(video: VideoInput, c: int = 0) -> VideoInput:
    f = video.features
    rig = f.cameras
    rig = dataclasses.replace(
        rig, K=rig.K[c : c + 1], R=rig.R[c : c + 1], t=rig.t[c : c + 1],
        dist=rig.dist[c : c + 1], size=rig.size[c : c + 1], names=rig.names[c : c + 1],
    )  # fmt: skip
    obs = Observation(f.observation.silhouette[:, :, c : c + 1])
    return VideoInput(
        VideoFeatures(obs, rig, f.frame_rate, name="cam"), [video.frames[c]], SCALE, "", []
    )


def _file_px(uv: np.ndarray) -> np.ndarray:
    """Working pixels -> the original file's (the inverse of a resize by SCALE)."""
    return (uv + 0.5) / SCALE - 0.5


def _body25b(uv: np.ndarray, names: list[str], conf: float = CONF) -> list[float]:
    """One person's BODY_25B pose_keypoints_2d from joints ``uv (J, 2)`` in file pixels:
    the matched keypoints at their joints, the face and heels near the head / ankles."""
    j = {n: i for i, n in enumerate(names)}
    out = []
    for k in BODY_25B:
        if k in BODY25B_CMU:
            u, v = uv[j[BODY25B_CMU[k]]]
        elif k in ("LHeel", "RHeel", "LSmallToe", "RSmallToe"):
            u, v = uv[j["LeftFoot" if k[0] == "L" else "RightFoot"]] + 3.0
        else:
            u, v = uv[j["Head"]] + 2.0
        out += [float(u), float(v), conf]
    return out


def _write_openpose(folder: Path, seq, c: int, empty_entry: bool = False) -> None:
    """Camera ``c``'s true joints as OpenPose BODY_25B files, a more confident distracting
    person (the same pose SHIFT working pixels right) listed first."""
    folder.mkdir(parents=True)
    names = seq.meta["joint_names"]
    for f, uv in enumerate(seq.arrays["joints2d"][c]):
        true = _file_px(uv)
        other = _file_px(uv + np.array([SHIFT, 0.0]))
        people = [
            {"person_id": [-1], "pose_keypoints_2d": _body25b(other, names, 0.95)},
            {"person_id": [-1], "pose_keypoints_2d": _body25b(true, names)},
        ]
        if empty_entry:
            people.append({})
        doc = {"version": 1.3, "people": people}
        (folder / f"cam{c + 1:02d}.{f:04d}.json").write_text(json.dumps(doc))


def _write_trc(path: Path, uv: np.ndarray, names: list[str], rate: float, t0: int = 0) -> None:
    """Sports2D's pixel TRC layout (make_trc_with_trc_data): ``uv (F, M, 2)`` file pixels,
    NaN as an empty cell, Z = 0, 'm' as the unit, Time from frame ``t0``."""
    f, m = uv.shape[:2]
    head = [
        f"PathFileType\t4\t(X/Y/Z)\t{path}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        "\t".join(map(str, [rate, rate, f, m, "m", rate, 0, f])),
        "Frame#\tTime\t" + "\t\t\t".join(names) + "\t\t\t",
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(m)),
    ]
    rows = []
    for i in range(f):
        cells = [str(i), repr((t0 + i) / rate)]
        for u, v in uv[i]:
            cells += ["", "", "0.0"] if math.isnan(u) else [repr(float(u)), repr(float(v)), "0.0"]
        rows.append("\t".join(cells))
    path.write_text("\n".join(head + rows) + "\n")


def _sports2d_uv(seq, c: int = 0) -> np.ndarray:
    """Camera ``c``'s joints in Sports2D's columns (file pixels): matched names at their
    CMU joints (Neck at the CMU Neck), the others near the head or the hips."""
    j = {n: i for i, n in enumerate(seq.meta["joint_names"])}
    to_cmu = {**BODY25B_CMU, "Neck": "Neck", "Head": "Head", "Hip": "Hips", "Nose": "Head"}
    uv = seq.arrays["joints2d"][c]
    cols = [uv[:, j[to_cmu[n]]] if n in to_cmu else uv[:, j["Hips"]] + 1.0 for n in SPORTS2D]
    return _file_px(np.stack(cols, 1))


def _expected(seq, c: int, joints: list[str]) -> np.ndarray:
    j = {n: i for i, n in enumerate(seq.meta["joint_names"])}
    return seq.arrays["joints2d"][c][:, [j[n] for n in joints]]


# -- the synthetic walk ---------------------------------------------------------------------
def test_body25b_maps_to_the_documented_cmu_joints(synthetic):
    _, _, ref = synthetic
    matches, spec = match_keypoints(list(BODY_25B), ref)
    assert spec == "openpose_body25b"
    assert {m.keypoint: m.joint for m in matches} == BODY25B_CMU
    assert [m.column for m in matches] == sorted(BODY_25B.index(k) for k in BODY25B_CMU)
    assert {m.role for m in matches if m.keypoint == "LWrist"} == {"wrist_l"}  # not the hand end
    halpe, spec = match_keypoints(HALPE_26, ref)
    assert spec == "pose2sim_21"
    assert {m.keypoint: m.joint for m in halpe} == {**BODY25B_CMU, "Neck": "Neck"}
    # the spec file is a complete keypoint body model
    assert BodyModel.from_keypoints("openpose_body25b").num_parts == 15


def test_openpose_folders_attach_the_person_on_the_silhouette(synthetic, tmp_path):
    """Two cameras from cam01_json / cam02_json: every matched joint within 1e-3 px x scale
    of the truth, the confidence the file's, the more confident distractor never chosen."""
    seq, video, ref = synthetic
    for c in range(2):
        _write_openpose(tmp_path / "pose" / f"cam{c + 1:02d}_json", seq, c, empty_entry=c == 1)
    got = attach_keypoints(video, tmp_path / "pose", ref)
    kp = got.features.observation.keypoints
    joints = got.features.keypoint_joints
    assert joints == list(BODY25B_CMU.values())
    assert kp.shape == (1, video.features.num_frames, 2, len(joints), 3)
    for c in range(2):
        want = torch.from_numpy(_expected(seq, c, joints)).float()
        torch.testing.assert_close(kp[0, :, c, :, :2], want, atol=1e-3 * SCALE, rtol=0)
    assert torch.allclose(kp[..., 2], torch.tensor(CONF))
    assert "14 joints matched" in got.note and "LWrist=LeftHand" in got.note
    assert got.features.observation.silhouette is video.features.observation.silhouette
    # person=0 takes the first detection of each file: the distractor
    first = attach_keypoints(video, tmp_path / "pose", ref, person=0)
    shifted = first.features.observation.keypoints[0, :, 0, :, :2] - kp[0, :, 0, :, :2]
    torch.testing.assert_close(shifted[..., 0], torch.full_like(shifted[..., 0], SHIFT))
    # person=2: only camera 2's files have a third (empty) entry: nobody anywhere
    none = attach_keypoints(video, tmp_path / "pose", ref, person=2).features.observation
    assert (none.keypoints == 0).all()


def test_no_silhouette_follows_the_previous_choice_and_a_bystander_is_refused(synthetic, tmp_path):
    seq, video, ref = synthetic
    one = _one_camera(video)
    _write_openpose(tmp_path / "cam01_json", seq, 0)
    (tmp_path / "cam01_json" / "cam01.0010.json").write_text('{"people": []}')  # nobody
    sil = one.features.observation.silhouette.clone()
    sil[:, 3:6] = 0  # the person not segmented in frames 3-5: followed from frame 2
    sil[:, 8, :, :, :] = 0
    sil[:, 8, :, :2, :2] = 1  # frame 8's silhouette is elsewhere: nobody there
    obs = Observation(sil)
    one = dataclasses.replace(one, features=dataclasses.replace(one.features, observation=obs))
    kp = attach_keypoints(one, tmp_path / "cam01_json", ref).features.observation.keypoints
    want = torch.from_numpy(_expected(seq, 0, list(BODY25B_CMU.values()))).float()
    seen = torch.ones(kp.shape[1], dtype=torch.bool)
    seen[[8, 10]] = False
    torch.testing.assert_close(kp[0, seen, 0, :, :2], want[seen], atol=1e-3 * SCALE, rtol=0)
    assert (kp[0, [8, 10]] == 0).all()


def test_sports2d_trc_attaches_with_missing_points_and_a_time_offset(synthetic, tmp_path):
    seq, video, ref = synthetic
    one = _one_camera(video)
    uv = _sports2d_uv(seq)
    lw = SPORTS2D.index("LWrist")
    uv[4, lw] = np.nan  # an empty cell
    uv[5, lw] = 0.0  # fill_large_gaps_with = zeros
    path = tmp_path / "walk_Sports2D_px_person00.trc"
    _write_trc(path, uv, SPORTS2D, one.features.frame_rate)
    got = attach_keypoints(one, path, ref)
    kp = got.features.observation.keypoints
    joints = got.features.keypoint_joints
    assert set(joints) == {*BODY25B_CMU.values(), "Neck"} and len(joints) == 15
    want = torch.from_numpy(_expected(seq, 0, joints)).float()
    col = joints.index("LeftHand")
    ok = torch.ones(kp.shape[1:2] + kp.shape[3:4], dtype=torch.bool)
    ok[4:6, col] = False
    torch.testing.assert_close(kp[0, :, 0][ok][:, :2], want[ok], atol=1e-3 * SCALE, rtol=0)
    assert (kp[0, :, 0][ok][:, 2] == 1).all() and (kp[0, 4:6, 0, col] == 0).all()
    # a file written from frame 2 on (Sports2D's time_range), for the video read from frame 2
    late = tmp_path / "late_px_person00.trc"
    _write_trc(late, uv[2:], SPORTS2D, one.features.frame_rate, t0=2)
    cut = dataclasses.replace(one, features=one.features.cut(slice(2, None)))
    kp2 = attach_keypoints(cut, late, ref, start=2).features.observation.keypoints
    torch.testing.assert_close(kp2, kp[:, 2:])
    with pytest.raises(
        KeypointInputError, match=r"late_px_person00.trc: keypoints for video frames 2\.\."
    ):
        attach_keypoints(one, late, ref)
    # Sports2D's 2024 layout: pixels / 1000, Y up
    old = tmp_path / "old_px_person00.trc"
    _write_trc(old, uv * [1e-3, -1e-3], SPORTS2D, one.features.frame_rate)
    legacy = attach_keypoints(one, old, ref)
    torch.testing.assert_close(legacy.features.observation.keypoints, kp, atol=1e-4, rtol=0)
    assert "2024 layout" in legacy.note


def test_start_and_step_select_the_video_frames(synthetic, tmp_path):
    seq, video, ref = synthetic
    one = _one_camera(video)
    path = tmp_path / "walk_px_person00.trc"
    _write_trc(path, _sports2d_uv(seq), SPORTS2D, one.features.frame_rate)
    # the video read from frame 1, every 2nd frame (at half the frame rate)
    rows = torch.arange(1, one.features.num_frames, 2)
    f = one.features.cut(rows)
    f = dataclasses.replace(f, frame_rate=f.frame_rate / 2)
    kept = dataclasses.replace(one, features=f)
    full = attach_keypoints(one, path, ref).features.observation.keypoints
    kp = attach_keypoints(kept, path, ref, start=1, step=2).features.observation.keypoints
    torch.testing.assert_close(kp, full[:, rows])


# -- the Pose2Sim demo ----------------------------------------------------------------------
POSE2SIM = SHARED_DATA / "keypoints" / "pose2sim_balancing_trial"


@requires_shared_data()
@pytest.mark.shared_data
def test_the_pose2sim_cam01_detections_attach_to_the_tracked_person():
    """cam01's BODY_25B folder (2 detections a frame, 1080 x 1920) on a 100-frame stub at a
    quarter size whose silhouette is the box around the person Pose2Sim associated: that
    person is chosen in every frame, and the CMU walk's 14 documented joints are matched."""
    raw = read_openpose_people(POSE2SIM / "pose2d_openpose_body25b" / "cam01_json")
    assert raw.names == list(BODY_25B) and raw.num_frames == 100
    assoc = read_openpose_people(POSE2SIM / "pose2d_associated" / "cam01_json")
    scale, w, h = 0.25, 270, 480
    sil = torch.zeros(1, 100, 1, h, w)
    for t, people in enumerate(assoc.people):
        p = people[0][people[0][:, 2] > 0]
        (u0, v0), (u1, v1) = (p[:, :2].min(0) + 0.5) * scale, (p[:, :2].max(0) + 0.5) * scale
        sil[0, t, 0, int(v0) : math.ceil(v1), int(u0) : math.ceil(u1)] = 1
    rig = default_camera(w, h)
    stub = VideoInput(
        VideoFeatures(Observation(sil), rig, 60.0, name="cam01"),
        [np.zeros((100, h, w, 3), np.uint8)],
        scale,
        "",
        [SHARED_DATA / "video" / "pose2sim_balancing_trial" / "cam01.mp4"],
    )
    ref = Reference.from_bvh(WALK)
    got = attach_keypoints(stub, POSE2SIM / "pose2d_openpose_body25b" / "cam01_json", ref)
    assert got.features.keypoint_joints == list(BODY25B_CMU.values())
    kp = got.features.observation.keypoints[0, :, 0]  # (100, 14, 3)
    cols = [BODY_25B.index(k) for k in BODY25B_CMU]
    want = np.stack([people[0][cols] for people in assoc.people])
    want[..., :2] = (want[..., :2] + 0.5) * scale - 0.5
    want[want[..., 2] <= 0] = 0
    np.testing.assert_allclose(kp.numpy(), want, atol=1e-3)
    assert (kp[..., 2] > 0).float().mean() > 0.9
    # a folder of the 4 cameras for this 1-camera stub; the 3-D TRC
    with pytest.raises(KeypointInputError, match=r"keypoints for 4 camera\(s\) .* but 1 video"):
        attach_keypoints(stub, POSE2SIM / "pose2d_openpose_body25b", ref)
    trc = POSE2SIM / "pose3d" / "S00_P00_T01_BalancingTrial_0-100.trc"
    with pytest.raises(KeypointInputError, match=r"0-100.trc: a 3-D TRC"):
        attach_keypoints(stub, trc, ref)


# -- bad inputs -----------------------------------------------------------------------------
def test_bad_inputs_are_refused_naming_the_file(synthetic, tmp_path):
    seq, video, ref = synthetic
    one = _one_camera(video)
    rate = one.features.frame_rate
    folder = tmp_path / "cam01_json"
    _write_openpose(folder, seq, 0)
    t = one.features.num_frames

    def refused(source, pattern, v=one, **kw):
        with pytest.raises(KeypointInputError, match=pattern) as info:
            attach_keypoints(v, source, ref, **kw)
        assert isinstance(info.value, KeypointFileError | RegistrationError)
        assert "\n" not in str(info.value)

    # camera counts
    refused(folder, r"cam01_json: keypoints for 1 camera\(s\) \(cam01_json\) but 2 video", v=video)
    refused([folder, folder], r"keypoints for 2 camera\(s\)")
    # frame counts: fewer files than the video's frames; another count than the video file's
    short = tmp_path / "short"
    short.mkdir()
    for f in sorted(folder.glob("*.json"))[: t - 3]:
        (short / f.name).write_text(f.read_text())
    refused(
        short,
        rf"short: keypoints for video frames 0\.\.{t - 4} \({t - 3} frames\) but the video's {t} frames are 0\.\.{t - 1}",
    )
    clip = tmp_path / "clip.avi"
    out = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"MJPG"), rate, (160, 120))
    for _ in range(t + 2):
        out.write(np.zeros((120, 160, 3), np.uint8))
    out.release()
    refused(
        folder,
        rf"cam01_json: {t} frames of keypoints but clip.avi has {t + 2} frames",
        v=dataclasses.replace(one, paths=[clip]),
    )
    # unreadable files, missing paths, other file types
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "f0.json").write_text("{not json")
    refused(bad, r"bad/f0.json: not OpenPose JSON")
    (bad / "f0.json").write_text(json.dumps({"people": [{"pose_keypoints_2d": [1.0] * 30}]}))
    refused(bad, r"f0.json: pose_keypoints_2d has 30 values, no known keypoint set")
    refused(tmp_path / "nowhere", r"nowhere: no such keypoint file or folder")
    refused(clip, r"clip.avi: not a keypoint source")
    empty = tmp_path / "empty"
    empty.mkdir()
    refused(empty, r"empty: no OpenPose .json files in it nor in its subfolders")
    garbage = tmp_path / "garbage.trc"
    garbage.write_text("hello\n")
    refused(garbage, r"garbage.trc:1: not a TRC file")
    # the wrong marker set: names no spec knows, found and expected named
    uv = _sports2d_uv(seq)
    markers = tmp_path / "markers_px.trc"
    _write_trc(markers, uv, [f"M{i}" for i in range(len(SPORTS2D))], rate)
    refused(
        markers,
        r"markers_px.trc: no keypoint name is a landmark's: found M0, M1, .*; expected names such as .*LShoulder",
    )
    # a 3-D TRC, metres, another frame rate, a person index for a TRC
    three = tmp_path / "three.trc"
    _write_trc(three, uv, SPORTS2D, rate)
    three.write_text(three.read_text().replace("\t0.0", "\t1.5"))
    refused(three, r"three.trc: a 3-D TRC \(Z is not 0")
    metres = tmp_path / "walk_m_person00.trc"
    _write_trc(metres, uv / 200 - 0.2, SPORTS2D, rate)
    refused(metres, r"walk_m_person00.trc: the keypoints span only .* not pixels")
    fast = tmp_path / "fast_px.trc"
    _write_trc(fast, uv, SPORTS2D, 3 * rate)
    refused(fast, rf"fast_px.trc: keypoints at {3 * rate:g} frames/s but cam")
    good = tmp_path / "good_px.trc"
    _write_trc(good, uv, SPORTS2D, rate)
    refused(good, r"good_px.trc: a TRC file holds one person", person=1)
    # cameras with different keypoint sets; bad arguments
    refused([folder, good], r"every camera needs the same keypoint set", v=video)
    refused(folder, r"person must be an index >= 0", person=-1)
    refused(folder, r"unknown keypoint convention 'body99'", convention="body99")
    refused(folder, r"expected 78 \(as the convention halpe26\)", convention="halpe26")


def test_body25_is_told_from_body25b(synthetic, tmp_path):
    """BODY_25's MidHip lies between its hips: a BODY_25 folder is read as BODY_25 and
    matches the same joints; forcing body25b on it finds other names at those columns."""
    seq, video, ref = synthetic
    one = _one_camera(video)
    folder = tmp_path / "b25"
    folder.mkdir()
    j = {n: i for i, n in enumerate(seq.meta["joint_names"])}
    for f, uv in enumerate(seq.arrays["joints2d"][0]):
        px = _file_px(uv)
        vals = []
        for k in BODY_25:
            if k == "MidHip":
                u, v = (px[j["LeftUpLeg"]] + px[j["RightUpLeg"]]) / 2
            elif k in BODY25B_CMU:
                u, v = px[j[BODY25B_CMU[k]]]
            else:
                u, v = px[j["Head"]]
            vals += [float(u), float(v), CONF]
        (folder / f"{f:04d}.json").write_text(json.dumps({"people": [{"pose_keypoints_2d": vals}]}))
    assert read_openpose_people(folder).names == BODY_25
    got = attach_keypoints(one, folder, ref)
    joints = got.features.keypoint_joints
    assert set(joints) == {*BODY25B_CMU.values(), "Neck"}
    want = torch.from_numpy(_expected(seq, 0, [n for n in joints if n != "Neck"])).float()
    keep = [i for i, n in enumerate(joints) if n != "Neck"]
    kp = got.features.observation.keypoints[0, :, 0, keep, :2]
    torch.testing.assert_close(kp, want, atol=1e-3 * SCALE, rtol=0)
