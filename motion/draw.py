"""Pictures for people: skeleton and part overlays, contact sheets, overlay videos (OpenCV).

Images are ``(H, W, 3)`` uint8 RGB; points are pixels ``(u, v)``.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from motion.render import ProjectedParts, label_map

__all__ = ["PART_COLOURS", "contact_sheet", "draw_parts", "draw_skeleton", "write_video"]

#: a distinct colour per body part (RGB, 0-255), left parts warm, right parts cool
PART_COLOURS = np.array([
    [200, 200, 200], [160, 160, 160], [240, 220, 120],
    [230, 90, 60], [240, 140, 60], [250, 190, 90],
    [60, 120, 230], [70, 170, 240], [110, 210, 250],
    [200, 60, 120], [230, 100, 160], [250, 150, 200],
    [60, 170, 90], [90, 210, 120], [150, 240, 160],
], dtype=np.uint8)  # fmt: skip


def draw_skeleton(
    image: np.ndarray,
    joints: np.ndarray,
    parents: Sequence[int],
    colour=(255, 255, 0),
    thickness: int = 2,
) -> np.ndarray:
    """Bones as lines and joints as dots on a copy of ``image``. joints ``(J, 2)`` pixels."""
    out = np.ascontiguousarray(image.copy())
    pts = np.round(np.asarray(joints)).astype(int)
    for j, p in enumerate(parents):
        if p >= 0:
            cv2.line(out, tuple(pts[p]), tuple(pts[j]), colour, thickness, cv2.LINE_AA)
    for q in pts:
        cv2.circle(out, tuple(q), thickness + 1, colour, -1, cv2.LINE_AA)
    return out


def draw_parts(
    image: np.ndarray, parts: ProjectedParts, alpha: float = 0.6, colours: np.ndarray = PART_COLOURS
) -> np.ndarray:
    """Blend the depth-ordered part-label map of one image's parts over ``image``."""
    h, w = image.shape[:2]
    labels, _ = label_map(parts, h, w)
    labels = labels.cpu().numpy()
    out = image.astype(np.float32).copy()
    mask = labels >= 0
    out[mask] = (1 - alpha) * out[mask] + alpha * colours[labels[mask] % len(colours)]
    return out.round().astype(np.uint8)


def contact_sheet(
    images: Sequence[np.ndarray],
    columns: int = 4,
    captions: Sequence[str] | None = None,
    gap: int = 4,
) -> np.ndarray:
    """Tile equally sized images into one, left to right, top to bottom, with captions."""
    if not images:
        raise ValueError("contact_sheet needs at least one image")
    h, w = images[0].shape[:2]
    if any(im.shape[:2] != (h, w) for im in images):
        raise ValueError("contact_sheet needs images of one size")
    rows = (len(images) + columns - 1) // columns
    sheet = np.full((rows * (h + gap) + gap, columns * (w + gap) + gap, 3), 255, dtype=np.uint8)
    for i, im in enumerate(images):
        r, c = divmod(i, columns)
        y, x = gap + r * (h + gap), gap + c * (w + gap)
        tile = np.ascontiguousarray(im.copy())
        if captions is not None:
            cv2.putText(
                tile,
                str(captions[i]),
                (4, 14),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.4,
                (0, 0, 0),
                1,
                cv2.LINE_AA,
            )
        sheet[y : y + h, x : x + w] = tile
    return sheet


def write_video(path: str | Path, frames: Iterable[np.ndarray] | np.ndarray, fps: float) -> Path:
    """Write RGB frames to a video file (mp4v for .mp4, MJPG for .avi), consuming ``frames``
    one at a time (a generator is never held in memory whole). Raises ``ValueError`` for no
    frames and ``OSError`` if OpenCV cannot open the writer."""
    path = Path(path)
    stream = iter(frames)
    first = next(stream, None)
    if first is None:
        raise ValueError("write_video needs at least one frame")
    h, w = first.shape[:2]
    codec = "MJPG" if path.suffix.lower() == ".avi" else "mp4v"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), fps, (w, h))
    if not writer.isOpened():
        raise OSError(f"{path}: OpenCV cannot write this video ({codec})")
    try:
        for f in itertools.chain([first], stream):
            writer.write(cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
    return path


def to_numpy_image(image: torch.Tensor) -> np.ndarray:
    """``(3, H, W)`` float in [0, 1] -> ``(H, W, 3)`` uint8."""
    return (image.clamp(0, 1).movedim(0, -1).cpu().numpy() * 255).round().astype(np.uint8)
