"""Registration inputs from real videos: static cameras' files -> :class:`VideoFeatures`.

Each video is decoded at a working width (frames downscaled for speed, the cameras' ``K`` and
image size scaled with them), the person is segmented by background subtraction and followed
through the frames (the largest moving region, or the one nearest a point the user gives),
and the features the registration scores are built as :func:`motion.registration.inputs.
features_from_sequence` builds them for a synthetic sequence: silhouettes, the distance to
the edges around the person, and the colour frames.

Without a calibration a single video gets :func:`default_camera`: an uncalibrated pinhole at
the world origin with a nominal field of view (:data:`FIELD_OF_VIEW_DEG`); several videos
need a calibration (:func:`motion.cameras.load_pose2sim_calibration`), its cameras in the
order of the videos.

Conventions: pixels ``(u, v)``, ``u`` right, ``v`` down, integer coordinates at pixel
centres (OpenCV's, as :mod:`motion.cameras`); a resize by ``s`` maps ``u`` to
``(u + 0.5) s - 0.5``. Shapes: ``T'`` video frames kept, ``C`` cameras, ``H x W`` the working
image size (the same for every camera: smaller frames are padded on the right and bottom).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np
import torch

from motion.body.observation import Observation
from motion.cameras import CameraRig, resized_rig
from motion.features import (
    BACKGROUND_SUFFIX,
    MOG2_FOREGROUND,
    MOG2_SHADOW,
    VideoError,
    clean_foreground,
    distance_to_edges,
    edges,
    foreground_masks,
    median_coverage,
    read_camera_videos,
    track_person,
)
from motion.registration.inputs import NO_EDGE_PX
from motion.registration.types import RegistrationError, VideoFeatures
from motion.settings import SettingError, Settings, coerce, setting, show

__all__ = [
    "FIELD_OF_VIEW_DEG",
    "HELD_SHARE_WARNING",
    "VideoInput",
    "VideoSettings",
    "VideoSettingsError",
    "default_camera",
    "features_from_videos",
    "held_share",
    "plates_beside",
    "with_silhouettes",
]

#: horizontal field of view (degrees) assumed for a video without a calibration: a typical
#: phone or action camera's main lens at 16:9 is 50-70 degrees; the focal length it implies,
#: ``(W / 2) / tan(FOV / 2)``, sets the scale of depth (a wrong guess makes the person nearer
#: or farther and larger or smaller together; joint angles are affected much less).
FIELD_OF_VIEW_DEG = 55.0

#: background subtraction's MOG2 history (frames) and morphological clean-up radii (working
#: pixels): :func:`motion.features.foreground_masks`'s defaults
_HISTORY, _OPEN_PX, _CLOSE_PX = 200, 2, 4

#: frames per chunk when computing edges and distance maps (bounds the float images in memory)
_CHUNK = 64


class VideoSettingsError(SettingError, VideoError):
    """A video setting outside its type or range (a :class:`VideoError` too)."""


@dataclass(frozen=True)
class VideoSettings(Settings):
    """How videos become features. Every field is checked at construction (a bad value
    raises :class:`VideoSettingsError` naming it); ``python -m motion register --help`` can
    list them with :func:`motion.settings.describe`.

    Pixel sizes (``min_area``, ``merge_px``, ``edge_band_px``) are at the working
    resolution; ``person`` is in the original video's pixels.
    """

    setting_error: ClassVar[type[SettingError]] = VideoSettingsError

    width: int | None = setting(
        320,
        "working width in pixels: frames are downscaled so that the widest camera is this "
        "wide (never upscaled), the cameras' intrinsics with them; none: native resolution",
        ge=8,
        le=8192,
    )
    start: int = setting(0, "first video frame read (0-based)", ge=0)
    count: int | None = setting(
        None, "at most this many frames kept (none: to the end of the video)", ge=1
    )
    step: int = setting(1, "keep every step-th frame from start (the frame rate divides)", ge=1)
    background: str = setting(
        "mog2",
        "background subtraction against the median of background_frames: mog2 (OpenCV's "
        "Gaussian mixture started from that median, adapting slowly; shadows count as "
        "background, except those the person's mask encloses: motion.features."
        "clean_foreground) or median (largest channel difference from it)",
        choices=("mog2", "median"),
    )
    background_frames: int = setting(
        50,
        "frames sampled evenly over the whole video (not only the frames kept) whose "
        "per-pixel median is the background: a person who stays in one place during the kept "
        "frames but not all the time is not learnt as background; 0: the kept frames' median",
        ge=0,
        le=10000,
    )
    backgrounds: list[str] | None = setting(
        None,
        "pictures of the empty scene, one per video in their order (image files at the "
        "video's size), subtracted instead of the median of background_frames: needed when "
        "the person covers the same pixels most of the time (walking towards the camera, "
        "balancing in place)",
        min_length=1,
        example="cam1_empty.png,cam2_empty.png",
    )
    find_backgrounds: bool = setting(
        True,
        "without backgrounds, a picture named after each video with _background.png "
        "(cam1.avi -> cam1_background.png, as motion synth writes it) beside it is that "
        "camera's empty scene, when every video has one",
    )
    threshold: float = setting(
        30.0,
        "foreground threshold: MOG2's variance threshold (squared distance in standard "
        "deviations), or the median method's grey-level difference (0-255)",
        gt=0,
    )
    person: list[float] | None = setting(
        None,
        "x,y in the original video's pixels near the person to follow in the first frame "
        "(of the first video; x1,y1,x2,y2,... gives one point per video); none: the largest "
        "moving region. The person is then followed frame to frame",
        min_length=2,
        example="880,510",
    )
    min_area: int = setting(
        50, "smallest foreground region (working pixels, after grouping) taken for a person", ge=1
    )
    merge_px: int = setting(
        8,
        "foreground pieces this close (working pixels) are grouped as one person (a limb "
        "cut off by a background of its colour); 0: connected pixels only",
        ge=0,
        le=100,
    )
    edge_band_px: int = setting(
        6,
        "edges count only within this distance (working pixels) of the person's silhouette "
        "(others' and the background's edges are clutter)",
        ge=0,
        le=1000,
    )
    canny_low: float = setting(
        0.1, "Canny's low hysteresis threshold on the gradient of the [0, 1] image", gt=0
    )
    canny_high: float = setting(0.2, "Canny's high threshold (>= canny_low)", gt=0)
    frame_rate: float | None = setting(
        None,
        "frames per second of the videos (none: read from the files, which must agree)",
        gt=0,
        le=10000,
    )
    colour: bool = setting(
        True, "keep the colour frames as the observation's image (4 bytes per pixel channel)"
    )
    truncated: str = setting(
        "error",
        "a video that stops decoding before the frames its file declares (cut short or "
        "corrupt): error (stop, naming the file and its last good frame) or keep "
        "(register the frames up to it, with a warning)",
        choices=("error", "keep"),
    )

    def validate(self) -> None:
        """Check (and normalise) every field, then ``canny_low <= canny_high`` and an even
        number of ``person`` values; ``person`` is stored as a tuple."""
        name = type(self).__name__
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, tuple):
                value = list(value)
            object.__setattr__(self, f.name, coerce(type(self), f.name, value, name))
        if self.canny_low > self.canny_high:
            raise VideoSettingsError(
                f"{name}: canny_low must be <= canny_high; got {show(self.canny_low)} > "
                f"{show(self.canny_high)}"
            )
        if self.person is not None:
            if len(self.person) % 2:
                raise VideoSettingsError(
                    f"{name}: person must be x,y (or x,y per video); got {show(self.person)}"
                )
            object.__setattr__(self, "person", tuple(self.person))


@dataclass
class VideoInput:
    """Videos read for registration, with what the overlay and report need.

    Attributes:
        features: the registration input (:class:`VideoFeatures`, cameras scaled to the
            working size).
        frames: per camera ``(T', H, W, 3)`` uint8 RGB at the working size (the frames the
            features were computed on).
        scale: the working size over the original (the same for every camera; a camera
            narrower than the widest is padded on the right and bottom, not stretched).
        note: what was assumed, for the report ("" when nothing was): an uncalibrated
            camera's focal length, padding.
        paths: the videos, one per camera.
        start, step: the first frame of the files kept and the step between kept frames
            (frame ``i`` of the features is frame ``start + i * step`` of the files).
        warnings: sentences for the user about the input (a video cut short and kept).
        held: the videos whose background, a median of their frames, holds the person
            (:data:`HELD_SHARE_WARNING`; each has a warning): their silhouettes miss parts
            of the body.
    """

    features: VideoFeatures
    frames: list[np.ndarray]
    scale: float
    note: str
    paths: list[Path]
    start: int = 0
    step: int = 1
    warnings: list[str] = field(default_factory=list)
    held: list[Path] = field(default_factory=list)


def default_camera(
    width: float, height: float, fov_deg: float = FIELD_OF_VIEW_DEG, name: str = "camera"
) -> CameraRig:
    """An uncalibrated pinhole for a ``width x height`` video: horizontal field of view
    ``fov_deg`` (``f = (width / 2) / tan(fov / 2)``, square pixels), principal point at the
    image centre ``((width - 1) / 2, (height - 1) / 2)``, no distortion, ``R = I``, ``t = 0``
    (the world is the camera frame: x right, y down, z forward). One camera, float64."""
    if not (width >= 1 and height >= 1):
        raise VideoError(
            f"default_camera needs a size of at least 1 x 1 px; got {width} x {height}"
        )
    if not 0 < fov_deg < 180:
        raise VideoError(f"default_camera: fov_deg must be in (0, 180); got {fov_deg}")
    f = (width / 2) / math.tan(math.radians(fov_deg) / 2)
    k = torch.tensor(
        [[[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]]],
        dtype=torch.float64,
    )
    return CameraRig(
        k,
        torch.eye(3, dtype=torch.float64)[None],
        torch.zeros(1, 3, dtype=torch.float64),
        torch.zeros(1, 5, dtype=torch.float64),
        torch.tensor([[float(width), float(height)]], dtype=torch.float64),
        [name],
    )


@dataclass(frozen=True)
class _Probe:
    fps: float  # as the container says (0: unknown)
    frames: int  # as the container says (0: unknown)
    width: int  # of the decoded frames (rotation metadata applied, as read_video sees them)
    height: int


def _probe(path: Path) -> _Probe:
    """Frame rate and count from the container, the size from the first decoded frame."""
    if not path.is_file():
        raise VideoError(f"{path}: no such video file")
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise VideoError(f"{path}: OpenCV cannot open this video (not a video file?)")
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        frames = int(max(cap.get(cv2.CAP_PROP_FRAME_COUNT), 0))
        ok, frame = cap.read()
        if not ok:
            raise VideoError(f"{path}: the video has no frames")
    finally:
        cap.release()
    height, width = frame.shape[:2]
    return _Probe(fps if math.isfinite(fps) else 0.0, frames, width, height)


def _listing(paths: list[Path], values) -> str:
    return ", ".join(f"{p.name}: {v}" for p, v in zip(paths, values, strict=True))


def _check_probes(paths: list[Path], probes: list[_Probe], settings: VideoSettings) -> float:
    """Frame counts that agree and the frame rate (the files', which must agree, unless
    ``settings.frame_rate`` overrides it)."""
    counts = [pr.frames for pr in probes]
    if all(counts) and len(set(counts)) > 1:
        raise VideoError(
            f"videos have different frame counts ({_listing(paths, counts)}); synchronised "
            "cameras must have the same frames (trim them to the same span)"
        )
    if settings.frame_rate is not None:
        return settings.frame_rate
    for p, pr in zip(paths, probes, strict=True):
        if not pr.fps > 0:
            raise VideoError(f"{p}: the file does not say its frame rate; give it (frame_rate=...)")
    rates = [pr.fps for pr in probes]
    if max(rates) - min(rates) > 1e-3 * max(rates):
        raise VideoError(
            f"videos have different frame rates ({_listing(paths, [f'{r:g} fps' for r in rates])}); "
            "synchronised cameras must have the same rate"
        )
    return rates[0]


#: frames by which decoding may fall short of a container's declared count before the video
#: counts as cut short: some containers estimate the count from duration x rate
TRUNCATION_SLACK_FRAMES = 2


def _check_truncation(
    paths: list[Path], probes: list[_Probe], decoded: int, settings: VideoSettings
) -> list[str]:
    """A video whose kept frames stop before those its container declares (more than
    :data:`TRUNCATION_SLACK_FRAMES` short) was cut or is corrupt there: a :class:`VideoError`
    naming the file and its last good frame, or with ``settings.truncated == "keep"`` a
    warning (returned) and the frames decoded. Videos that do not declare a count pass."""
    declared = [pr.frames for pr in probes]
    if not all(declared):
        return []
    expected = len(range(settings.start, min(declared), settings.step))
    if settings.count is not None:
        expected = min(expected, settings.count)
    if decoded >= expected - TRUNCATION_SLACK_FRAMES:
        return []
    path = paths[declared.index(min(declared))] if len(paths) > 1 else paths[0]
    last = settings.start + settings.step * (decoded - 1)
    what = (
        f"{path}: the video stops decoding after frame {last} (0-based) but its file declares "
        f"{min(declared)} frames: it is cut short or corrupt from frame {last + 1}"
    )
    if settings.truncated == "error":
        raise VideoError(
            f"{what}; repair or re-export it, or register the frames up to {last} with "
            "video.truncated=keep"
        )
    return [f"{what}; only the frames up to {last} were registered"]


def _check_cameras(paths: list[Path], cameras: CameraRig | None) -> None:
    if cameras is None:
        if len(paths) > 1:
            raise RegistrationError(
                f"{len(paths)} videos ({', '.join(p.name for p in paths)}) but no calibration: "
                "several cameras need a calibration (a Pose2Sim TOML, its cameras in the "
                "order of the videos)"
            )
        return
    if not isinstance(cameras, CameraRig):
        raise RegistrationError(
            f"cameras must be a motion.cameras.CameraRig or None; got {type(cameras).__name__}"
        )
    if cameras.orthographic:
        raise RegistrationError(
            "cameras must be pinhole cameras for video; got an orthographic rig"
        )
    if cameras.num_cameras != len(paths):
        raise RegistrationError(
            f"the calibration has {cameras.num_cameras} camera(s) ({', '.join(cameras.names)}) "
            f"but {len(paths)} video(s) were given ({', '.join(p.name for p in paths)}); give "
            "one video per calibrated camera, in the calibration's order"
        )


def _pad(frames: np.ndarray, height: int, width: int) -> np.ndarray:
    """``(T, h, w, ...)`` -> ``(T, height, width, ...)`` on the right and bottom: images with
    their last row and column repeated (no edge at the seam), masks with False."""
    h, w = frames.shape[1:3]
    if (h, w) == (height, width):
        return frames
    pad = [(0, 0), (0, height - h), (0, width - w)] + [(0, 0)] * (frames.ndim - 3)
    if frames.dtype == bool:
        return np.pad(frames, pad, constant_values=False)
    return np.pad(frames, pad, mode="edge")


def _check_person(settings: VideoSettings, paths: list[Path], probes: list[_Probe]) -> None:
    """``person``: 2 numbers or 2 per video, each point inside its video's frame."""
    person = settings.person
    if person is None:
        return
    c = len(paths)
    if len(person) not in (2, 2 * c):
        raise VideoSettingsError(
            f"person must be x,y (the first video) or one x,y per video ({2 * c} numbers for "
            f"{c} videos); got {len(person)} numbers"
        )
    for i in range(len(person) // 2):
        x, y = person[2 * i], person[2 * i + 1]
        pr = probes[i]
        if not (-0.5 <= x <= pr.width - 0.5 and -0.5 <= y <= pr.height - 0.5):
            raise VideoError(
                f"{paths[i]}: person ({x:g}, {y:g}) is outside the {pr.width} x {pr.height} px "
                "frame (give x,y in the original video's pixels)"
            )


def _person_points(
    settings: VideoSettings, probes: list[_Probe], scaled
) -> list[tuple[float, float] | None]:
    """Each camera's start point for :func:`track_person`, in working pixels (checked by
    :func:`_check_person`)."""
    points: list[tuple[float, float] | None] = [None] * len(probes)
    person = settings.person or ()
    for i in range(len(person) // 2):
        x, y = person[2 * i], person[2 * i + 1]
        sx, sy = scaled[i][0] / probes[i].width, scaled[i][1] / probes[i].height
        points[i] = ((x + 0.5) * sx - 0.5, (y + 0.5) * sy - 0.5)
    return points


def _follow(
    masks: np.ndarray, start: tuple[float, float] | None, settings: VideoSettings
) -> np.ndarray:
    """The tracked person's pixels: components grouped within ``merge_px`` (dilated for the
    choice, the foreground's own pixels kept). ``(T, H, W)`` bool -> the same."""
    grouped = masks
    if settings.merge_px:
        r = settings.merge_px
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)
        grouped = np.stack([cv2.dilate(m.astype(np.uint8), kernel) > 0 for m in masks])
    return track_person(grouped, start=start, min_area=settings.min_area) & masks


#: files with more frames than this are sampled for the background by seeking (each seek
#: decodes from a key frame), shorter ones by decoding through (exact, but its cost grows
#: with the file's length, hence the bound)
_SEEK_BEYOND = 3000


def _background_sample(path: Path, total: int, n: int, size: tuple[int, int]) -> np.ndarray:
    """``n`` frames spread evenly over the whole file (``total`` frames, 0: unknown), resized
    to ``size = (W, H)`` as :func:`motion.features.read_video` resizes: ``(n', H, W, 3)`` uint8
    RGB (``n' <= n``; empty if the file gives none)."""
    cap = cv2.VideoCapture(str(path))
    out: list[np.ndarray] = []

    def keep(frame):
        if (frame.shape[1], frame.shape[0]) != size:
            frame = cv2.resize(frame, size, interpolation=cv2.INTER_AREA)
        out.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))

    try:
        if total > _SEEK_BEYOND:
            for i in np.linspace(0, total - 1, n).round().astype(int):
                cap.set(cv2.CAP_PROP_POS_FRAMES, int(i))
                ok, frame = cap.read()
                if ok:
                    keep(frame)
        else:
            if total > 0:
                wanted = set(np.linspace(0, total - 1, n).round().astype(int).tolist())
            else:  # unknown length: every frame (then thinned)
                wanted = None
            i = 0
            while cap.grab():
                if wanted is None or i in wanted:
                    ok, frame = cap.retrieve()
                    if ok:
                        keep(frame)
                i += 1
    finally:
        cap.release()
    if not out:
        return np.zeros((0, size[1], size[0], 3), dtype=np.uint8)
    sample = np.stack(out)
    if len(sample) > n:
        sample = sample[np.linspace(0, len(sample) - 1, n).round().astype(int)]
    return sample


def _foreground(frames: np.ndarray, background: np.ndarray, settings: VideoSettings) -> np.ndarray:
    """:func:`motion.features.foreground_masks` with a given background image ``(H, W, 3)``
    uint8 instead of the frames' own median (MOG2 is started from it, then adapts slowly;
    the median method differences against it). ``(T, H, W, 3)`` -> ``(T, H, W)`` bool."""
    history = _HISTORY
    if settings.background == "mog2":
        sub = cv2.createBackgroundSubtractorMOG2(
            history=history, varThreshold=settings.threshold, detectShadows=True
        )
        boot = min(history, 30)
        for _ in range(boot):
            sub.apply(background, learningRate=1.0 / boot)
        # adapt slowly enough that a person in view at one place through all the frames is
        # not learnt as background (MOG2 counts a mode as background once the modes before it
        # hold less than 90 % of the weight: ~0.1 / rate frames)
        rate = min(1.0 / history, 0.05 / max(len(frames), 1))
        labels = np.stack([sub.apply(f, learningRate=rate) for f in frames])
        return clean_foreground(
            labels == MOG2_FOREGROUND, labels == MOG2_SHADOW, _OPEN_PX, _CLOSE_PX
        )
    diff = np.abs(frames.astype(np.int16) - background.astype(np.int16)).max(-1)
    return clean_foreground(diff > settings.threshold, None, _OPEN_PX, _CLOSE_PX)


def plates_beside(paths: list[Path]) -> list[Path] | None:
    """The clean plate beside each video (``<stem>`` + :data:`motion.features.
    BACKGROUND_SUFFIX`), or ``None`` unless every video has one."""
    found = [path.with_name(path.stem + BACKGROUND_SUFFIX) for path in paths]
    return found if all(p.is_file() for p in found) else None


def _check_backgrounds(
    settings: VideoSettings, paths: list[Path], probes: list[_Probe]
) -> tuple[list, str]:
    """The clean plates of ``settings.backgrounds`` (or, with ``find_backgrounds``, those
    beside the videos: :func:`plates_beside`) as ``(H, W, 3)`` uint8 RGB at each video's size
    (``None`` per camera when there are none), and a note naming the plates found (``""``
    when given or none)."""
    names, note, found = settings.backgrounds, "", False
    if names is None and settings.find_backgrounds:
        beside = plates_beside(paths)
        found = beside is not None
        if found:
            names = [str(p) for p in beside]
            note = (
                "background: the picture of the empty scene beside each video ("
                + ", ".join(p.name for p in beside)
                + "), found by its name (video.find_backgrounds=false: learnt from the video)"
            )
    if names is None:
        return [None] * len(paths), note
    if len(names) != len(paths):
        raise VideoSettingsError(
            f"backgrounds must name one picture per video ({len(paths)}); got {len(names)}"
        )
    # a plate the user did not name says where it came from and how to leave it out
    origin = (
        " (found beside the video by its name; video.find_backgrounds=false ignores it)"
        if found
        else ""
    )
    plates = []
    for name, path, pr in zip(names, paths, probes, strict=True):
        image = cv2.imread(name, cv2.IMREAD_COLOR) if Path(name).is_file() else None
        if image is None:
            raise VideoError(
                f"{name}: not an image file OpenCV can read (background of {path}){origin}"
            )
        if image.shape[:2] != (pr.height, pr.width):
            raise VideoError(
                f"{name}: the background is {image.shape[1]} x {image.shape[0]} px but "
                f"{path.name}'s frames are {pr.width} x {pr.height}{origin}"
            )
        plates.append(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
    return plates, note


def _foreground_of(
    path: Path, video: np.ndarray, probe: _Probe, settings: VideoSettings, plate=None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The foreground of the kept frames ``video``, against the clean ``plate`` (native
    size) if given, else a background from frames of the whole file
    (``settings.background_frames``) or, with 0, the kept frames' own median; and, for a
    median, the pixels where it holds the person rather than the scene
    (:func:`_median_holds`; ``None`` with a plate)."""
    size = (video.shape[2], video.shape[1])
    if plate is not None:
        if (plate.shape[1], plate.shape[0]) != size:
            plate = cv2.resize(plate, size, interpolation=cv2.INTER_AREA)
        return _foreground(video, plate, settings), None
    if settings.background_frames == 0:
        fg = foreground_masks(
            video, settings.background, settings.threshold, _HISTORY, _OPEN_PX, _CLOSE_PX
        )
        return fg, _median_holds(video, np.median(video, axis=0).astype(np.uint8))
    sample = _background_sample(path, probe.frames, settings.background_frames, size)
    if len(sample) == 0:
        sample = video
    background = np.median(sample, axis=0).astype(np.uint8)
    return _foreground(video, background, settings), _median_holds(sample, background)


#: grey levels by which a frame differs from the median where :func:`_median_holds` counts a
#: moving body (the median method's own default threshold)
_HELD_GREY = 30.0
#: a temporal median is the person's colour, not the scene's, at pixels the person covers in
#: at least half of the frames (the median's breakdown point)
_HELD_COVERAGE = 0.5
#: the warning of :func:`_held_warning` is given when on average at least this share of the
#: person's bounding box lies where the median holds them: walking straight toward a camera
#: (the rendered CMU students, 0.21-0.50 of the box, whose median silhouettes reach IoU
#: 0.41-0.49 with the truth against 0.78-0.84 with the clean plate) or balancing in place (the
#: Pose2Sim trial, 0.11-0.75 by camera), not crossing its view (the Sports2D walker and the
#: rendered students crossing, 0.00: docs/experiments.md, "Walking toward the camera")
HELD_SHARE_WARNING = 0.2


def _median_holds(frames: np.ndarray, background: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: where the median ``background`` of ``frames`` is the person's colour
    (:func:`motion.features.median_coverage` at least :data:`_HELD_COVERAGE`)."""
    coverage = median_coverage(frames, background, _HELD_GREY, _OPEN_PX, _CLOSE_PX)
    return coverage >= _HELD_COVERAGE


def held_share(person: np.ndarray, held: np.ndarray) -> float:
    """The mean over the frames with a person (``person`` ``(T, H, W)`` bool) of the share of
    their bounding box on ``held`` ``(H, W)`` pixels (0 when no frame has a person)."""
    shares = []
    for mask in person:
        rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
        if len(rows):
            box = held[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
            shares.append(float(box.mean()))
    return float(np.mean(shares)) if shares else 0.0


def _held_warning(path: Path, share: float) -> str:
    return (
        f"{path.name}: the person stays over the same pixels in most of the frames the "
        f"background was learnt from ({100 * share:.0f} % of their box, on average, lies "
        "where the median of those frames is the person: walking toward or away from the "
        "camera, or in place), so background subtraction loses them there: wherever the "
        "person detector's mask does not stand in, the silhouettes miss parts of the body, "
        "and the depth, the path and the verdicts read from them are unreliable; a picture "
        "of the empty scene, given with --background or saved beside the video as "
        f"{path.stem}{BACKGROUND_SUFFIX}, gives clean ones"
    )


def _edge_distances(frames: np.ndarray, person: np.ndarray, settings: VideoSettings) -> np.ndarray:
    """Distance (px) to the image's Canny edges within ``edge_band_px`` of the person, with
    :data:`NO_EDGE_PX` where a frame has none. ``(T, H, W, 3)`` uint8, ``(T, H, W)`` bool ->
    ``(T, H, W)`` float32."""
    t, h, w = person.shape
    out = np.empty((t, h, w), dtype=np.float32)
    r = settings.edge_band_px
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)
    for s in range(0, t, _CHUNK):
        sl = slice(s, min(s + _CHUNK, t))
        rgb = torch.from_numpy(frames[sl]).permute(0, 3, 1, 2).float() / 255
        e = edges(rgb, settings.canny_low, settings.canny_high)[:, 0].numpy()
        band = np.stack([cv2.dilate(m.astype(np.uint8), kernel) > 0 for m in person[sl]])
        dist = distance_to_edges(torch.from_numpy(e & band)[:, None])[:, 0]
        dist = torch.where(torch.isfinite(dist), dist, torch.full_like(dist, NO_EDGE_PX))
        out[sl] = dist.numpy()
    return out


def features_from_videos(
    paths, cameras: CameraRig | None = None, settings: VideoSettings | None = None
) -> VideoInput:
    """Read synchronised videos of static cameras as registration input.

    Args:
        paths: one video per camera (a list; a single path is one camera), in the order of
            the calibration's cameras.
        cameras: the calibration (intrinsics in the original videos' pixels), or ``None`` for
            a single uncalibrated video (:func:`default_camera`, noted in the result).
        settings: :class:`VideoSettings` (default: its defaults).

    Returns:
        :class:`VideoInput`: the :class:`VideoFeatures` (silhouettes ``(1, T', C, H, W)``
        float 0/1; edge distances, same shape, pixels; colour images ``(1, T', C, 3, H, W)``
        in [0, 1] unless ``settings.colour`` is false; cameras scaled to the working size;
        frame rate the files' divided by ``step``), the working frames, the scale and a note.

    Raises:
        VideoError: naming the file: missing or unreadable, no frames, frame counts or rates
            that differ between the videos, frame sizes that disagree with the calibration,
            a ``person`` point outside the frame; :class:`VideoSettingsError` for settings.
        RegistrationError: several videos without a calibration, a calibration with another
            number of cameras than videos, or a video in which no person is found.
    """
    if isinstance(paths, str | Path):
        paths = [paths]
    paths = [Path(p) for p in paths]
    if not paths:
        raise VideoError("features_from_videos needs at least one video; got none")
    settings = VideoSettings() if settings is None else settings
    if not isinstance(settings, VideoSettings):
        raise VideoSettingsError(
            f"settings must be VideoSettings or None; got {type(settings).__name__}"
        )
    _check_cameras(paths, cameras)
    probes = [_probe(p) for p in paths]
    rate = _check_probes(paths, probes, settings)
    _check_person(settings, paths, probes)
    plates, plate_note = _check_backgrounds(settings, paths, probes)

    widest = max(pr.width for pr in probes)
    scale = 1.0 if settings.width is None else min(1.0, settings.width / widest)
    videos = read_camera_videos(
        paths,
        expected_sizes=None if cameras is None else cameras.size,
        start=settings.start,
        count=settings.count,
        step=settings.step,
        scale=scale,
    )
    warnings = _check_truncation(paths, probes, len(videos[0]), settings)
    native = [(pr.width, pr.height) for pr in probes]
    scaled = [(v.shape[2], v.shape[1]) for v in videos]
    width, height = max(s[0] for s in scaled), max(s[1] for s in scaled)
    notes = [plate_note] if plate_note else []
    rig = cameras
    if rig is None:
        rig = default_camera(*native[0], name=paths[0].stem)
        notes.append(
            f"{paths[0].name}: no calibration, so the focal length was assumed: a pinhole with "
            f"a {FIELD_OF_VIEW_DEG:g} degree horizontal field of view (f = "
            f"{float(rig.K[0, 0, 0]):.0f} px at {native[0][0]} x {native[0][1]}), principal "
            "point at the centre, the camera at the world origin (y down); distances and "
            "body size scale with the true focal length"
        )
    rig = resized_rig(rig, native, scaled, (width, height))
    starts = _person_points(settings, probes, scaled)

    sils, dists, frames, held_videos = [], [], [], []
    for c, (path, video) in enumerate(zip(paths, videos, strict=True)):
        if scaled[c] != (width, height):
            notes.append(
                f"{path.name}: {scaled[c][0]} x {scaled[c][1]} px at the working scale, padded "
                f"on the right and bottom to {width} x {height}"
            )
        fg, held = _foreground_of(path, video, probes[c], settings, plates[c])
        person = _follow(fg, starts[c], settings)
        if not person.any():
            raise RegistrationError(
                f"{path}: no person found in any of the {len(video)} frames read (nothing "
                f"moving of at least min_area={settings.min_area} working pixels against the "
                "background); the person must move in front of a static camera; point at "
                "them with --person x,y (original pixels) or lower min_area / threshold"
            )
        share = 0.0 if held is None else held_share(person, held)
        if share >= HELD_SHARE_WARNING:
            warnings.append(_held_warning(path, share))
            held_videos.append(path)
        video = _pad(video, height, width)
        person = _pad(person, height, width)
        sils.append(person)
        dists.append(_edge_distances(video, person, settings))
        frames.append(video)

    sil = torch.from_numpy(np.stack(sils, 1)).float()[None]  # (1, T', C, H, W)
    dist = torch.from_numpy(np.stack(dists, 1))[None]
    image = None
    if settings.colour:
        rgb = torch.from_numpy(np.stack(frames, 1)).permute(0, 1, 4, 2, 3)  # (T', C, 3, H, W)
        image = (rgb.float() / 255)[None]
    features = VideoFeatures(
        Observation(sil, dist, image),
        rig,
        rate / settings.step,
        None,
        name=", ".join(p.name for p in paths),
    )
    return VideoInput(
        features,
        frames,
        scale,
        "; ".join(notes),
        paths,
        settings.start,
        settings.step,
        warnings,
        held_videos,
    )


def with_silhouettes(
    video: VideoInput, silhouettes: np.ndarray, settings: VideoSettings | None = None
) -> VideoInput:
    """``video`` with other silhouettes (a fused, soft one: :mod:`motion.perception.fusion`)
    and the edge distances recomputed around them (edges within ``edge_band_px`` of the new
    person, ``silhouettes > 0.5``).

    Args:
        video: as :func:`features_from_videos` made it (its working frames are used).
        silhouettes: ``(T', C, H, W)`` float in [0, 1] at the working size.
        settings: the settings the video was read with (the edge band and Canny's
            thresholds; default: the defaults).
    """
    settings = VideoSettings() if settings is None else settings
    obs = video.features.observation
    expected = tuple(obs.silhouette.shape[1:])
    if silhouettes.shape != expected:
        raise ValueError(f"silhouettes must be {expected} (T', C, H, W); got {silhouettes.shape}")
    person = silhouettes > 0.5
    dists = [
        _edge_distances(frames, person[:, c], settings) for c, frames in enumerate(video.frames)
    ]
    sil = torch.from_numpy(np.clip(silhouettes, 0.0, 1.0).astype(np.float32))[None]
    dist = torch.from_numpy(np.stack(dists, 1))[None]
    obs = dataclasses.replace(obs, silhouette=sil.to(obs.silhouette.dtype), edge_distance=dist)
    features = dataclasses.replace(video.features, observation=obs)
    return dataclasses.replace(video, features=features)
