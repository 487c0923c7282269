"""The person's silhouette from the detector's soft mask and the background model together.

Background subtraction finds everything that changed: the person, and also their shadow on
the wall and floor, reflections, a bystander; it loses limbs in front of a background of
their colour, and most of a person who stays in place (balancing, in the Pose2Sim trial,
the median background holds them). A person detector's segmentation finds the person it
detected and nothing of the shadow. Per frame and camera (:func:`fuse_silhouettes`):

* the detector's mask ``m`` (soft, [0, 1]) is about the tracked person when one piece of
  its confident pixels (``m > 0.5``, 8-connected) and the background model's tracked
  region, dilated by ``reach``, overlap on at least ``agreement`` of the smaller of the two
  (a region that is mostly shadow, or one that holds only the moving arm, both pass; a
  detector following a bystander does not): otherwise the frame keeps the background
  model's silhouette;
* there, the silhouette is ``m`` on the pieces of the mask that touch the tracked region
  (their confident pixels, dilated by 2 px to keep the soft border) and 0 elsewhere: the
  shadow and reflections (changed, no person in the mask) are dropped, the body the
  background model lost is kept whole, a piece of mask on someone else is dropped.

The result is a soft silhouette in [0, 1], which the silhouette cue reads as it is
(:class:`motion.body.observation.Silhouette`); thresholded at 0.5 for the fit's IoU.

Shapes: ``T'`` frames, ``H x W`` the working size.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["fuse_silhouettes"]

#: the soft border kept around the mask's confident pixels (working pixels)
_BORDER_PX = 2


def _dilated(mask: np.ndarray, radius: int) -> np.ndarray:
    if radius <= 0:
        return mask
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1,) * 2)
    return cv2.dilate(mask.astype(np.uint8), kernel) > 0


def fuse_silhouettes(
    foreground: np.ndarray,
    masks: np.ndarray,
    detected: np.ndarray,
    reach_px: int,
    agreement: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """One camera's fused silhouettes (see the module's docstring).

    Args:
        foreground: ``(T', H, W)`` bool, the background model's tracked person.
        masks: ``(T', H, W)`` float in [0, 1], the detector's masks at the working size.
        detected: ``(T',)`` bool, the frames in which the detector found a person.
        reach_px: how far (working pixels) from the tracked region the two may overlap.
        agreement: the share of the smaller of the two that must overlap.

    Returns:
        ``(T', H, W)`` float32 silhouettes in [0, 1], and ``(T',)`` bool: the frames that
        took the detector's mask.
    """
    if foreground.shape != masks.shape or detected.shape != foreground.shape[:1]:
        raise ValueError(
            f"foreground {foreground.shape}, masks {masks.shape} and detected "
            f"{detected.shape} must be (T, H, W), (T, H, W) and (T,)"
        )
    out = foreground.astype(np.float32)
    used = np.zeros(len(out), dtype=bool)
    for t in np.flatnonzero(detected):
        region = foreground[t]
        confident = masks[t] > 0.5
        if not region.any() or not confident.any():
            continue
        near = _dilated(region, reach_px)
        _, labels = cv2.connectedComponents(confident.astype(np.uint8), connectivity=8)
        touching = np.unique(labels[confident & near])
        touching = touching[touching > 0]
        if not len(touching):
            continue
        size = np.bincount(labels.ravel())[touching]
        overlap = np.bincount(labels[confident & near], minlength=labels.max() + 1)[touching]
        if (overlap / np.minimum(size, region.sum())).max() < agreement:
            continue
        pieces = np.isin(labels, touching)
        out[t] = np.where(_dilated(pieces, _BORDER_PX), masks[t], 0.0).astype(np.float32)
        used[t] = True
    return out, used
