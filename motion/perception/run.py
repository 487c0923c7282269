"""Run a person detector over videos, writing what it finds as files registration reads.

Per camera the detections go to a folder of OpenPose-format JSON (one file per frame of the
whole video, as :func:`motion.registration.keypoints.read_openpose_people` reads them:
``{"people": [{"pose_keypoints_2d": [u, v, c, ...]}]}`` in the video's own pixels, an empty
``people`` list for a frame not detected or not kept) and the person masks to
``<camera>_masks.npz`` (the frames detected and their masks, uint8 0-255 at the detection
size). A ``manifest.json`` names the videos (path, size, modification time), the frames and
the settings; a later run with the same ones reuses the files instead of detecting again.

Shapes: ``F`` frames detected, ``K`` keypoints, ``h x w`` the detection size (the video
downscaled to :attr:`PerceptionSettings.width`).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import shutil
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from motion.features import VideoError
from motion.perception.detector import PerceptionSettings, PersonDetector, make_detector

__all__ = ["CameraDetections", "DetectionRun", "detect_videos", "masks_at", "read_masks"]

MANIFEST = "manifest.json"
#: the manifest's layout version (a change makes older caches be detected again)
_LAYOUT = 2

Progress = Callable[[Iterable, str, int], Iterator]


@dataclass(frozen=True)
class CameraDetections:
    """One camera's detections as written.

    Attributes:
        video: the video file.
        folder: its OpenPose-format JSON folder (one file per video frame).
        masks: its ``.npz`` of masks (``None``: the detector gives none).
        frames_total: the files written (the video's frame count).
        detected: the kept frames in which a person was found.
        size: the video's frames, ``(width, height)`` pixels.
    """

    video: Path
    folder: Path
    masks: Path | None
    frames_total: int
    detected: int
    size: tuple[int, int]


@dataclass(frozen=True)
class DetectionRun:
    """What :func:`detect_videos` did.

    Attributes:
        detector: the detector's name and version.
        keypoint_set, spec: its keypoint set and keypoint spec (for
            :func:`motion.registration.keypoints.attach_keypoints`).
        cameras: per camera, in the videos' order.
        frames: the video frames detected (the same in every camera).
        seconds: time spent detecting (decoding included; 0 when reused).
        reused: the files of an earlier run with the same inputs were used.
    """

    detector: str
    keypoint_set: str
    spec: str
    cameras: list[CameraDetections]
    frames: list[int]
    seconds: float
    reused: bool

    @property
    def frames_per_second(self) -> float | None:
        """Frames detected per second over all cameras (``None`` when reused)."""
        n = len(self.frames) * len(self.cameras)
        return None if self.reused or self.seconds <= 0 else n / self.seconds

    def summary(self) -> dict:
        """Plain data for ``summary.json``."""
        return {
            "detector": self.detector,
            "frames_per_second": self.frames_per_second,
            "seconds": self.seconds,
            "reused": self.reused,
            "frames": len(self.frames),
            "detected": {c.video.name: c.detected for c in self.cameras},
        }


def _video_key(path: Path) -> dict:
    st = path.stat()
    return {"path": str(path.resolve()), "bytes": st.st_size, "mtime_ns": st.st_mtime_ns}


def _manifest(
    detector: PersonDetector, paths: list[Path], frames: list[int], settings: PerceptionSettings
) -> dict:
    chosen = dataclasses.asdict(settings)
    chosen.pop("cache")
    return {
        "layout": _LAYOUT,
        "detector": type(detector).version,
        "settings": chosen,
        "videos": [_video_key(p) for p in paths],
        "frames": frames,
    }


def _camera_names(paths: list[Path]) -> list[str]:
    return [f"{i + 1:02d}_{p.stem}" for i, p in enumerate(paths)]


def _cameras_written(
    out: Path, paths: list[Path], detector: PersonDetector, manifest: dict
) -> list[CameraDetections] | None:
    """The cameras of an earlier run with this ``manifest``, or ``None``."""
    try:
        written = json.loads((out / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    if written.get("key") != manifest:
        return None
    cams = []
    for path, name, counts in zip(
        paths, _camera_names(paths), written.get("cameras", []), strict=False
    ):
        folder = out / f"{name}_json"
        masks = out / f"{name}_masks.npz" if type(detector).gives_mask else None
        if not folder.is_dir() or (masks is not None and not masks.is_file()):
            return None
        cams.append(
            CameraDetections(
                path, folder, masks, counts["files"], counts["detected"], tuple(counts["size"])
            )
        )
    return cams if len(cams) == len(paths) else None


def _frame_count(path: Path) -> int:
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise VideoError(f"{path}: cannot be opened as a video")
        return int(max(cap.get(cv2.CAP_PROP_FRAME_COUNT), 0))
    finally:
        cap.release()


def _kept_frames(path: Path, frames: list[int]) -> Iterator[tuple[int, np.ndarray]]:
    """``(frame index, BGR frame)`` of the ``frames`` (sorted) of the video, decoding through."""
    wanted = set(frames)
    cap = cv2.VideoCapture(str(path))
    try:
        i = 0
        while i <= frames[-1] and cap.grab():
            if i in wanted:
                ok, image = cap.retrieve()
                if ok:
                    yield i, image
            i += 1
    finally:
        cap.release()


def _json_text(keypoints: np.ndarray | None) -> str:
    people = []
    if keypoints is not None:
        flat = [round(float(x), 3) for x in keypoints.reshape(-1)]
        people.append({"person_id": [-1], "pose_keypoints_2d": flat})
    return json.dumps({"version": 1.3, "people": people})


def _detect_camera(
    detector: PersonDetector,
    path: Path,
    frames: list[int],
    width: int,
    bar: Progress,
) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray], int]:
    """Keypoints (video pixels) and masks per detected frame, and the video's frame count."""
    total = max(_frame_count(path), frames[-1] + 1)
    detector.reset()
    keypoints: dict[int, np.ndarray] = {}
    masks: dict[int, np.ndarray] = {}
    for index, bgr in bar(_kept_frames(path, frames), f"detect {path.stem}", len(frames)):
        h, w = bgr.shape[:2]
        s = min(1.0, width / w)
        if s < 1.0:
            bgr = cv2.resize(bgr, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
        found = detector.detect(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        if not found:
            continue
        person = found[0]
        kp = person.keypoints.copy()
        kp[:, :2] = (kp[:, :2] + 0.5) / s - 0.5  # detection pixels -> the video's
        keypoints[index] = kp
        if person.mask is not None:
            masks[index] = np.rint(person.mask * 255).astype(np.uint8)
    return keypoints, masks, total


def _write_camera(
    folder: Path,
    stem: str,
    total: int,
    keypoints: dict[int, np.ndarray],
    masks: dict[int, np.ndarray],
    mask_path: Path | None,
    frames: list[int],
    size: tuple[int, int],
) -> None:
    folder.mkdir(parents=True)
    for i in range(total):
        (folder / f"{stem}.{i:06d}.json").write_text(_json_text(keypoints.get(i)))
    if mask_path is not None:
        h, w = size
        stack = np.zeros((len(frames), h, w), dtype=np.uint8)
        for j, f in enumerate(frames):
            if f in masks:
                stack[j] = masks[f]
        np.savez_compressed(mask_path, frames=np.asarray(frames), masks=stack)


def _sizes(path: Path, width: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """The video's frame size ``(width, height)`` and the detection's ``(height, width)``."""
    cap = cv2.VideoCapture(str(path))
    try:
        w = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        h = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    finally:
        cap.release()
    s = min(1.0, width / max(w, 1))
    return (w, h), ((round(h * s), round(w * s)) if s < 1.0 else (h, w))


def _no_bar(items: Iterable, desc: str, total: int) -> Iterator:
    return iter(items)


def detect_videos(
    paths: Sequence[str | Path],
    out: str | Path,
    frames: Sequence[int],
    settings: PerceptionSettings | None = None,
    *,
    detector: PersonDetector | None = None,
    progress: Progress | None = None,
) -> DetectionRun:
    """Detect the person in the ``frames`` of each video and write them under ``out``.

    Args:
        paths: one video per camera.
        out: the detections folder (created; its earlier files are replaced unless they
            are reused).
        frames: the video frames to detect (0-based, increasing; the same in every video).
        settings: :class:`PerceptionSettings` (default: its defaults).
        detector: the detector to use (default: :func:`make_detector` of ``settings``).
        progress: ``(items, description, total) -> items``, for a progress bar.

    Returns:
        :class:`DetectionRun`.

    Raises:
        DetectorUnavailable: the detector's package is not installed.
        VideoError: a video that cannot be opened, or no frames asked for.
    """
    settings = PerceptionSettings() if settings is None else settings
    paths = [Path(p) for p in paths]
    frames = [int(f) for f in frames]
    if not frames or any(b <= a for a, b in itertools.pairwise(frames)) or frames[0] < 0:
        raise VideoError(f"detect_videos needs increasing frame indices >= 0; got {frames[:5]}...")
    out = Path(out)
    owned = detector is None
    detector = make_detector(settings) if detector is None else detector
    bar = progress or _no_bar
    try:
        manifest = _manifest(detector, paths, frames, settings)
        if settings.cache:
            cams = _cameras_written(out, paths, detector, manifest)
            if cams is not None:
                return _run(detector, cams, frames, 0.0, True)
        if out.exists():
            shutil.rmtree(out)
        out.mkdir(parents=True)
        cams, counts = [], []
        start = time.perf_counter()
        for path, name in zip(paths, _camera_names(paths), strict=True):
            folder = out / f"{name}_json"
            keypoints, masks, total = _detect_camera(detector, path, frames, settings.width, bar)
            mask_path = out / f"{name}_masks.npz" if type(detector).gives_mask else None
            native, size = _sizes(path, settings.width)
            _write_camera(folder, path.stem, total, keypoints, masks, mask_path, frames, size)
            cams.append(CameraDetections(path, folder, mask_path, total, len(keypoints), native))
            counts.append({"files": total, "detected": len(keypoints), "size": native})
        seconds = time.perf_counter() - start
        (out / MANIFEST).write_text(json.dumps({"key": manifest, "cameras": counts}, indent=1))
        return _run(detector, cams, frames, seconds, False)
    finally:
        if owned:
            detector.close()


def _run(
    detector: PersonDetector,
    cams: list[CameraDetections],
    frames: list[int],
    seconds: float,
    reused: bool,
) -> DetectionRun:
    kind = type(detector)
    return DetectionRun(kind.version, kind.keypoint_set, kind.spec, cams, frames, seconds, reused)


def masks_at(cam: CameraDetections, frames: Sequence[int], scale: float, size: tuple[int, int]):
    """A camera's masks of the video ``frames`` at the working size: the video's frames
    resized by ``scale`` (as :func:`motion.features.read_video` rounds it), padded on the
    right and bottom to ``size = (W, H)``. Returns ``(T', H, W)`` float32 and ``(T',)`` bool
    (the frames with a mask of a detected person)."""
    w, h = size
    out = np.zeros((len(frames), h, w), dtype=np.float32)
    found = np.zeros(len(frames), dtype=bool)
    if cam.masks is None:
        return out, found
    have, masks = read_masks(cam.masks)
    row = {int(f): i for i, f in enumerate(have)}
    scaled = (round(cam.size[0] * scale), round(cam.size[1] * scale))
    for t, f in enumerate(frames):
        i = row.get(int(f))
        if i is None or not masks[i].any():
            continue
        m = cv2.resize(masks[i], scaled, interpolation=cv2.INTER_AREA)
        hh, ww = min(h, m.shape[0]), min(w, m.shape[1])
        out[t, :hh, :ww] = m[:hh, :ww]
        found[t] = True
    return out, found


def read_masks(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A camera's masks file: the frames ``(F,)`` int and their masks ``(F, h, w)`` float32
    in [0, 1]."""
    with np.load(path) as data:
        return data["frames"].astype(np.int64), data["masks"].astype(np.float32) / 255
