"""Pictures of a registration: the registered body over the video, the reference beside it.

The student's body is the registered posture (local rotations, T, G) as the body model's
capsules; the reference's is its posture at C(t') placed with the same T and G, so the two
stand in the same place and only the articulation differs. Both are drawn in the video's
own cameras (the rig the features were computed with, at the working resolution).

Images are ``(H, W, 3)`` uint8 RGB; poses ``(T', P, 7)`` (metres, quaternion ``w`` first).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch import Tensor

from motion.body.observation import PartShapes
from motion.cameras import CameraRig, resized_rig
from motion.draw import PART_COLOURS
from motion.registration.refine import place_poses
from motion.registration.types import Reference, Registration, scaled_spec
from motion.render import ProjectedParts, label_map, project_parts

__all__ = [
    "BodyPoses",
    "body_poses",
    "camera",
    "crop",
    "draw_body",
    "person_box",
    "points_in_view",
    "side_by_side",
    "side_by_side_frames",
]

#: how strongly the body's colours cover the video (0: invisible, 1: opaque)
OVERLAY_ALPHA = 0.55
#: the reference panel shows the video this faint, so the body is read against the scene
REFERENCE_BACKGROUND_FADE = 0.25
#: frames rendered per batch (bounds memory: a batch is frames x parts x pixels floats)
RENDER_BATCH = 8


@dataclass(frozen=True)
class BodyPoses:
    """The two bodies to draw, in the cameras' world frame.

    Attributes:
        student: ``(T', P, 7)`` the registered posture's part poses.
        reference: ``(T', P, 7)`` the reference at ``C(t')``, placed with the student's T.
        radii: ``(P, 2)`` capsule radii, metres (scaled by G).
        axis: ``(P, 3)`` the reference's capsule axes, metres (scaled by G).
        student_axis: ``(P, 3)`` the student's (G and the student's proportions).
    """

    student: Tensor
    reference: Tensor
    radii: Tensor
    axis: Tensor
    student_axis: Tensor

    def segments(self, which: str) -> Tensor:
        """``(T', P, 2, 3)`` capsule end points of ``which`` ("student" or "reference")."""
        poses = self.student if which == "student" else self.reference
        axis = self.student_axis if which == "student" else self.axis
        shapes = PartShapes(axis, self.radii)
        return shapes.segments(poses, torch.arange(poses.shape[-2]))


def body_poses(registration: Registration, reference: Reference) -> BodyPoses:
    """Part poses of the registered student (at the student's proportions, where measured)
    and of the reference at C, both placed by T."""
    reg = registration
    scale = float(reg.G)
    student = reference.posture_poses(reg.rotations, scale, reg.joint_scales())
    ref = reference.body_poses(reg.C, scale)
    rot, pos = reg.T_rotation.to(torch.float64), reg.T_translation.to(torch.float64)
    spec = scaled_spec(reference.spec, scale)
    parts = None if reg.proportions is None else reg.proportions.part_scales
    student_spec = scaled_spec(reference.spec, scale, parts)
    return BodyPoses(
        place_poses(rot, pos, student),
        place_poses(rot, pos, ref),
        spec.shapes.radii.to(torch.float64),
        spec.shapes.axis.to(torch.float64),
        student_spec.shapes.axis.to(torch.float64),
    )


def camera(rig: CameraRig, index: int) -> CameraRig:
    """The rig of camera ``index`` alone."""
    pick = slice(index, index + 1)
    return dataclasses.replace(
        rig,
        K=rig.K[pick],
        R=rig.R[pick],
        t=rig.t[pick],
        dist=rig.dist[pick],
        size=rig.size[pick],
        names=[rig.names[index]],
    )


def _labels(rig: CameraRig, segments: Tensor, radii: Tensor, height: int, width: int) -> Tensor:
    """``(N, H, W)`` long part in front at each pixel (-1: none) of a one-camera rig.

    Each frame's map is computed inside the box around its projected parts only (the
    pixels outside it are none by construction): a body covers a small part of a frame,
    and an overlay upscaled to 720 px would otherwise test every part at every pixel."""
    parts = project_parts(rig, segments.to(rig.K), radii.to(rig.K))
    out = torch.full((len(segments), height, width), -1, dtype=torch.long)
    reach = parts.ends - parts.radii[..., None]  # (N, 1, P, 2, 2): the ends less the radii
    low = reach.flatten(-3, -2).amin(-2)[:, 0]  # (N, 2) x, y
    high = (parts.ends + parts.radii[..., None]).flatten(-3, -2).amax(-2)[:, 0]
    for k in range(len(segments)):
        if not (torch.isfinite(low[k]).all() and torch.isfinite(high[k]).all()):
            labels, _ = label_map(_frame_parts(parts, k), height, width)  # let it decide
            out[k] = labels[0]
            continue
        x0, y0 = (max(0, math.floor(float(v))) for v in low[k])
        x1 = min(width, math.ceil(float(high[k, 0])) + 1)
        y1 = min(height, math.ceil(float(high[k, 1])) + 1)
        if x1 <= x0 or y1 <= y0:
            continue  # the body is outside the image
        one = _frame_parts(parts, k)
        shift = torch.tensor([x0, y0], dtype=one.ends.dtype, device=one.ends.device)
        shifted = ProjectedParts(one.ends - shift, one.radii, one.depth)
        labels, _ = label_map(shifted, y1 - y0, x1 - x0)
        out[k, y0:y1, x0:x1] = labels[0].cpu()
    return out


def _frame_parts(parts: ProjectedParts, k: int) -> ProjectedParts:
    return ProjectedParts(parts.ends[k], parts.radii[k], parts.depth[k])


def draw_body(image: np.ndarray, labels: np.ndarray, alpha: float = OVERLAY_ALPHA) -> np.ndarray:
    """Blend part colours over ``image`` where ``labels`` ``(H, W)`` (-1: none) shows a
    part, with a dark outline so the body reads on any background."""
    out = image.astype(np.float32).copy()
    mask = labels >= 0
    out[mask] = (1 - alpha) * out[mask] + alpha * PART_COLOURS[labels[mask] % len(PART_COLOURS)]
    out = out.round().astype(np.uint8)
    edge = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8))
    out[edge > 0] = (40, 40, 40)
    return out


def points_in_view(rig: CameraRig, points: Tensor, margin_px: float = 1.0) -> Tensor:
    """Whether world ``points`` ``(..., N, 3)`` project inside every camera's image (at
    least ``margin_px`` from the border, in front of the camera): ``(..., N)`` bool."""
    uv, depth = rig.project(points.to(rig.K))  # (..., C, N, 2), (..., C, N)
    size = rig.size.to(rig.K)[:, None, :]  # (C, 1, 2)
    inside = ((uv >= margin_px) & (uv <= size - 1 - margin_px)).all(-1) & (depth > 0)
    return inside.all(-2).cpu()


def _caption(image: np.ndarray, text: str) -> np.ndarray:
    """``text`` in black on a white box in the top left corner of ``image``."""
    out = np.ascontiguousarray(image.copy())
    scale = max(0.4, image.shape[0] / 600)
    thickness = 1 if scale < 0.8 else 2
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
    cv2.rectangle(out, (0, 0), (w + 6, h + base + 6), (255, 255, 255), -1)
    cv2.putText(
        out, text, (3, h + 3), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), thickness, cv2.LINE_AA
    )
    return out


def person_box(masks: list[np.ndarray], margin: float = 0.15, aspect: float = 0.75):
    """``(x0, y0, x1, y1)`` pixels around everything the ``(H, W)`` bool ``masks`` show,
    grown by ``margin`` of its height and widened or heightened to ``aspect`` (width over
    height); may reach outside the image (:func:`crop` pads). ``None`` when all are empty."""
    union = np.any(np.stack(masks), 0)
    ys, xs = np.nonzero(union)
    if len(xs) == 0:
        return None
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    h = (y1 - y0) * (1 + 2 * margin)
    w = max((x1 - x0) * (1 + 2 * margin), h * aspect)
    h = max(h, w / aspect)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    return round(cx - w / 2), round(cy - h / 2), round(cx + w / 2), round(cy + h / 2)


def crop(image: np.ndarray, box, height: int) -> np.ndarray:
    """``image`` inside ``box`` (padded with white beyond the image), resized to ``height``
    pixels high."""
    x0, y0, x1, y1 = box
    h, w = image.shape[:2]
    pad = max(0, -x0, -y0, x1 - w, y1 - h)
    padded = cv2.copyMakeBorder(
        image, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=(255, 255, 255)
    )
    part = padded[y0 + pad : y1 + pad, x0 + pad : x1 + pad]
    width = max(1, round(part.shape[1] * height / part.shape[0]))
    return cv2.resize(part, (width, height), interpolation=cv2.INTER_LINEAR)


def side_by_side(
    frame: np.ndarray,
    student_labels: np.ndarray,
    reference_labels: np.ndarray,
    captions: tuple[str, ...] | None = None,
    with_video: bool = False,
    zoom: int | None = None,
) -> np.ndarray:
    """One picture: [the video alone,] the registered student over the video, and the
    reference's posture over a faded copy. ``(H, W, 3)`` -> ``(H, 2W or 3W, 3)``; with
    ``zoom``, each panel is cropped around the two bodies and ``zoom`` pixels high;
    ``captions``: a text per panel, written in its top left corner."""
    student = draw_body(frame, student_labels)
    faded = (255 - REFERENCE_BACKGROUND_FADE * (255 - frame.astype(np.float32))).astype(np.uint8)
    reference = draw_body(faded, reference_labels, alpha=0.8)
    panels = [frame, student, reference] if with_video else [student, reference]
    box = None if zoom is None else person_box([student_labels >= 0, reference_labels >= 0])
    if box is not None:
        panels = [crop(p, box, zoom) for p in panels]
    if captions is not None:
        if len(captions) != len(panels):
            raise ValueError(f"expected {len(panels)} captions, one per panel; got {len(captions)}")
        panels = [_caption(p, text) for p, text in zip(panels, captions, strict=True)]
    return np.concatenate(panels, 1)


def side_by_side_frames(
    frames: np.ndarray,
    rig: CameraRig,
    index: int,
    poses: BodyPoses,
    captions: list[tuple[str, ...]] | None = None,
    frame_ids: list[int] | None = None,
    with_video: bool = False,
    zoom: int | None = None,
    min_height: int | None = None,
) -> Iterator[np.ndarray]:
    """:func:`side_by_side` for video frames ``frame_ids`` (default all) of camera
    ``index``: ``frames`` ``(T', H, W, 3)`` uint8 at the rig's resolution. With
    ``min_height`` above ``H``, each frame is first upscaled to ``min_height`` pixels high
    and the bodies are drawn at that size (through the resized camera, so their outlines
    are sharp, not magnified pixels). Rendered in batches of :data:`RENDER_BATCH` frames;
    yields one picture per frame."""
    one = camera(rig, index)
    h, w = frames.shape[1:3]
    size = (w, h)
    if min_height is not None and min_height > h:
        size = (max(1, round(w * min_height / h)), min_height)
        one = resized_rig(one, [(w, h)], [size])
    ids = list(range(len(frames))) if frame_ids is None else list(frame_ids)
    student, reference = poses.segments("student"), poses.segments("reference")
    for start in range(0, len(ids), RENDER_BATCH):
        batch = torch.as_tensor(ids[start : start + RENDER_BATCH])
        s_lab = _labels(one, student[batch], poses.radii, size[1], size[0]).numpy()
        r_lab = _labels(one, reference[batch], poses.radii, size[1], size[0]).numpy()
        for k, t in enumerate(batch.tolist()):
            text = None if captions is None else captions[start + k]
            frame = frames[t]
            if size != (w, h):
                frame = cv2.resize(frame, size, interpolation=cv2.INTER_CUBIC)
            yield side_by_side(frame, s_lab[k], r_lab[k], text, with_video, zoom)
