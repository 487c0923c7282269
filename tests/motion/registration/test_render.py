"""The overlay's pictures: the camera of resized frames against pixel-centre geometry,
upscaled overlays against the same picture drawn at the video's own size, and the labels
computed inside the body's box against the whole frame's."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from motion.cameras import load_pose2sim_calibration, resized_rig
from motion.registration.export import load_registration
from motion.registration.render import _labels, body_poses, camera, side_by_side_frames
from motion.registration.types import Reference
from motion.render import label_map, project_parts
from tests.motion.registration.conftest import REFERENCE


def _video(path) -> np.ndarray:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    cap.release()
    return np.stack(frames)


def test_a_resized_camera_sees_each_point_at_the_scaled_pixel_centre(student_video):
    """cv2.resize maps pixel centres by (u + 0.5) s - 0.5: a point's projection in the
    resized image is its native projection mapped so, per axis, at any factor."""
    rig = load_pose2sim_calibration(student_video.calibration)
    w, h = (int(v) for v in rig.size[0].tolist())
    size = (round(w * 2.5), h * 3)
    big = resized_rig(rig, [(w, h)], [size])
    assert big.size[0].tolist() == [size[0], size[1]]
    g = torch.Generator().manual_seed(0)
    points = torch.randn(20, 3, generator=g, dtype=torch.float64) * 0.5
    points[:, 1] += 1.0
    uv, depth = rig.project(points.to(rig.K))
    uv_big, depth_big = big.project(points.to(big.K))
    scale = torch.tensor([size[0] / w, size[1] / h], dtype=uv.dtype)
    torch.testing.assert_close(uv_big, (uv + 0.5) * scale - 0.5, atol=1e-6, rtol=0)
    torch.testing.assert_close(depth_big, depth)


def test_an_upscaled_overlay_is_the_same_picture_drawn_bigger(register_run):
    """The overlay at 4x, shrunk back, matches the one drawn at the video's size (bodies
    drawn at the larger size differ only along their outlines); min_height at or below the
    frame's height changes nothing."""
    reg = load_registration(register_run.out / "registration.npz")
    reference = Reference.from_bvh(REFERENCE)
    rig = load_pose2sim_calibration(register_run.student.calibration)
    frames = _video(register_run.student.video)
    h, w = frames.shape[1:3]
    poses = body_poses(reg, reference)
    ids = [0, len(frames) // 2]
    small = list(side_by_side_frames(frames, rig, 0, poses, frame_ids=ids))
    same = list(side_by_side_frames(frames, rig, 0, poses, frame_ids=ids, min_height=h))
    big = list(side_by_side_frames(frames, rig, 0, poses, frame_ids=ids, min_height=4 * h))
    for a, b, c in zip(small, same, big, strict=True):
        assert a.shape == (h, 2 * w, 3) and c.shape == (4 * h, 8 * w, 3)
        np.testing.assert_array_equal(a, b)
        shrunk = cv2.resize(c, (2 * w, h), interpolation=cv2.INTER_AREA).astype(float)
        differs = np.abs(shrunk - a.astype(float)).mean(-1) > 40
        # bodies drawn at 4x move their outlines by under a native pixel: what differs lies
        # on an outline of the native picture (its edges, grown by one pixel)
        grey = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)
        outline = cv2.dilate(cv2.Canny(grey, 30, 90), np.ones((3, 3), np.uint8)) > 0
        assert differs.any() and (differs & ~outline).mean() < 0.01, (differs & ~outline).mean()
    # the two frames' pictures do differ (the test can fail): the body moved
    assert np.abs(small[0].astype(float) - small[1].astype(float)).mean(-1).__gt__(40).any()


def test_labels_inside_the_bodys_box_are_the_whole_frames_label_map(register_run):
    """The overlay's part labels are computed inside the box around the projected parts
    only: the same map as label_map over every pixel, for bodies inside the image, half
    outside it and wholly outside it."""
    reg = load_registration(register_run.out / "registration.npz")
    rig = camera(load_pose2sim_calibration(register_run.student.calibration), 0)
    poses = body_poses(reg, Reference.from_bvh(REFERENCE))
    w, h = (int(v) for v in rig.size[0].tolist())
    segments = poses.segments("student")[[0, len(reg.C) // 2]]
    sideways = segments.clone()
    sideways[..., 0] += 0.6  # half out of the view (1.2 m wide about the body)
    gone = segments.clone()
    gone[..., 0] += 50.0
    for segs in (segments, sideways, gone):
        got = _labels(rig, segs, poses.radii, h, w)
        parts = project_parts(rig, segs.to(rig.K), poses.radii.to(rig.K))
        want = label_map(parts, h, w)[0][:, 0]
        torch.testing.assert_close(got, want, rtol=0, atol=0)
    assert (_labels(rig, segments, poses.radii, h, w) >= 0).any()
    assert (_labels(rig, gone, poses.radii, h, w) < 0).all()
