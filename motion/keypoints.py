"""Keypoint files: TRC (3D markers) and OpenPose JSON (2D detections).

Units as stored: TRC positions in the file's declared unit (pose2sim: metres, Y up);
OpenPose pixels ``(x, y, confidence)``. Shapes: ``F`` frames, ``M`` markers / keypoints.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "BODY_25B",
    "MEDIAPIPE_POSE_33",
    "KeypointFileError",
    "Markers",
    "read_openpose_folder",
    "read_trc",
]

#: OpenPose BODY_25B keypoint order
BODY_25B = [
    "Nose", "LEye", "REye", "LEar", "REar", "LShoulder", "RShoulder", "LElbow", "RElbow", "LWrist",
    "RWrist", "LHip", "RHip", "LKnee", "RKnee", "LAnkle", "RAnkle", "UpperNeck", "HeadTop",
    "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel",
]  # fmt: skip

#: MediaPipe (BlazePose) Pose's 33 landmarks in its order, named as OpenPose names its own
#: (``LFootIndex`` is the tip of the second toe, ``LEyeInner`` the eye's inner corner)
MEDIAPIPE_POSE_33 = [
    "Nose", "LEyeInner", "LEye", "LEyeOuter", "REyeInner", "REye", "REyeOuter", "LEar", "REar",
    "MouthL", "MouthR", "LShoulder", "RShoulder", "LElbow", "RElbow", "LWrist", "RWrist",
    "LPinky", "RPinky", "LIndex", "RIndex", "LThumb", "RThumb", "LHip", "RHip", "LKnee",
    "RKnee", "LAnkle", "RAnkle", "LHeel", "RHeel", "LFootIndex", "RFootIndex",
]  # fmt: skip


class KeypointFileError(ValueError):
    """A malformed keypoint file; the message names the file and the place."""


@dataclass
class Markers:
    """3D marker trajectories. positions ``(F, M, 3)``; rate in Hz; unit as declared."""

    names: list[str]
    positions: np.ndarray
    rate: float
    unit: str


def read_trc(path: str | Path) -> Markers:
    """Read a TRC marker file (tab separated, 5 header lines)."""
    path = Path(path)
    lines = path.read_text().splitlines()
    if len(lines) < 6 or not lines[0].startswith("PathFileType"):
        raise KeypointFileError(f"{path}:1: not a TRC file (expected 'PathFileType')")
    keys = lines[1].split("\t")
    values = lines[2].split("\t")
    header = dict(zip(keys, values, strict=False))
    try:
        rate = float(header["DataRate"])
        num_markers = int(header["NumMarkers"])
        unit = header.get("Units", "m")
    except (KeyError, ValueError) as err:
        raise KeypointFileError(f"{path}:3: bad TRC header ({err})") from None
    names = [n for n in lines[3].split("\t")[2:] if n.strip()]
    if len(names) != num_markers:
        raise KeypointFileError(
            f"{path}:4: {len(names)} marker names but NumMarkers = {num_markers}"
        )
    rows = []
    for i, line in enumerate(lines[5:], start=6):
        if not line.strip():
            continue
        parts = line.split("\t")
        try:
            vals = [float(v) if v.strip() else math.nan for v in parts[2 : 2 + 3 * num_markers]]
        except ValueError as err:
            raise KeypointFileError(f"{path}:{i}: {err}") from None
        if len(vals) != 3 * num_markers:
            raise KeypointFileError(f"{path}:{i}: {len(vals)} values; expected {3 * num_markers}")
        rows.append(vals)
    return Markers(names, np.array(rows).reshape(len(rows), num_markers, 3), rate, unit)


def read_openpose_folder(folder: str | Path, person: int = 0) -> np.ndarray:
    """All frames of one camera: ``(F, 25, 3)`` pixels and confidence (NaN where nobody).

    Frames are the folder's ``*.json`` files in name order.
    """
    folder = Path(folder)
    files = sorted(folder.glob("*.json"))
    if not files:
        raise KeypointFileError(f"{folder}: no OpenPose .json files")
    out = np.full((len(files), 25, 3), np.nan)
    for f, file in enumerate(files):
        try:
            people = json.loads(file.read_text())["people"]
        except (json.JSONDecodeError, KeyError) as err:
            raise KeypointFileError(f"{file}: not OpenPose JSON ({err})") from None
        # an empty person entry ({}) means nobody was associated in that frame
        if len(people) > person and people[person].get("pose_keypoints_2d"):
            kp = np.asarray(people[person]["pose_keypoints_2d"], dtype=np.float64)
            if kp.size != 75:
                raise KeypointFileError(
                    f"{file}: pose_keypoints_2d has {kp.size} values; expected 75"
                )
            out[f] = kp.reshape(25, 3)
    return out
