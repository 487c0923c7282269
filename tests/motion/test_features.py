"""Image features: both backends agree, OpenCV's distance transform is exact, silhouettes
are recovered from a synthetic static-camera clip, and videos open (or fail clearly)."""

import cv2
import numpy as np
import pytest
import torch
from scipy.ndimage import distance_transform_edt

from motion.features import (
    VideoError,
    clean_foreground,
    distance_to_edges,
    edges,
    foreground_masks,
    median_coverage,
    read_camera_videos,
    read_video,
    select_person,
    track_person,
)
from tests.conftest import SHARED_DATA, requires_shared_data


def _shapes_image(seed=0, size=96):
    rng = np.random.default_rng(seed)
    img = np.full((size, size), 0.2, dtype=np.float32)
    cv2.rectangle(img, (10, 15), (50, 60), 0.8, -1)
    cv2.circle(img, (70, 60), 15, 0.6, -1)
    img += rng.normal(0, 0.01, img.shape).astype(np.float32)
    return torch.from_numpy(img.clip(0, 1))[None, None]


def test_canny_backends_agree():
    img = _shapes_image()
    a = edges(img, 0.1, 0.3, backend="opencv")[0, 0].numpy()
    b = edges(img, 0.1, 0.3, backend="kornia")[0, 0].numpy()
    assert a.sum() > 100 and b.sum() > 100
    # agreement within one pixel, both ways (F-score of edge pixels)
    near_a = cv2.dilate(a.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    near_b = cv2.dilate(b.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    precision = (b & near_a).sum() / b.sum()
    recall = (a & near_b).sum() / a.sum()
    assert precision > 0.95 and recall > 0.95, (precision, recall)
    assert (a == b).mean() > 0.99


def test_opencv_distance_transform_is_exact_and_kornia_close():
    g = np.random.default_rng(1)
    mask = np.zeros((1, 1, 64, 80), dtype=bool)
    mask[0, 0, g.integers(0, 64, 12), g.integers(0, 80, 12)] = True
    exact = distance_transform_edt(~mask[0, 0])
    ocv = distance_to_edges(torch.from_numpy(mask), backend="opencv")[0, 0].numpy()
    np.testing.assert_allclose(ocv, exact, atol=1e-3)
    kor = distance_to_edges(torch.from_numpy(mask), backend="kornia")[0, 0].numpy()
    rel = np.abs(kor - exact).mean() / exact.mean()
    assert rel < 0.2, rel  # kornia's is an approximation (DESIGN.md: ~13 % on sparse edges)


def test_empty_edge_map_is_infinite_far():
    assert torch.isinf(distance_to_edges(torch.zeros(1, 1, 5, 5, dtype=torch.bool), "opencv")).all()


def _synthetic_clip(frames=40, size=(60, 80)):
    rng = np.random.default_rng(2)
    bg = rng.integers(40, 200, (*size, 3), dtype=np.uint8)
    clip, truth = [], []
    for f in range(frames):
        img = bg.astype(np.int16) + rng.integers(-3, 4, bg.shape)
        m = np.zeros(size, dtype=bool)
        x = 5 + f
        m[15:45, x : x + 12] = True
        img[m] = (230, 30, 30)
        clip.append(img.clip(0, 255).astype(np.uint8))
        truth.append(m)
    return np.stack(clip), np.stack(truth)


@pytest.mark.parametrize("method", ["mog2", "median"])
def test_foreground_masks_recover_a_moving_person(method):
    clip, truth = _synthetic_clip()
    masks = foreground_masks(clip, method=method, threshold=30 if method == "median" else 25)
    iou = (masks & truth).sum((1, 2)) / (masks | truth).sum((1, 2))
    assert np.median(iou) > 0.85, np.median(iou)


def test_shadow_the_foreground_encloses_is_foreground_and_the_rest_is_not():
    """A ring of foreground around shadow pixels (a grey shirt inside arms and shoulders):
    filled. Background pixels inside it (an arm's gap): kept out. Shadow reaching the
    border (cast on the floor) and shadow inside a ring with a gap: kept out."""
    raw = np.zeros((1, 40, 60), dtype=bool)
    shadow = np.zeros_like(raw)
    raw[0, 5:25, 5:25] = True
    raw[0, 9:21, 9:21] = False  # the ring's inside ...
    shadow[0, 9:21, 9:15] = True  # ... half shadow, half background
    shadow[0, 30:40, 0:20] = True  # on the floor, reaching the border
    raw[0, 5:25, 35:55] = True
    raw[0, 9:21, 39:51] = False
    raw[0, 5:9, 44:46] = False  # a gap in the second ring
    shadow[0, 9:21, 39:51] = True
    out = clean_foreground(raw, shadow, 0, 0)
    assert out[0, 9:21, 9:15].all() and not out[0, 9:21, 15:21].any()
    assert not out[0, 30:40, 0:20].any() and not out[0, 9:21, 39:51].any()
    assert (out & ~raw).sum() == 12 * 6  # nothing else added
    assert (clean_foreground(raw, None, 0, 0) == raw).all()


def test_mog2_counts_a_shirt_darker_than_the_wall_and_not_a_cast_shadow():
    """MOG2 calls a darker copy of the background's colour shadow: a grey shirt (0.7 of a
    light wall) framed by a red head, arms and legs is the person all the same, while the
    person's shadow on the floor (the wall at 0.7, reaching the image's bottom) is not. The
    person walks 3 px a frame, so MOG2's slow learning never takes the red for the wall."""
    rng = np.random.default_rng(3)
    wall = np.array([200, 200, 190], dtype=np.int16)
    clip = []
    for f in range(20):
        img = wall + rng.integers(-2, 3, (70, 110, 3))
        x = 5 + 3 * f
        img[8:50, x : x + 26] = (220, 40, 40)  # head, arms, legs: the frame of the shirt
        img[16:38, x + 6 : x + 20] = (0.7 * wall).astype(np.int16)  # wider than a closing
        img[58:70, x + 26 : x + 40] = (0.7 * wall).astype(np.int16)  # cast on the floor
        clip.append(img.clip(0, 255).astype(np.uint8))
    last = foreground_masks(np.stack(clip), method="mog2", threshold=25)[-1]
    x = 5 + 3 * 19
    assert last[16:38, x + 6 : x + 20].mean() > 0.95
    assert last[60:70, x + 28 : x + 38].mean() < 0.05


def test_select_person_largest_and_nearest():
    m = np.zeros((40, 40), dtype=bool)
    m[2:10, 2:10] = True  # 64 px, top left
    m[20:35, 20:35] = True  # 225 px, bottom right
    assert select_person(m)[25, 25] and not select_person(m)[5, 5]
    near = select_person(m, near=(5.0, 5.0))
    assert near[5, 5] and not near[25, 25]


def test_video_errors(tmp_path):
    with pytest.raises(VideoError, match="no such video file"):
        read_video(tmp_path / "missing.mp4")
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"not a video")
    with pytest.raises(VideoError, match=r"bad\.mp4"):
        read_video(bad)


@requires_shared_data()
@pytest.mark.shared_data
def test_reads_the_shared_video():
    frames = read_video(SHARED_DATA / "video" / "pose2sim_balancing_trial" / "cam01.mp4", count=5)
    assert frames.shape == (5, 1920, 1080, 3) and frames.dtype == np.uint8


def test_camera_videos_must_agree(tmp_path):
    from motion.draw import write_video

    frames = [np.full((24, 32, 3), 100, dtype=np.uint8)] * 4
    a = write_video(tmp_path / "a.avi", frames, 10)
    b = write_video(tmp_path / "b.avi", frames[:3], 10)
    with pytest.raises(VideoError, match=r"different frame counts \(a.avi: 4, b.avi: 3\)"):
        read_camera_videos([a, b])
    with pytest.raises(VideoError, match="frames are 32 x 24 px but the calibration says 64 x 48"):
        read_camera_videos([a], expected_sizes=[[64, 48]])
    assert len(read_camera_videos([a, a], expected_sizes=[[32, 24], [30, 24]])) == 2


@requires_shared_data()
@pytest.mark.shared_data
def test_pose2sim_videos_fit_their_calibration():
    from motion.cameras import load_pose2sim_calibration

    folder = SHARED_DATA / "video" / "pose2sim_balancing_trial"
    rig = load_pose2sim_calibration(folder / "calibration" / "Calib_qualisys.toml")
    videos = read_camera_videos(
        [folder / f"cam0{c}.mp4" for c in range(1, 5)],
        expected_sizes=rig.size.numpy(),
        count=3,
        scale=0.25,
    )
    assert [v.shape[0] for v in videos] == [3, 3, 3, 3]


def test_track_person_keeps_the_chosen_one_when_another_is_larger():
    masks = np.zeros((10, 40, 60), dtype=bool)
    for f in range(10):
        masks[f, 5:15, 5 + 2 * f : 12 + 2 * f] = True  # the student, small, moving right
        masks[f, 20:38, 40 - f : 55 - f] = True  # a bystander, larger, moving left
    tracked = track_person(masks, start=(8.0, 10.0))
    assert tracked[:, 5:15].any(axis=(1, 2)).all()
    assert not tracked[:, 20:38].any()


def _frames_with_boxes(boxes, size=(60, 80), grey=100, colour=200) -> np.ndarray:
    """``(N, H, W, 3)`` uint8: a flat scene with one filled box ``(x, y, w, h)`` per frame."""
    frames = np.full((len(boxes), *size, 3), grey, dtype=np.uint8)
    for frame, (x, y, w, h) in zip(frames, boxes, strict=True):
        frame[y : y + h, x : x + w] = colour
    return frames


def test_median_coverage_counts_each_frames_largest_changed_region():
    # a body over the same place in 30 of 50 frames, elsewhere in 20; a speck of noise
    # beside it in every frame is not the largest region and counts nowhere
    boxes = [(10, 10, 12, 20)] * 30 + [(50, 30, 12, 20)] * 20
    frames = _frames_with_boxes(boxes)
    frames[:, 50:52, 5:7] = 0
    background = np.full(frames.shape[1:], 100, dtype=np.uint8)
    coverage = median_coverage(frames, background, 30.0, 0, 0)
    assert coverage[15, 15] == pytest.approx(30 / 50)
    assert coverage[35, 55] == pytest.approx(20 / 50)
    assert coverage[51, 6] == 0 and coverage[0, 0] == 0
    # only the box counts, outline included, nothing beside it
    assert coverage[10:30, 10:22].min() == pytest.approx(0.6) and coverage[9, 10] == 0


def test_median_coverage_marks_where_a_median_holds_the_person():
    # a body whose surface changes from frame to frame (limbs, clothes) over one place in 30
    # of 50 frames, elsewhere in 20: the temporal median there is the body, not the scene
    rng = np.random.default_rng(0)
    boxes = [(10, 10, 12, 20)] * 30 + [(50, 30, 12, 20)] * 20
    frames = _frames_with_boxes(boxes)
    for frame, (x, y, w, h) in zip(frames, boxes, strict=True):
        frame[y : y + h, x : x + w] = rng.integers(150, 256, (h, w, 1), dtype=np.uint8)
    median = np.median(frames, axis=0).astype(np.uint8)
    assert (median[10:30, 10:22] >= 150).all()
    coverage = median_coverage(frames, median, 30.0, 0, 0)
    # where it stays, its box counts in its own frames at least (its ghost in the others):
    # held; where it only passes, not
    assert coverage[15, 15] >= 30 / 50 and coverage[35, 55] <= 20 / 50
    with pytest.raises(ValueError, match=r"background must be \(60, 80, 3\)"):
        median_coverage(frames, median[:10], 30.0)
    with pytest.raises(ValueError, match="frames must be"):
        median_coverage(frames[..., 0], median, 30.0)
