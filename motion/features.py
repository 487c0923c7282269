"""Image features from video: frames, foreground silhouettes, edges, distance transforms.

Two backends where the design card asks for kornia and speed asks for OpenCV: OpenCV is the
fast, exact CPU path (Canny, ``distanceTransform`` with ``DIST_MASK_PRECISE``), kornia the
differentiable, device-agnostic one (its distance transform is an approximation). Every
function takes ``backend="auto"`` (OpenCV for CPU tensors, kornia otherwise).

Conventions: images are ``(B, 1, H, W)`` float in [0, 1] (or ``(B, 3, H, W)`` RGB), masks
``(B, 1, H, W)`` bool; frames from :func:`read_video` are ``(F, H, W, 3)`` uint8 RGB;
distances are in pixels.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import cv2
import kornia
import numpy as np
import torch
from torch import Tensor

__all__ = [
    "BACKGROUND_SUFFIX",
    "MAX_SCALE",
    "VideoError",
    "clean_foreground",
    "distance_to_edges",
    "edges",
    "foreground_masks",
    "median_coverage",
    "native_stderr_silenced",
    "read_camera_videos",
    "read_video",
    "select_person",
    "track_person",
]


#: a picture of a camera's empty scene (a clean plate) beside its video is named
#: ``<video's name without suffix><BACKGROUND_SUFFIX>`` (``cam1.avi`` -> ``cam1_background.png``):
#: ``motion synth`` writes it so, ``motion register`` finds it so
BACKGROUND_SUFFIX = "_background.png"


class VideoError(ValueError):
    """A video that cannot be used (does not open, has no frames, inconsistent sizes)."""


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """File descriptor 2 to the null device meanwhile: native libraries print there, past
    ``sys.stderr`` (FFmpeg inside OpenCV its complaints about a file, ``moov atom not
    found``; TensorFlow Lite inside MediaPipe its delegate's start-up lines)."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


# Largest accepted resize factor: upscaling beyond this only multiplies memory (a 1080p video
# at scale 8 is 200 MB a frame); features are computed at or below the native resolution.
MAX_SCALE = 8.0


def _whole(value, name: str, path: Path, low: int) -> int:
    """An int (not a bool) >= ``low``, else a :class:`VideoError` naming the argument."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
        raise VideoError(f"{path}: {name} must be a whole number >= {low}; got {value!r}")
    return int(value)


def _check_read_args(path: Path, start, count, step, scale) -> None:
    _whole(start, "start", path, 0)
    _whole(step, "step", path, 1)
    if count is not None:
        if isinstance(count, bool) or not isinstance(count, int | np.integer) or count < 1:
            raise VideoError(
                f"{path}: count must be None (every frame) or a whole number >= 1; got {count!r}"
            )
    if isinstance(scale, bool) or not isinstance(scale, int | float | np.floating):
        raise VideoError(f"{path}: scale must be a number in (0, {MAX_SCALE:g}]; got {scale!r}")
    if not 0 < scale <= MAX_SCALE:
        raise VideoError(f"{path}: scale must be in (0, {MAX_SCALE:g}]; got {scale!r}")


def _resize(frame: np.ndarray, scale: float, path: Path) -> np.ndarray:
    """Area-resize by ``scale``; the result must keep at least one pixel each way."""
    h, w = frame.shape[:2]
    size = (round(w * scale), round(h * scale))
    if min(size) < 1:
        raise VideoError(f"{path}: scale {scale!r} shrinks the {w} x {h} frames to nothing")
    return cv2.resize(frame, size, interpolation=cv2.INTER_AREA)


def _decode(cap, path: Path, start: int, count, step: int, scale: float):
    """The kept frames (RGB, resized) and the number of frames read from ``cap``."""
    frames: list[np.ndarray] = []
    shape = None
    index = 0
    while count is None or len(frames) < count:
        ok, frame = cap.read()
        if not ok:
            break
        if index >= start and (index - start) % step == 0:
            if shape is not None and frame.shape[:2] != shape:
                raise VideoError(
                    f"{path}: frame {index} is {frame.shape[1]} x {frame.shape[0]} px but "
                    f"earlier frames are {shape[1]} x {shape[0]}"
                )
            shape = frame.shape[:2]
            if scale != 1.0:
                frame = _resize(frame, scale, path)
            frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
        index += 1
    return frames, index


def read_video(
    path: str | Path, start: int = 0, count: int | None = None, step: int = 1, scale: float = 1.0
) -> np.ndarray:
    """Decode frames ``start, start + step, ...`` (at most ``count``) as ``(F, H, W, 3)`` uint8 RGB,
    optionally resized by ``scale`` (area interpolation).

    Args:
        path: a video file OpenCV can decode.
        start: first frame index, >= 0.
        count: at most this many frames (>= 1), or None for every frame to the end.
        step: keep every ``step``-th frame, >= 1.
        scale: resize factor in (0, :data:`MAX_SCALE`]; frames keep at least 1 x 1 pixel.

    Raises:
        VideoError: naming the file: an argument out of range, the file does not open, no
            frame at or after ``start`` (with the number of frames the file has), frame sizes
            changing within the file.
    """
    path = Path(path)
    _check_read_args(path, start, count, step, scale)
    if not path.is_file():
        raise VideoError(f"{path}: no such video file")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise VideoError(f"{path}: OpenCV cannot open this video")
    try:
        frames, index = _decode(cap, path, start, count, step, scale)
    finally:
        cap.release()
    if not frames:
        if index == 0:
            raise VideoError(f"{path}: OpenCV decoded no frames from this file")
        raise VideoError(
            f"{path}: no frames at or after frame {start}: the file has {index} frames"
        )
    return np.stack(frames)


def _check_camera_paths(paths) -> list:
    if isinstance(paths, str | Path):
        raise VideoError(
            f"read_camera_videos needs a list of video paths, one per camera; got the single "
            f"path {str(paths)!r}"
        )
    paths = list(paths)
    if not paths:
        raise VideoError("read_camera_videos needs at least one video path; got an empty list")
    return paths


def _check_same_sizes(paths: list, videos: list[np.ndarray]) -> None:
    sizes = [(v.shape[2], v.shape[1]) for v in videos]
    if len(set(sizes)) > 1:
        detail = ", ".join(
            f"{Path(p).name}: {w} x {h}" for p, (w, h) in zip(paths, sizes, strict=True)
        )
        raise VideoError(
            f"cameras have different frame sizes ({detail}); pass expected_sizes (e.g. "
            "CameraRig.size) to accept per-camera sizes that match a calibration"
        )


def read_camera_videos(
    paths, size_tolerance: int = 16, expected_sizes=None, **kwargs
) -> list[np.ndarray]:
    """Read one synchronised video per camera and check that they fit together.

    Without ``expected_sizes`` every camera must have the same frame size. With it, each camera
    is checked against its own expected size instead, so cameras of different sizes are
    accepted when each matches its calibration (the pose2sim demo's cameras are 1080 and
    1088 px wide).

    Args:
        paths: one video per camera (a non-empty list).
        size_tolerance: pixels (>= 0) by which a video may differ from ``expected_sizes``
            (encoders pad: the pose2sim demo's cam01 is 1080 px wide where its calibration
            says 1088).
        expected_sizes: optional ``(C, 2)`` (width, height) per camera, e.g. ``CameraRig.size``.
        **kwargs: passed to :func:`read_video` (start, count, step, scale).

    Returns:
        ``C`` arrays ``(F, H_c, W_c, 3)`` uint8, the same ``F`` for every camera.

    Raises:
        VideoError: no videos, ``expected_sizes`` not one row per camera, cameras whose frame
            counts disagree, sizes that disagree (with each other, or with ``expected_sizes``).
    """
    paths = _check_camera_paths(paths)
    if (
        isinstance(size_tolerance, bool)
        or not isinstance(size_tolerance, int)
        or size_tolerance < 0
    ):
        raise VideoError(
            f"size_tolerance must be a whole number of pixels >= 0; got {size_tolerance!r}"
        )
    if expected_sizes is not None:
        expected_sizes = np.asarray(expected_sizes, dtype=np.float64)
        if expected_sizes.shape != (len(paths), 2):
            raise VideoError(
                f"expected_sizes must be ({len(paths)}, 2), a (width, height) per camera; got "
                f"shape {expected_sizes.shape}"
            )
    videos = [read_video(p, **kwargs) for p in paths]
    counts = [len(v) for v in videos]
    if len(set(counts)) > 1:
        detail = ", ".join(f"{Path(p).name}: {n}" for p, n in zip(paths, counts, strict=True))
        raise VideoError(
            f"cameras have different frame counts ({detail}); they must be synchronised"
        )
    if expected_sizes is None:
        _check_same_sizes(paths, videos)
        return videos
    scale = kwargs.get("scale", 1.0)
    for p, v, size in zip(paths, videos, expected_sizes, strict=True):
        got = np.array([v.shape[2], v.shape[1]]) / scale
        if np.abs(got - size).max() > size_tolerance:
            raise VideoError(
                f"{p}: frames are {int(got[0])} x {int(got[1])} px but the calibration says "
                f"{int(size[0])} x {int(size[1])}"
            )
    return videos


def _backend(backend: str, x: Tensor) -> str:
    if backend == "auto":
        return "opencv" if x.device.type == "cpu" and not x.requires_grad else "kornia"
    if backend not in ("opencv", "kornia"):
        raise ValueError(f"backend must be 'auto', 'opencv' or 'kornia'; got {backend!r}")
    return backend


def _check_image(x: Tensor, name: str) -> Tensor:
    if x.dim() == 2:
        x = x[None, None]
    if x.dim() != 4 or x.shape[1] not in (1, 3):
        raise ValueError(
            f"{name} must be (B, 1, H, W), (B, 3, H, W) or (H, W); got {tuple(x.shape)}"
        )
    return x


def edges(
    image: Tensor, low: float = 0.1, high: float = 0.2, sigma: float = 1.0, backend: str = "auto"
) -> Tensor:
    """Canny edges with kornia's conventions on both backends.

    The image is blurred by a 5x5 Gaussian of ``sigma``; the gradient is the L2 norm of the
    unnormalised 3x3 Sobel derivatives of the [0, 1] image; ``low`` and ``high`` are the
    hysteresis thresholds on that magnitude (as :func:`kornia.filters.canny`).

    Shapes: ``(B, C, H, W)`` float in [0, 1] -> ``(B, 1, H, W)`` bool.
    """
    image = _check_image(image, "image")
    if image.shape[1] == 3:
        image = kornia.color.rgb_to_grayscale(image)
    if _backend(backend, image) == "kornia":
        _, e = kornia.filters.canny(image, low, high, (5, 5), (sigma, sigma))
        return e > 0.5
    out = np.empty((image.shape[0], 1, *image.shape[-2:]), dtype=bool)
    for b, img in enumerate(image[:, 0].detach().cpu().numpy().astype(np.float32)):
        blurred = cv2.GaussianBlur(img, (5, 5), sigma, borderType=cv2.BORDER_REFLECT)
        dx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
        dy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE)
        # Canny on given derivatives needs 16-bit integers: scale so that thresholds keep
        # four decimal digits of the [0, 1] magnitude.
        scale = 4096.0
        dx16 = np.clip(np.rint(dx * scale), -32768, 32767).astype(np.int16)
        dy16 = np.clip(np.rint(dy * scale), -32768, 32767).astype(np.int16)
        out[b, 0] = cv2.Canny(dx16, dy16, low * scale, high * scale, L2gradient=True) > 0
    return torch.from_numpy(out).to(image.device)


def distance_to_edges(edge_mask: Tensor, backend: str = "auto") -> Tensor:
    """Euclidean distance (pixels) from every pixel to the nearest edge pixel (chamfer maps).

    OpenCV's ``DIST_MASK_PRECISE`` is exact; kornia's cascaded convolutions approximate it
    (coarsely on sparse edges) but are differentiable and run on any device.
    A mask without edges gives ``inf`` (OpenCV) -- check before matching.

    Shapes: ``(B, 1, H, W)`` bool -> ``(B, 1, H, W)`` float32.
    """
    edge_mask = _check_image(edge_mask, "edge_mask")
    if _backend(backend, edge_mask.float()) == "kornia":
        return kornia.contrib.distance_transform(edge_mask.float())
    out = np.empty(edge_mask.shape, dtype=np.float32)
    for b, m in enumerate(edge_mask[:, 0].cpu().numpy()):
        if not m.any():
            out[b, 0] = np.inf
            continue
        out[b, 0] = cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return torch.from_numpy(out).to(edge_mask.device)


def median_coverage(
    frames: np.ndarray,
    background: np.ndarray,
    threshold: float = 30.0,
    open_radius: int = 2,
    close_radius: int = 4,
) -> np.ndarray:
    """Per pixel, the share of ``frames`` in which a moving body covers it: how far a
    temporal median of those frames can be trusted as the background there.

    The median of the frames is a pixel's background only where the person covers it in
    fewer than half of them; past that it is the person's colour (walking toward or away
    from the camera, the torso stays over the same pixels; balancing in place, all of the
    body), and background subtraction against it loses the person there. The person's own
    pixels cannot say so -- where the median holds them they do not differ from it -- so each
    frame counts the bounding box of its largest region that differs from ``background`` by
    more than ``threshold`` grey levels in some channel (opened and closed as
    :func:`clean_foreground`): the changing parts of a body (limbs, the outline, the
    median's ghost of it) bound where the body is.

    Args:
        frames: ``(N, H, W, 3)`` uint8, the frames ``background`` was learnt from.
        background: ``(H, W, 3)`` uint8, e.g. their median.
        threshold: grey levels.
        open_radius, close_radius: morphological clean-up (pixels).

    Returns:
        ``(H, W)`` float64 in [0, 1].
    """
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames must be (N, H, W, 3) uint8; got {frames.shape} {frames.dtype}")
    if background.shape != frames.shape[1:]:
        raise ValueError(f"background must be {frames.shape[1:]}; got {background.shape}")
    changed = np.abs(frames.astype(np.int16) - background.astype(np.int16)).max(-1) > threshold
    covered = np.zeros(frames.shape[1:3], dtype=np.float64)
    for mask in clean_foreground(changed, None, open_radius, close_radius):
        count, _, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
        if count > 1:
            x, y, w, h = stats[1 + np.argmax(stats[1:, cv2.CC_STAT_AREA]), :4]
            covered[y : y + h, x : x + w] += 1
    return covered / max(len(frames), 1)


def foreground_masks(
    frames: np.ndarray,
    method: str = "mog2",
    threshold: float = 30.0,
    history: int = 200,
    open_radius: int = 2,
    close_radius: int = 4,
) -> np.ndarray:
    """Foreground silhouettes of a static camera's frames.

    Args:
        frames: ``(F, H, W, 3)`` uint8.
        method: ``"mog2"`` (OpenCV's adaptive Gaussian mixture, shadows counted as
            background except where the person encloses them: :func:`clean_foreground`) or ``"median"`` (per-pixel temporal median as the background, a
            pixel is foreground when its largest channel difference exceeds ``threshold``).
        threshold: MOG2's variance threshold, or the median method's grey-level difference.
        history: MOG2's history length (frames).
        open_radius, close_radius: morphological clean-up (pixels); 0 disables.

    Returns:
        ``(F, H, W)`` bool.
    """
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames must be (F, H, W, 3) uint8; got {frames.shape} {frames.dtype}")
    shadow = None
    if method == "mog2":
        sub = cv2.createBackgroundSubtractorMOG2(
            history=history, varThreshold=threshold, detectShadows=True
        )
        # Bootstrap with the temporal median (a person who stands still for a while would
        # otherwise be learnt as background, and the first frames would be all foreground),
        # then adapt slowly while segmenting.
        background = np.median(frames, axis=0).astype(np.uint8)
        for _ in range(min(history, 30)):
            sub.apply(background, learningRate=1.0 / min(history, 30))
        labels = np.stack([sub.apply(f, learningRate=1.0 / history) for f in frames])
        raw, shadow = labels == MOG2_FOREGROUND, labels == MOG2_SHADOW
    elif method == "median":
        background = np.median(frames, axis=0).astype(np.int16)
        raw = np.abs(frames.astype(np.int16) - background).max(-1) > threshold
    else:
        raise ValueError(f"method must be 'mog2' or 'median'; got {method!r}")
    return clean_foreground(raw, shadow, open_radius, close_radius)


#: the labels of OpenCV's MOG2 with shadow detection: foreground, shadow (0: background)
MOG2_FOREGROUND, MOG2_SHADOW = 255, 127


def clean_foreground(
    raw: np.ndarray, shadow: np.ndarray | None, open_radius: int, close_radius: int
) -> np.ndarray:
    """Foreground masks cleaned up: ``raw`` ``(F, H, W)`` bool opened by ``open_radius`` and
    closed by ``close_radius`` pixels (0 skips either), then the pixels of ``shadow`` (same
    shape; ``None``: none) that the result encloses added to it.

    MOG2 calls a pixel shadow when it is a darker copy of the background's colour, which a
    grey shirt before a light wall is as much as a shadow on the floor. A shadow cast by the
    person lies on the ground beside them, reachable from the image's border without
    crossing the person; a "shadow" the person's mask closes around (a hole in the torso) is
    the person. So enclosed shadow pixels are foreground; enclosed pixels that look like the
    background itself (the gap of an arm held akimbo) stay background. Returns ``(F, H, W)``
    bool."""
    k_open = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * open_radius + 1,) * 2)
    k_close = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * close_radius + 1,) * 2)
    out = np.empty(raw.shape, dtype=bool)
    for i, m in enumerate(raw.astype(np.uint8)):
        if open_radius:
            m = cv2.morphologyEx(m, cv2.MORPH_OPEN, k_open)
        if close_radius:
            m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, k_close)
        out[i] = m > 0
        if shadow is not None and shadow[i].any():
            out[i] |= shadow[i] & ~_outside(out[i])
    return out


def _outside(mask: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: the pixels off ``mask`` that the image's border reaches without
    crossing it (4-connected)."""
    count, comp = cv2.connectedComponents((~mask).astype(np.uint8), connectivity=4)
    border = np.unique(np.concatenate([comp[0], comp[-1], comp[:, 0], comp[:, -1]]))
    reached = np.zeros(count, dtype=bool)
    reached[border] = True
    reached[0] = False  # label 0: the mask's own pixels
    return reached[comp]


def select_person(
    mask: np.ndarray, near: tuple[float, float] | None = None, min_area: int = 50
) -> np.ndarray:
    """Keep one connected component of a silhouette mask: the largest, or the one whose
    centroid is nearest ``near = (x, y)`` pixels (to follow a person across frames while
    others are in view). ``(H, W)`` bool -> ``(H, W)`` bool (all False if nothing is large enough)."""
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(
        mask.astype(np.uint8), connectivity=8
    )
    candidates = [i for i in range(1, count) if stats[i, cv2.CC_STAT_AREA] >= min_area]
    if not candidates:
        return np.zeros_like(mask, dtype=bool)
    if near is None:
        best = max(candidates, key=lambda i: stats[i, cv2.CC_STAT_AREA])
    else:
        best = min(candidates, key=lambda i: float(np.hypot(*(centroids[i] - np.asarray(near)))))
    return labels == best


def track_person(
    masks: np.ndarray, start: tuple[float, float] | None = None, min_area: int = 50
) -> np.ndarray:
    """Follow one person through foreground masks while others are in view.

    Frame by frame, keep the component nearest the previous frame's centroid (the largest
    component, or the one nearest ``start = (x, y)``, in the first frame). A frame where
    nothing is large enough keeps the last centroid.

    Shapes: ``(F, H, W)`` bool -> ``(F, H, W)`` bool.
    """
    out = np.zeros_like(masks, dtype=bool)
    near = start
    for i, m in enumerate(masks):
        keep = select_person(m, near=near, min_area=min_area)
        out[i] = keep
        if keep.any():
            ys, xs = np.nonzero(keep)
            near = (float(xs.mean()), float(ys.mean()))
    return out
