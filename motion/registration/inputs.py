"""Registration inputs from what the project already produces: a synthetic sequence of
:mod:`motion.synth` (rendered features, its cameras, noisy 2-D joints) as
:class:`~motion.registration.types.VideoFeatures`.

Units: pixels for images and keypoints, metres for the cameras.
"""

from __future__ import annotations

import numpy as np
import torch

from motion.body.observation import Observation
from motion.cameras import CameraRig
from motion.features import distance_to_edges
from motion.registration.types import VideoFeatures
from motion.synth import Sequence

__all__ = ["features_from_sequence", "sequence_cameras"]

#: pixels standing for "no edge anywhere" in an edge-distance map (an empty edge image)
NO_EDGE_PX = 1e3


def sequence_cameras(seq: Sequence, dtype=torch.float32) -> CameraRig:
    """The rig a synthetic sequence was rendered with (its ``K``, ``R``, ``t`` arrays)."""
    k = torch.from_numpy(seq.arrays["K"]).to(dtype)
    c = k.shape[0]
    h, w = seq.arrays["silhouettes"].shape[-2:]
    return CameraRig(
        k,
        torch.from_numpy(seq.arrays["R"]).to(dtype),
        torch.from_numpy(seq.arrays["t"]).to(dtype),
        torch.zeros(c, 5, dtype=dtype),
        torch.tensor([[w, h]] * c, dtype=dtype),
        list(seq.meta["cameras"]),
    )


def features_from_sequence(
    seq: Sequence,
    keypoints: bool = False,
    noisy: bool = True,
    image: bool = True,
    image_dtype: torch.dtype = torch.float32,
) -> VideoFeatures:
    """A synthetic sequence as registration input: silhouettes, the distance to its edge
    images, the colour frames (``image``) and, with ``keypoints``, the 2-D joints (noisy
    ones unless ``noisy=False``), named by the sequence's skeleton joints.

    ``image_dtype``: ``torch.float32`` gives colour in [0, 1]; ``torch.uint8`` keeps the
    sequence's 0-255 frames as they are (no copy, a quarter of the memory), which
    :func:`motion.registration.register` converts a window at a time
    (:func:`motion.registration.refine.colour_image`) -- for long videos; other consumers
    of :class:`~motion.body.observation.Observation` expect float images."""
    if image_dtype not in (torch.float32, torch.uint8):
        raise ValueError(f"image_dtype must be torch.float32 or torch.uint8; got {image_dtype}")
    sil = torch.from_numpy(seq.arrays["silhouettes"]).float()  # (C, T', H, W)
    c, t, h, w = sil.shape
    edge = torch.from_numpy(seq.arrays["edges"]).reshape(c * t, 1, h, w)
    dist = distance_to_edges(edge).reshape(c, t, h, w)
    dist.masked_fill_(~torch.isfinite(dist), NO_EDGE_PX)  # in place: no second map
    frames = None
    if image:
        rgb = torch.from_numpy(np.ascontiguousarray(seq.arrays["frames"]))  # (C, T', H, W, 3)
        if image_dtype == torch.float32:
            rgb = rgb.float().div_(255)
        frames = rgb.permute(1, 0, 4, 2, 3)[None]  # (1, T', C, 3, H, W)
    kp, names = None, None
    if keypoints:
        uv = torch.from_numpy(seq.arrays["joints2d_noisy" if noisy else "joints2d"]).float()
        kp = torch.cat([uv, torch.ones_like(uv[..., :1])], -1).transpose(0, 1)[None]
        names = list(seq.meta["joint_names"])
    obs = Observation(sil.transpose(0, 1)[None], dist.transpose(0, 1)[None], frames, kp)
    return VideoFeatures(
        obs,
        sequence_cameras(seq),
        float(seq.meta["video_rate_hz"]),
        names,
        name=str(seq.meta.get("student") or seq.meta["reference"]),
    )
