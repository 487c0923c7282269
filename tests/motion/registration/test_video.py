"""Real videos -> VideoFeatures: silhouettes of a drawn moving ellipse, person selection,
intrinsics at the working width, every bad input, and the shipped outdoor video."""

import math

import cv2
import numpy as np
import pytest
import torch

from motion.cameras import CameraRig
from motion.draw import write_video
from motion.features import VideoError
from motion.registration.inputs import NO_EDGE_PX
from motion.registration.types import RegistrationError, VideoFeatures
from motion.registration.video import (
    FIELD_OF_VIEW_DEG,
    VideoInput,
    VideoSettings,
    VideoSettingsError,
    default_camera,
    features_from_videos,
    held_share,
    plates_beside,
)
from tests.conftest import SHARED_DATA, requires_shared_data

F64 = torch.float64
W, H, N = 160, 120, 40


def _background(width=W, height=H, seed=0) -> np.ndarray:
    """A static textured scene: smooth colour blobs plus fine stripes (edges everywhere)."""
    rng = np.random.default_rng(seed)
    coarse = rng.integers(40, 200, (height // 10, width // 10, 3)).astype(np.uint8)
    bg = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    bg[::7] = bg[::7] // 2  # stripes: background edges (clutter away from the person)
    return bg


def _blob_masks(blobs, n=N, width=W, height=H) -> np.ndarray:
    """``(n, height, width)`` bool: each blob ``(x0, x1, axes, colour)`` an ellipse moving
    from x0 to x1 and bobbing vertically."""
    masks = np.zeros((len(blobs), n, height, width), dtype=np.uint8)
    for b, (x0, x1, axes, _) in enumerate(blobs):
        for t in range(n):
            x = x0 + (x1 - x0) * t / (n - 1)
            y = height / 2 + 10 * math.sin(2 * math.pi * t / n)
            cv2.ellipse(masks[b, t], (round(x), round(y)), axes, 15 * t / n, 0, 360, 1, -1)
    return masks.astype(bool)


ONE = [(20, 140, (12, 24), (230, 40, 40))]


def _video(path, blobs=ONE, n=N, width=W, height=H, fps=25.0):
    """Write the blobs over the background as an MJPG .avi; returns the ``(B, n, h, w)``
    masks of the blobs drawn."""
    masks = _blob_masks(blobs, n, width, height)
    frames = np.repeat(_background(width, height)[None], n, 0)
    for b, (*_, colour) in enumerate(blobs):
        frames[masks[b]] = colour
    write_video(path, frames, fps)
    return masks


def _rig(c=1, size=(W, H), names=None) -> CameraRig:
    k = torch.tensor([[200.0, 0.5, 81.3], [0.0, 210.0, 58.7], [0.0, 0.0, 1.0]], dtype=F64)
    return CameraRig(
        k.expand(c, 3, 3).clone(),
        torch.eye(3, dtype=F64).expand(c, 3, 3).clone(),
        torch.tensor([[0.1, 0.2, 3.0]] * c, dtype=F64),
        torch.tensor([[0.01, -0.002, 0.0, 0.0, 0.0]] * c, dtype=F64),
        torch.tensor([list(size)] * c, dtype=F64),
        names or [f"c{i}" for i in range(c)],
    )


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per frame, ``(T, H, W)`` bool each."""
    inter = (a & b).reshape(len(a), -1).sum(1)
    union = (a | b).reshape(len(a), -1).sum(1)
    return inter / np.maximum(union, 1)


@pytest.fixture(scope="module")
def one(tmp_path_factory):
    path = tmp_path_factory.mktemp("one") / "v.avi"
    return path, _video(path)[0]


def test_the_silhouette_is_the_moving_ellipse(one):
    """One uncalibrated video at native size: the tracked silhouette matches the drawn
    ellipse (IoU > 0.8 every frame; all of it, and nothing beyond 4 px of it); the features have the layouts of
    features_from_sequence; edges are only near the person; the camera is the default one,
    and the note says its focal length was assumed."""
    path, mask = one
    vi = features_from_videos([path], None, VideoSettings(width=None))
    assert isinstance(vi, VideoInput) and isinstance(vi.features, VideoFeatures)
    f = vi.features
    obs = f.observation
    assert obs.silhouette.shape == (1, N, 1, H, W) and obs.silhouette.dtype == torch.float32
    assert set(obs.silhouette.unique().tolist()) <= {0.0, 1.0}
    sil = obs.silhouette[0, :, 0].numpy() > 0.5
    iou = _iou(sil, mask)
    assert iou.min() > 0.8, iou
    # what is lost to a perfect 1.0 is a halo: MJPG's chroma subsampling and block ringing
    # smear the ellipse's colour 1-4 px outwards; nothing of the ellipse is missed
    assert (sil & mask).sum() > 0.99 * mask.sum()
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (9, 9))
    halo = np.stack([cv2.dilate(m.astype(np.uint8), disc) for m in mask]) > 0
    assert not (sil & ~halo).any()
    assert obs.edge_distance.shape == (1, N, 1, H, W)
    d = obs.edge_distance[0, :, 0].numpy()
    assert np.isfinite(d).all() and d.max() <= NO_EDGE_PX and d.min() == 0
    # edges lie within edge_band_px (6) of the silhouette: none in the striped background
    far = cv2.distanceTransform((~mask[10]).astype(np.uint8), cv2.DIST_L2, 5) > 10
    assert (d[10][far] > 0).all()
    assert obs.image.shape == (1, N, 1, 3, H, W) and 0 <= obs.image.min() <= obs.image.max() <= 1
    assert len(vi.frames) == 1 and vi.frames[0].shape == (N, H, W, 3)
    assert vi.frames[0].dtype == np.uint8 and vi.scale == 1.0 and vi.paths == [path]
    assert f.frame_rate == 25.0 and f.num_frames == N and f.name == "v.avi"
    torch.testing.assert_close(f.cameras.K, default_camera(W, H).K)
    assert "focal length was assumed" in vi.note and f"{FIELD_OF_VIEW_DEG:g} degree" in vi.note


def test_start_count_and_step_select_frames(one):
    path, mask = one
    st = VideoSettings(width=None, start=3, count=10, step=2, colour=False)
    f = features_from_videos(path, None, st).features
    assert f.num_frames == 10 and f.frame_rate == 12.5 and f.observation.image is None
    iou = _iou(f.observation.silhouette[0, :, 0].numpy() > 0.5, mask[3:23:2])
    assert iou.min() > 0.8


def test_person_picks_which_of_two_blobs_to_follow(tmp_path):
    """A large and a small moving blob: by default the largest is followed; ``person`` (in
    original pixels, here given at half the working width) picks the small one."""
    blobs = [(15, 75, (10, 22), (230, 40, 40)), (100, 150, (6, 14), (40, 40, 230))]
    masks = _video(tmp_path / "two.avi", blobs)
    default = features_from_videos([tmp_path / "two.avi"], None, VideoSettings(width=None))
    sil = default.features.observation.silhouette[0, :, 0].numpy() > 0.5
    assert _iou(sil, masks[0]).min() > 0.8
    chosen = VideoSettings(width=80, person=(100.0, 60.0))  # the small blob in frame 0
    small = features_from_videos([tmp_path / "two.avi"], None, chosen)
    sil = small.features.observation.silhouette[0, :, 0].numpy() > 0.5
    want = np.stack(
        [cv2.resize(m.astype(np.uint8), (80, 60), interpolation=cv2.INTER_AREA) for m in masks[1]]
    )
    assert sil.shape == (N, 60, 80) and _iou(sil, want > 0).mean() > 0.7
    assert not (
        sil & (np.stack([cv2.resize(m.astype(np.uint8), (80, 60)) for m in masks[0]]) > 0)
    ).any()


def test_a_clean_plate_finds_a_person_who_stays_in_place(tmp_path):
    """A blob that hardly moves is part of every median of the video's frames, so background
    subtraction without help finds little of it; a picture of the empty scene
    (``backgrounds``) finds all of it. A plate of the wrong size or count is refused."""
    masks = _video(tmp_path / "still.avi", [(70, 76, (12, 24), (230, 40, 40))])[0]
    median = features_from_videos(tmp_path / "still.avi", None, VideoSettings(width=None))
    sil = median.features.observation.silhouette[0, :, 0].numpy() > 0.5
    assert _iou(sil, masks).mean() < 0.5
    # ... and says so, naming the file and the remedy
    (warning,) = median.warnings
    assert median.held == [tmp_path / "still.avi"]
    assert warning.startswith("still.avi: the person stays over the same pixels")
    assert "--background or saved beside the video as still_background.png" in warning
    plate = tmp_path / "empty.png"
    cv2.imwrite(str(plate), cv2.cvtColor(_background(), cv2.COLOR_RGB2BGR))
    st = VideoSettings(width=80, backgrounds=[str(plate)])
    clean = features_from_videos(tmp_path / "still.avi", None, st)
    assert clean.warnings == [] and clean.held == []
    sil = clean.features.observation.silhouette[0, :, 0].numpy() > 0.5
    want = np.stack(
        [cv2.resize(m.astype(np.uint8), (80, 60), interpolation=cv2.INTER_AREA) for m in masks]
    )
    assert _iou(sil, want > 0).min() > 0.8
    # the plate beside the video under the video's name is found without being given
    cv2.imwrite(
        str(tmp_path / "still_background.png"), cv2.cvtColor(_background(), cv2.COLOR_RGB2BGR)
    )
    found = features_from_videos(tmp_path / "still.avi", None, VideoSettings(width=80))
    assert found.warnings == [] and "still_background.png), found by its name" in found.note
    assert np.array_equal(
        found.features.observation.silhouette.numpy(), clean.features.observation.silhouette.numpy()
    )
    off = VideoSettings(width=None, find_backgrounds=False)
    assert len(features_from_videos(tmp_path / "still.avi", None, off).warnings) == 1
    # one of the wrong size says it was found, and how to leave it out
    cv2.imwrite(str(tmp_path / "still_background.png"), _background(80, 60))
    _raises(
        VideoError,
        r"still_background\.png: the background is 80 x 60 px but still\.avi's frames are "
        r"160 x 120 \(found beside the video by its name; video\.find_backgrounds=false "
        r"ignores it\)",
        [tmp_path / "still.avi"],
        None,
        VideoSettings(),
    )
    (tmp_path / "still_background.png").unlink()
    two = VideoSettings(backgrounds=[str(plate), str(plate)])
    _raises(
        VideoSettingsError,
        r"one picture per video \(1\); got 2",
        [tmp_path / "still.avi"],
        None,
        two,
    )
    cv2.imwrite(str(tmp_path / "small.png"), _background(80, 60))
    small = VideoSettings(backgrounds=[str(tmp_path / "small.png")])
    _raises(
        VideoError,
        r"small\.png: the background is 80 x 60 px but still\.avi's frames are 160 x 120",
        [tmp_path / "still.avi"],
        None,
        small,
    )
    (tmp_path / "junk.png").write_bytes(b"not a picture")
    junk = VideoSettings(backgrounds=[str(tmp_path / "junk.png")])
    _raises(VideoError, r"junk\.png: not an image file", [tmp_path / "still.avi"], None, junk)


def test_a_person_crossing_the_view_gets_no_warning_about_the_background(one):
    path, _ = one
    crossing = features_from_videos(path, None, VideoSettings(width=None))
    assert crossing.warnings == [] and crossing.held == []
    kept = VideoSettings(width=None, background_frames=0)
    assert features_from_videos(path, None, kept).warnings == []


def test_plates_are_found_beside_every_video_or_not_at_all(tmp_path):
    videos = [tmp_path / "a.avi", tmp_path / "b.mp4"]
    (tmp_path / "a_background.png").write_bytes(b"")
    assert plates_beside(videos) is None
    (tmp_path / "b_background.png").write_bytes(b"")
    assert plates_beside(videos) == [tmp_path / "a_background.png", tmp_path / "b_background.png"]


def test_held_share_is_the_mean_share_of_the_persons_box_on_held_pixels():
    held = np.zeros((10, 10), dtype=bool)
    held[:, :5] = True
    person = np.zeros((3, 10, 10), dtype=bool)
    person[0, 2:4, 3:7] = True  # half its box held
    person[1, 8, 0] = True  # all of it
    assert held_share(person, held) == pytest.approx((0.5 + 1.0) / 2)
    assert held_share(np.zeros((2, 10, 10), dtype=bool), held) == 0.0


def test_intrinsics_scale_with_the_working_width(tmp_path):
    """width=80 halves 160-px frames: focal lengths and skew scale by 0.5 exactly, the
    principal point by the pixel-centre convention ``(c + 0.5) s - 0.5``; R, t and distortion
    are unchanged; a camera a few pixels narrower than the other (within the calibration's
    tolerance) is padded to the common working size, and the note says so."""
    _video(tmp_path / "a.avi")
    _video(tmp_path / "b.avi", width=150)
    rig = _rig(2, names=["a", "b"])
    rig.size[1, 0] = 150
    vi = features_from_videos(
        [tmp_path / "a.avi", tmp_path / "b.avi"], rig, VideoSettings(width=80)
    )
    cams = vi.features.cameras
    assert vi.scale == 0.5
    for c in range(2):
        k0, k = rig.K[c], cams.K[c]
        assert k[0, 0] == 0.5 * k0[0, 0] and k[1, 1] == 0.5 * k0[1, 1] and k[0, 1] == 0.5 * k0[0, 1]
        assert k[0, 2] == (k0[0, 2] + 0.5) * 0.5 - 0.5 and k[1, 2] == (k0[1, 2] + 0.5) * 0.5 - 0.5
        assert k[2].tolist() == [0.0, 0.0, 1.0]
    for key in ("R", "t", "dist"):
        assert torch.equal(getattr(cams, key), getattr(rig, key))
    assert cams.size.tolist() == [[80.0, 60.0], [80.0, 60.0]] and cams.names == ["a", "b"]
    assert vi.features.observation.silhouette.shape == (1, N, 2, 60, 80)
    assert [f.shape for f in vi.frames] == [(N, 60, 80, 3)] * 2
    assert "b.avi: 75 x 60 px at the working scale, padded" in vi.note
    assert "focal length" not in vi.note
    assert (vi.features.observation.silhouette[0, :, 1, :, 75:] == 0).all()
    # the default camera scales the same way
    alone = features_from_videos([tmp_path / "a.avi"], None, VideoSettings(width=80))
    f0 = (W / 2) / math.tan(math.radians(FIELD_OF_VIEW_DEG) / 2)
    k = alone.features.cameras.K[0]
    assert k[0, 0] == 0.5 * f0 and k[0, 2] == ((W - 1) / 2 + 0.5) * 0.5 - 0.5 == 39.5


def _raises(error, match, *args, **kwargs):
    with pytest.raises(error, match=match) as info:
        features_from_videos(*args, **kwargs)
    assert "\n" not in str(info.value)
    return str(info.value)


def test_bad_videos_are_named_in_one_line(tmp_path):
    good = tmp_path / "good.avi"
    _video(good)
    _raises(VideoError, r"none\.avi: no such video file", [tmp_path / "none.avi"])
    (tmp_path / "junk.avi").write_bytes(np.random.default_rng(0).bytes(3000))
    _raises(VideoError, r"junk\.avi: OpenCV cannot open", [tmp_path / "junk.avi"])
    writer = cv2.VideoWriter(str(tmp_path / "e.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25, (W, H))
    writer.release()
    _raises(
        VideoError, r"e\.avi: (the video has no frames|OpenCV cannot open)", [tmp_path / "e.avi"]
    )
    _video(tmp_path / "short.avi", n=30)
    _raises(
        VideoError,
        r"different frame counts \(good\.avi: 40, short\.avi: 30\)",
        [good, tmp_path / "short.avi"],
        _rig(2),
    )
    _video(tmp_path / "fast.avi", fps=30)
    _raises(
        VideoError,
        r"different frame rates \(good\.avi: 25 fps, fast\.avi: 30 fps\)",
        [good, tmp_path / "fast.avi"],
        _rig(2),
    )
    # a frame-rate override accepts files whose headers disagree
    st = VideoSettings(frame_rate=50.0, width=40)
    assert (
        features_from_videos([good, tmp_path / "fast.avi"], _rig(2), st).features.frame_rate == 50
    )
    _raises(
        VideoError,
        r"good\.avi: frames are 160 x 120 px but the calibration says 320 x 240",
        [good],
        _rig(1, size=(320, 240)),
    )


def _decodable(path) -> int:
    """Frames a plain OpenCV loop decodes from ``path`` (the independent count)."""
    cap = cv2.VideoCapture(str(path))
    n = 0
    while cap.read()[0]:
        n += 1
    cap.release()
    return n


def test_a_video_cut_short_is_named_with_its_last_good_frame(tmp_path):
    """An .avi whose last 40 % of bytes are gone still declares 40 frames: the error names
    the file and the last frame OpenCV can decode; ``truncated=keep`` registers up to it
    with a warning; a stretch that ends before the cut reads as usual."""
    full = tmp_path / "full.avi"
    _video(full)
    cut = tmp_path / "cut.avi"
    data = full.read_bytes()
    cut.write_bytes(data[: int(0.6 * len(data))])
    good = _decodable(cut)
    assert 0 < good < N - 2
    message = _raises(VideoError, r"cut\.avi: the video stops decoding after frame", [cut])
    assert f"after frame {good - 1} (0-based) but its file declares {N} frames" in message
    assert f"up to {good - 1} with video.truncated=keep" in message
    kept = features_from_videos([cut], None, VideoSettings(truncated="keep"))
    assert kept.features.num_frames == good
    assert len(kept.warnings) == 1 and f"only the frames up to {good - 1}" in kept.warnings[0]
    early = features_from_videos([cut], None, VideoSettings(count=good - 3))
    assert early.features.num_frames == good - 3 and early.warnings == []
    assert features_from_videos([full], None, VideoSettings()).warnings == []


def test_bad_cameras_and_settings_are_named_in_one_line(tmp_path):
    good = tmp_path / "good.avi"
    _video(good)
    _raises(
        RegistrationError,
        r"the calibration has 2 camera\(s\) \(c0, c1\) but 1 video\(s\) were given \(good\.avi\)",
        [good],
        _rig(2),
    )
    _raises(
        RegistrationError, r"2 videos \(good\.avi, good\.avi\) but no calibration", [good, good]
    )
    _raises(
        VideoError,
        r"good\.avi: person \(500, 20\) is outside the 160 x 120 px frame",
        [good],
        None,
        VideoSettings(person=(500, 20)),
    )
    _raises(
        VideoSettingsError,
        r"person must be x,y .* \(4 numbers for 2 videos\); got 6 numbers",
        [good, good],
        _rig(2),
        VideoSettings(person=(1, 2, 3, 4, 5, 6)),
    )
    still = np.repeat(_background()[None], 12, 0)
    write_video(tmp_path / "still.avi", still, 25)
    msg = _raises(
        RegistrationError,
        r"still\.avi: no person found in any of the 12 frames",
        [tmp_path / "still.avi"],
    )
    assert "--person" in msg
    with pytest.raises(VideoSettingsError, match=r"^VideoSettings: width must be"):
        VideoSettings(width=2)
    with pytest.raises(VideoSettingsError, match=r"canny_low must be <= canny_high"):
        VideoSettings(canny_low=0.5, canny_high=0.2)
    with pytest.raises(VideoError, match=r"background must be"):
        VideoSettings(background="knn")
    assert VideoSettings(person=[1, 2]).person == (1.0, 2.0)


@requires_shared_data()
@pytest.mark.shared_data
def test_the_outdoor_video_shows_a_person_on_the_box():
    """sports2d's demo, first 30 frames at width 320 without a calibration: a person is found
    in most frames, the size of a person at that distance, on the box top (upper left), the
    one person in view then (jumping jacks; inspected by eye: head, torso and arms segmented,
    the dark shorts against the dark tree partly missed)."""
    vi = features_from_videos(
        [SHARED_DATA / "video" / "sports2d_demo" / "demo.mp4"],
        None,
        VideoSettings(width=320, count=30),
    )
    sil = vi.features.observation.silhouette[0, :, 0].numpy() > 0.5
    assert sil.shape == (30, 180, 320) and vi.features.frame_rate == 30.0
    area = sil.reshape(30, -1).sum(1)
    assert (area > 50).sum() >= 27, area
    ys, xs = np.nonzero(sil.any(0))
    assert 90 < xs.mean() < 150 and 5 < ys.mean() < 70, (xs.mean(), ys.mean())
    assert np.median(area) < 0.05 * 320 * 180
    assert "focal length was assumed" in vi.note


@requires_shared_data()
@pytest.mark.shared_data
def test_person_picks_the_man_on_the_box_while_a_woman_walks_by():
    """Frames 60-89 of sports2d's demo have two people in view: by default the largest (the
    woman walking on the lawn, right) is followed; person= a point on the man on the box
    (original pixels) follows him instead."""
    path = SHARED_DATA / "video" / "sports2d_demo" / "demo.mp4"
    centres = []
    for person in (None, (635.0, 250.0)):
        st = VideoSettings(start=60, count=30, person=person, colour=False)
        sil = features_from_videos([path], None, st).features.observation.silhouette[0, :, 0]
        assert (sil.flatten(1).sum(1) > 50).all()
        ys, xs = np.nonzero(sil.numpy().any(0))
        centres.append((xs.mean(), ys.mean()))
    (wx, wy), (mx, my) = centres
    assert wx > 200 and wy > 90, centres  # the woman: right, on the lawn
    assert 90 < mx < 150 and my < 70, centres  # the man: on the box, upper left
