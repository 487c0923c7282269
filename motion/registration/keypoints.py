"""2-D joints from files as an extra observation of registration (``--keypoints``).

A pose detector's output for the videos registration reads
(:func:`motion.registration.video.features_from_videos`) becomes the observation's
``keypoints`` and :attr:`VideoFeatures.keypoint_joints`, which stage 1 (a pose from the
2-D joints, a robust reprojection term) and stage 2 (the :class:`~motion.body.observation.
Joints2D` cue) use. Inputs (:func:`read_keypoint_source`):

* **OpenPose JSON**, one folder per camera, one file per video frame (files in natural name
  order); every person of each file is read, as the keypoint sets
  :data:`KEYPOINT_SETS` by their number of values (75: BODY_25B, or BODY_25 when its MidHip
  column sits between the hips; 78: HALPE_26, as Pose2Sim's and Sports2D's RTMPose write;
  51: COCO-17; 54: OpenPose's COCO-18; 99: MediaPipe Pose's 33 landmarks, as
  :mod:`motion.perception` writes them). One person per frame is kept: a given index into
  the file's ``people``, or (``person=None``) the detection whose confident keypoints fall
  most inside the tracked silhouette of that frame and camera (dilated by
  :data:`INSIDE_FRACTION` of the image size); where the silhouette is empty, the detection
  nearest to the previous choice; where no detection touches a non-empty silhouette,
  nobody (a bystander is never taken for the tracked person).
* **TRC of 2-D pixels**, one file per camera, as Sports2D writes them (``*_px_person00.trc``:
  X, Y in pixels, Y down, Z = 0, 'Units m' in the header regardless; a missing point is an
  empty cell, or 0, 0 with ``fill_large_gaps_with = zeros``). The first row's Time says which
  video frame it is (Sports2D's ``time_range``). Its 2024 releases wrote pixels / 1000 with Y
  up: recognised (every X >= 0, Y <= 0, the whole track under 5 units wide) and scaled back,
  with a note. Coordinates that look like metres (a track under 5 units wide otherwise) and
  3-D TRC files (Z not 0) are refused.

A ``source`` is a folder of per-camera subfolders of JSON files (``cam01_json``, ...: matched
to the cameras in natural name order), a single folder of JSON files (one camera), one
``.trc`` file (one camera), or a list of any of those (one camera each, in order).

Keypoint names reach the reference's joints through the body model's landmark roles
(:func:`match_keypoints`): a bundled keypoint spec (``motion/data/bodyparts`` files with a
``markers`` list: ``openpose_body25b``, ``pose2sim_21``, ``mediapipe_pose33``; the one naming the most roles
with a single keypoint of the file, or one given) gives each role its keypoints, the
reference's :class:`~motion.bodyparts.BodyModel` its joints; a keypoint that is the only
keypoint of a role which the reference places on exactly one skeleton joint is that joint.
Roles are visited in the body model's part order, proximal end first, so a keypoint standing
for two roles (the wrist, also the hand's end where a detector has no hand keypoints) is the
first's joint. Other keypoints are dropped.

For the CMU skeleton (``motion/data/cmu_02_01_walk.bvh``, the cgspeed names; ``cmu_07_01``
alike) and BODY_25B this matches 14 joints: LShoulder -> LeftArm, LElbow -> LeftForeArm,
LWrist -> LeftHand, LHip -> LeftUpLeg, LKnee -> LeftLeg, LAnkle -> LeftFoot, LBigToe ->
LeftToeBase, and the same on the right. HeadTop is the head_top role, but the CMU head top is
an End Site, not a joint; BODY_25B has no neck base (its UpperNeck is not the CMU Neck).
BODY_25 and HALPE_26 (``pose2sim_21``'s names) also match Neck -> Neck (their Neck is the
neck's base, as the cgspeed Neck): 15 joints; COCO-18 13 (no toes); COCO-17 12. LBigToe is
the toe's tip, the CMU LeftToeBase the ball of the foot: a few centimetres apart (the joint
terms are Cauchy-robust).

Pixels: ``u`` right, ``v`` down, integer coordinates at pixel centres (OpenCV's); a file's
pixels are the original video's, mapped to the working size by the video's ``scale`` ``s``
as frames are resized: ``u -> (u + 0.5) s - 0.5``. Confidence in [0, 1]; a missing keypoint
has confidence 0 and coordinates 0 (the stage 1 and stage 2 joint terms weight each
keypoint by its confidence). Shapes: ``T'`` video frames, ``C`` cameras, ``K`` matched
keypoints, ``F`` frames in a file.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import yaml

from motion.bodyparts import DATA, canonical_name, joint_of_point, load_spec, read_parts
from motion.keypoints import BODY_25B, MEDIAPIPE_POSE_33, KeypointFileError, read_trc
from motion.registration.types import Reference, RegistrationError
from motion.registration.video import VideoInput

__all__ = [
    "BODY_25",
    "COCO_18",
    "HALPE_26",
    "INSIDE_FRACTION",
    "KEYPOINT_SETS",
    "CameraKeypoints",
    "KeypointInputError",
    "KeypointMatch",
    "attach_keypoints",
    "keypoint_specs",
    "match_keypoints",
    "read_keypoint_source",
    "read_openpose_people",
    "read_trc_2d",
]

#: OpenPose BODY_25 keypoint order
BODY_25 = [
    "Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "MidHip",
    "RHip", "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar",
    "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel",
]  # fmt: skip
#: HALPE_26 (AlphaPose, RTMPose body with feet: Pose2Sim's and Sports2D's default)
HALPE_26 = [
    "Nose", "LEye", "REye", "LEar", "REar", "LShoulder", "RShoulder", "LElbow", "RElbow",
    "LWrist", "RWrist", "LHip", "RHip", "LKnee", "RKnee", "LAnkle", "RAnkle", "Head", "Neck",
    "Hip", "LBigToe", "RBigToe", "LSmallToe", "RSmallToe", "LHeel", "RHeel",
]  # fmt: skip
#: OpenPose's COCO-18 keypoint order
COCO_18 = [
    "Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "RHip",
    "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar",
]  # fmt: skip

#: keypoint sets of OpenPose-format JSON, by name (``convention=``)
KEYPOINT_SETS: dict[str, list[str]] = {
    "body25b": list(BODY_25B),
    "body25": BODY_25,
    "halpe26": HALPE_26,
    "coco17": HALPE_26[:17],
    "coco18": COCO_18,
    "mediapipe33": MEDIAPIPE_POSE_33,
}
# values per person (3 per keypoint) -> the sets of that size, the default first
_BY_SIZE = {
    75: ("body25b", "body25"),
    78: ("halpe26",),
    51: ("coco17",),
    54: ("coco18",),
    99: ("mediapipe33",),
}

#: a keypoint counts as inside the silhouette within this fraction of the image's larger
#: side (working pixels, at least 2): detectors put joints on the body's outline, and
#: background subtraction loses thin limbs
INSIDE_FRACTION = 0.01

# BODY_25 tells itself from BODY_25B by its MidHip (column 8) lying between its hips (9, 12):
# the median of |p8 - (p9 + p12) / 2| / |p9 - p12| over the detections is below this (in
# BODY_25B those columns are a right elbow, a left wrist and a right hip)
_MIDHIP_RATIO = 0.2
# a track narrower and shorter than this (file units) is not in pixels
_PIXEL_EXTENT = 5.0


class KeypointInputError(KeypointFileError, RegistrationError):
    """Keypoint files that cannot observe this video and reference (the message names the
    file and why): a :class:`KeypointFileError` and a :class:`RegistrationError`."""


@dataclass
class CameraKeypoints:
    """One camera's detections as read, in the file's pixels.

    Attributes:
        path: the folder or file.
        names: the K keypoint names, in column order.
        people: per file frame, ``(n, K, 3)`` float64 ``u, v, confidence`` of the ``n``
            people detected (NaN where a person has no detection; ``n`` may be 0).
        first_frame: the video frame of ``people[0]``.
        whole_video: whether the file covers the video from its first frame (then it must
            have as many frames as the video file, where that is known).
        rate: frames per second the file declares (``None``: none).
        note: what was assumed while reading ("" when nothing was).
    """

    path: Path
    names: list[str]
    people: list[np.ndarray]
    first_frame: int = 0
    whole_video: bool = True
    rate: float | None = None
    note: str = ""

    @property
    def num_frames(self) -> int:
        return len(self.people)


@dataclass(frozen=True)
class KeypointMatch:
    """A keypoint column matched to a reference joint through a landmark role."""

    column: int
    keypoint: str
    role: str
    joint: str


# -- reading --------------------------------------------------------------------------------
def _natural(path: Path):
    return [int(s) if s.isdigit() else s.lower() for s in re.split(r"(\d+)", path.name)]


def _json_files(folder: Path) -> list[Path]:
    return sorted((p for p in folder.glob("*.json") if p.is_file()), key=_natural)


def _read_json(file: Path) -> list:
    try:
        people = json.loads(file.read_text())["people"]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as err:
        raise KeypointInputError(
            f"{file}: not OpenPose JSON ({type(err).__name__}: {err})"
        ) from None
    if not isinstance(people, list):
        raise KeypointInputError(f"{file}: not OpenPose JSON ('people' is not a list)")
    return people


def _body25_or_b(people: list[np.ndarray]) -> str:
    """``"body25"`` when column 8 is the hips' midpoint in most detections, else
    ``"body25b"``."""
    ratios = []
    for frame in people:
        for p in frame:
            if (p[[8, 9, 12], 2] > 0).all() and np.isfinite(p[[8, 9, 12], :2]).all():
                width = np.linalg.norm(p[9, :2] - p[12, :2])
                if width > 1e-6:
                    ratios.append(np.linalg.norm(p[8, :2] - (p[9, :2] + p[12, :2]) / 2) / width)
    return "body25" if ratios and float(np.median(ratios)) < _MIDHIP_RATIO else "body25b"


def read_openpose_people(folder: str | Path, convention: str | None = None) -> CameraKeypoints:
    """Every person of every frame of one camera's OpenPose JSON folder.

    Args:
        folder: the camera's folder of ``*.json`` files, one per video frame.
        convention: a :data:`KEYPOINT_SETS` name, or ``None`` to tell it from the number of
            values per person (75: BODY_25B unless BODY_25's MidHip shows).

    Raises:
        KeypointInputError: naming the folder or file: no JSON files, a file that is not
            OpenPose JSON, people of different sizes, a size no keypoint set has, a
            ``convention`` of another size, or nobody detected in any file.
    """
    folder = Path(folder)
    files = _json_files(folder)
    if not files:
        raise KeypointInputError(f"{folder}: no OpenPose .json files")
    if convention is not None and convention not in KEYPOINT_SETS:
        raise KeypointInputError(
            f"{folder}: unknown keypoint convention {convention!r}; expected one of "
            f"{', '.join(KEYPOINT_SETS)}"
        )
    size = None if convention is None else 3 * len(KEYPOINT_SETS[convention])
    raw: list[list[np.ndarray | None]] = []  # per file, per entry (None: an empty entry)
    for file in files:
        frame: list[np.ndarray | None] = []
        for entry in _read_json(file):
            kp = entry.get("pose_keypoints_2d") if isinstance(entry, dict) else None
            if not kp:  # an empty entry ({}): nobody associated there (keeps the index)
                frame.append(None)
                continue
            try:
                kp = np.asarray(kp, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError) as err:
                raise KeypointInputError(
                    f"{file}: pose_keypoints_2d is not numbers ({err})"
                ) from None
            if size is None:
                if kp.size not in _BY_SIZE:
                    known = ", ".join(
                        f"{'/'.join(_BY_SIZE[n]).upper()}: {n}" for n in sorted(_BY_SIZE)
                    )
                    raise KeypointInputError(
                        f"{file}: pose_keypoints_2d has {kp.size} values, no known keypoint "
                        f"set ({known} values)"
                    )
                size = kp.size
            if kp.size != size:
                raise KeypointInputError(
                    f"{file}: pose_keypoints_2d has {kp.size} values; expected {size} (as "
                    f"{'the convention ' + convention if convention else 'the earlier files'})"
                )
            frame.append(kp.reshape(-1, 3))
        raw.append(frame)
    if size is None:
        raise KeypointInputError(f"{folder}: nobody detected in any of the {len(files)} files")
    empty = np.full((size // 3, 3), np.nan)
    people = [
        np.stack([empty if p is None else p for p in frame])
        if frame
        else np.zeros((0, *empty.shape))
        for frame in raw
    ]
    if convention is None:
        options = _BY_SIZE[size]
        convention = _body25_or_b(people) if len(options) > 1 else options[0]
    return CameraKeypoints(folder, list(KEYPOINT_SETS[convention]), people)


def _trc_first_time(path: Path) -> float | None:
    """The Time column of the first data row (line 6 on), or ``None``."""
    for line in path.read_text().splitlines()[5:]:
        if line.strip():
            parts = line.split("\t")
            try:
                return float(parts[1])
            except (IndexError, ValueError):
                return None
    return None


def read_trc_2d(path: str | Path) -> CameraKeypoints:
    """One camera's 2-D keypoints from a TRC of pixels (Sports2D's ``*_px_person*.trc``).

    Raises:
        KeypointInputError: naming the file: unreadable or not a TRC, a 3-D TRC (Z not 0),
            coordinates that are not pixels (metres), or no point at all.
    """
    path = Path(path)
    try:
        markers = read_trc(path)
        t0 = _trc_first_time(path)
    except KeypointFileError as err:
        raise KeypointInputError(str(err)) from None
    except (OSError, UnicodeDecodeError) as err:
        raise KeypointInputError(f"{path}: cannot read ({type(err).__name__}: {err})") from None
    pos = markers.positions  # (F, M, 3)
    z = pos[..., 2][np.isfinite(pos[..., 2])]
    if z.size and np.abs(z).max() > 1e-9:
        raise KeypointInputError(
            f"{path}: a 3-D TRC (Z is not 0, up to {np.abs(z).max():g} {markers.unit}); "
            "expected 2-D pixel coordinates with Z = 0 (Sports2D's *_px_person*.trc)"
        )
    uv = pos[..., :2].copy()
    missing = ~np.isfinite(uv).all(-1) | (uv == 0).all(-1)
    if missing.all():
        raise KeypointInputError(f"{path}: no keypoint in any of the {len(uv)} frames")
    seen = uv[~missing]
    extent = float((seen.max(0) - seen.min(0)).max())
    note = ""
    if extent < _PIXEL_EXTENT:
        if (seen[:, 0] >= 0).all() and (seen[:, 1] <= 0).all():
            uv = uv * np.array([1000.0, -1000.0])
            note = (
                f"{path.name}: read as Sports2D's 2024 layout (pixels / 1000, Y up), scaled "
                "back to pixels"
            )
        else:
            raise KeypointInputError(
                f"{path}: the keypoints span only {extent:.3g} units: not pixels (metres?); "
                "expected Sports2D's pixel file (*_px_person*.trc)"
            )
    conf = (~missing).astype(np.float64)
    uv[missing] = np.nan
    people = [np.concatenate([uv[f], conf[f, :, None]], -1)[None] for f in range(len(uv))]
    rate = markers.rate if markers.rate > 0 else None
    first = 0
    if t0 is not None and rate is not None and math.isfinite(t0):
        first = max(round(t0 * rate), 0)
    return CameraKeypoints(path, list(markers.names), people, first, first == 0, rate, note)


def _camera_sources(source: Path) -> list[Path]:
    """The per-camera folders or files of one ``source`` path."""
    if not source.exists():
        raise KeypointInputError(f"{source}: no such keypoint file or folder")
    if source.is_file():
        if source.suffix.lower() != ".trc":
            raise KeypointInputError(
                f"{source}: not a keypoint source (expected a .trc file or a folder of "
                "OpenPose .json files)"
            )
        return [source]
    if _json_files(source):
        return [source]
    subs = sorted((d for d in source.iterdir() if d.is_dir() and _json_files(d)), key=_natural)
    if subs:
        return subs
    trcs = sorted(source.glob("*.trc"))
    hint = f" (it holds {len(trcs)} .trc files: pass them as files)" if trcs else ""
    raise KeypointInputError(f"{source}: no OpenPose .json files in it nor in its subfolders{hint}")


def read_keypoint_source(
    source: str | Path | Sequence[str | Path], convention: str | None = None
) -> list[CameraKeypoints]:
    """Each camera's detections from a keypoint ``source`` (see the module's docstring):
    one :class:`CameraKeypoints` per camera, in the cameras' order."""
    items = [source] if isinstance(source, str | Path) else list(source)
    if not items:
        raise KeypointInputError("no keypoint source given")
    out = []
    for item in items:
        for cam in _camera_sources(Path(item)):
            if cam.is_file():
                out.append(read_trc_2d(cam))
            else:
                out.append(read_openpose_people(cam, convention))
    return out


# -- names to joints ------------------------------------------------------------------------
def keypoint_specs() -> dict[str, dict[str, list[str]]]:
    """The bundled keypoint specs (``motion/data/bodyparts`` files with ``markers``): name
    -> role -> keypoint names."""
    out = {}
    for path in sorted(DATA.glob("*.yaml")):
        raw = yaml.safe_load(path.read_text()) or {}
        if isinstance(raw, dict) and "markers" in raw and "roles" in raw:
            out[path.stem] = load_spec(path)
    return out


def _single_roles(spec: dict[str, list[str]], index: dict[str, int]) -> dict[str, int]:
    """role -> column, for the roles the spec gives one keypoint that the names have."""
    out = {}
    for role, names in spec.items():
        if len(names) == 1 and canonical_name(names[0]) in index:
            out[role] = index[canonical_name(names[0])]
    return out


def match_keypoints(
    names: list[str],
    reference: Reference,
    spec: str | Path | dict[str, list[str]] | None = None,
    where: str = "keypoints",
) -> tuple[list[KeypointMatch], str]:
    """Which keypoint columns are which joints of ``reference`` (see the module's docstring).

    Args:
        names: the keypoint names, in column order (compared by
            :func:`motion.bodyparts.canonical_name`).
        reference: whose body model maps roles to joints.
        spec: role -> keypoint names (a dict, a spec file, a bundled spec's name), or
            ``None``: the bundled spec naming the most roles with one of ``names``.
        where: the file, for messages.

    Returns:
        The matches in column order, and the spec's name.

    Raises:
        KeypointInputError: no keypoint name is a role's (naming what was found and what was
            expected), or no such role is a single joint of the reference.
    """
    index: dict[str, int] = {}
    for i, n in enumerate(names):
        index.setdefault(canonical_name(n), i)
    if spec is None:
        specs = keypoint_specs()

        def coverage(item):
            roles = _single_roles(item[1], index)
            markers = {canonical_name(m) for ms in item[1].values() for m in ms}
            return len(roles), len(markers & set(index))

        spec_name, roles_spec = max(specs.items(), key=coverage)
    elif isinstance(spec, dict):
        spec_name, roles_spec = (
            "given",
            {r: [v] if isinstance(v, str) else list(v) for r, v in spec.items()},
        )
    else:
        spec_name, roles_spec = Path(spec).stem, load_spec(spec)
    roles = _single_roles(roles_spec, index)
    if not roles:
        expected = sorted({ms[0] for ms in roles_spec.values() if len(ms) == 1})
        raise KeypointInputError(
            f"{where}: no keypoint name is a landmark's: found {', '.join(names)}; expected "
            f"names such as {', '.join(expected)} (the {spec_name} keypoint spec)"
        )
    model = reference.model
    joints = set(reference.skeleton.names)
    order = []
    for part in read_parts(model.parts_path).values():
        for role in (part["from"], part["to"]):
            if role not in order:
                order.append(role)
    matches: list[KeypointMatch] = []
    used_columns: set[int] = set()
    used_joints: set[str] = set()
    for role in order:
        col = roles.get(role)
        points = model.mapping.get(role, [])
        if col is None or col in used_columns or len(points) != 1:
            continue
        point = points[0]
        if joint_of_point(point)[1] or point not in joints or point in used_joints:
            continue
        matches.append(KeypointMatch(col, names[col], role, point))
        used_columns.add(col)
        used_joints.add(point)
    if not matches:
        listed = ", ".join(f"{r}: {'+'.join(model.mapping.get(r, ['-']))}" for r in roles)
        raise KeypointInputError(
            f"{where}: the keypoints name the roles {', '.join(roles)}, but {reference.name} "
            f"places none of them on exactly one joint ({listed})"
        )
    return sorted(matches, key=lambda m: m.column), spec_name


# -- choosing the person, framing, scaling --------------------------------------------------
def _to_working(people: np.ndarray, scale: float) -> np.ndarray:
    """``(..., K, 3)`` file pixels -> working pixels (NaN and confidence kept)."""
    out = people.copy()
    out[..., :2] = (out[..., :2] + 0.5) * scale - 0.5
    return out


def _confident(p: np.ndarray) -> np.ndarray:
    return np.isfinite(p).all(-1) & (p[..., 2] > 0)


def _inside(p: np.ndarray, mask: np.ndarray) -> float:
    """Confidence of the keypoints ``(K, 3)`` (working pixels) on the ``mask``."""
    ok = _confident(p)
    if not ok.any():
        return 0.0
    h, w = mask.shape
    u = np.rint(p[ok, 0]).astype(np.int64)
    v = np.rint(p[ok, 1]).astype(np.int64)
    within = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    hit = np.zeros(len(u), dtype=bool)
    hit[within] = mask[v[within], u[within]]
    return float((p[ok, 2] * hit).sum())


def _nearest(frame: np.ndarray, previous: np.ndarray) -> int | None:
    """The detection of ``frame (n, K, 3)`` nearest to ``previous (K, 3)`` (mean distance of
    the keypoints both have), if within half the previous one's bounding-box diagonal."""
    prev_ok = _confident(previous)
    if not prev_ok.any():
        return None
    box = previous[prev_ok, :2]
    reach = 0.5 * max(float(np.linalg.norm(box.max(0) - box.min(0))), 1.0)
    best, best_d = None, math.inf
    for i, p in enumerate(frame):
        both = prev_ok & _confident(p)
        if both.any():
            d = float(np.linalg.norm(p[both, :2] - previous[both, :2], axis=-1).mean())
            if d < best_d:
                best, best_d = i, d
    return best if best_d <= reach else None


def _choose(people: list[np.ndarray], silhouette: np.ndarray, person: int | None) -> np.ndarray:
    """One detection per frame: ``people`` (per frame ``(n, K, 3)`` working pixels),
    ``silhouette`` ``(T', H, W)`` bool -> ``(T', K, 3)`` (NaN: nobody)."""
    k = people[0].shape[1] if people else 0
    out = np.full((len(people), k, 3), np.nan)
    if person is not None:
        for t, frame in enumerate(people):
            if person < len(frame):
                out[t] = frame[person]
        return out
    h, w = silhouette.shape[1:]
    r = max(2, round(INSIDE_FRACTION * max(h, w)))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)
    previous = None
    for t, frame in enumerate(people):
        if len(frame) == 0:
            continue
        mask = silhouette[t]
        if mask.any():
            mask = cv2.dilate(mask.astype(np.uint8), kernel) > 0
            scores = [_inside(p, mask) for p in frame]
            best = int(np.argmax(scores))
            pick = best if scores[best] > 0 else None
        else:  # no silhouette this frame: follow the previous choice
            pick = None if previous is None else _nearest(frame, previous)
        if pick is not None:
            out[t] = previous = frame[pick]
    return out


def _video_frame_count(path: Path) -> int:
    """Frames the container says the video has (0: unknown or not a readable file)."""
    if not path.is_file():
        return 0
    cap = cv2.VideoCapture(str(path))
    try:
        return int(max(cap.get(cv2.CAP_PROP_FRAME_COUNT), 0)) if cap.isOpened() else 0
    finally:
        cap.release()


def _check_frames(
    cam: CameraKeypoints, video: VideoInput, c: int, frames: np.ndarray, step: int
) -> None:
    """The file covers the kept video frames ``frames``; a whole-video file has the video
    file's frame count (where the container says it); a declared rate is the video's."""
    last = cam.first_frame + cam.num_frames - 1
    name = video.paths[c].name if c < len(video.paths) else f"camera {c}"
    if frames[0] < cam.first_frame or frames[-1] > last:
        raise KeypointInputError(
            f"{cam.path}: keypoints for video frames {cam.first_frame}..{last} "
            f"({cam.num_frames} frames) but the video's {len(frames)} frames are "
            f"{frames[0]}..{frames[-1]} (every {step}) of {name}; the keypoints must cover "
            "every video frame kept"
        )
    if cam.whole_video and c < len(video.paths):
        total = _video_frame_count(Path(video.paths[c]))
        if total and total != cam.num_frames:
            raise KeypointInputError(
                f"{cam.path}: {cam.num_frames} frames of keypoints but {name} has {total} "
                "frames; the keypoints must come from this very video"
            )
    video_rate = video.features.frame_rate * step
    if cam.rate is not None and abs(cam.rate - video_rate) > 0.01 * video_rate:
        raise KeypointInputError(
            f"{cam.path}: keypoints at {cam.rate:g} frames/s but {name} runs at "
            f"{video_rate:g}; the keypoints must come from this very video"
        )


def attach_keypoints(
    video: VideoInput,
    source: str | Path | Sequence[str | Path],
    reference: Reference,
    person: int | None = None,
    *,
    start: int | None = None,
    step: int | None = None,
    convention: str | None = None,
    spec: str | Path | dict[str, list[str]] | None = None,
) -> VideoInput:
    """The video with 2-D joints from files as its keypoint observation.

    Args:
        video: the videos read (:func:`motion.registration.video.features_from_videos`).
        source: the keypoint files (see the module's docstring), one camera each, in the
            order of the videos.
        reference: the reference the keypoints are matched to (:func:`match_keypoints`).
        person: index into each OpenPose file's ``people``, or ``None``: the detection on
            the tracked silhouette, frame by frame (a TRC holds one person: ``None`` or 0).
        start, step: the first video frame kept and the step between kept frames, as the
            video's settings (:class:`~motion.registration.video.VideoSettings`) read them
            (``None``: the ``video``'s own :attr:`VideoInput.start` / ``step``);
            the number kept is the video's.
        convention: the OpenPose JSON keypoint set (a :data:`KEYPOINT_SETS` name), or
            ``None`` to tell it from the files.
        spec: the keypoint spec mapping roles to keypoint names (see :func:`match_keypoints`).

    Returns:
        A :class:`VideoInput` whose ``features.observation.keypoints`` is ``(1, T', C, K, 3)``
        (working pixels, confidence in [0, 1]; missing: 0, 0, 0), ``features.keypoint_joints``
        the K matched joints, and ``note`` extended with what was read.

    Raises:
        KeypointInputError: naming the file: unreadable files, another number of cameras
            than the videos', keypoints that do not cover the video's frames (or not as
            many frames as the video file has), another frame rate, another marker set
            (no keypoint name matches a role), no matched joint, a bad ``person``.
    """
    start = int(video.start if start is None else start)
    step = int(video.step if step is None else step)
    if start < 0 or step < 1:
        raise KeypointInputError(f"start must be >= 0 and step >= 1; got {start}, {step}")
    if person is not None and (
        isinstance(person, bool) or not isinstance(person, int) or person < 0
    ):
        raise KeypointInputError(f"person must be an index >= 0 or None; got {person!r}")
    features = video.features
    cams = read_keypoint_source(source, convention)
    c = features.cameras.num_cameras
    if len(cams) != c:
        videos = ", ".join(Path(p).name for p in video.paths) or features.name
        where = source if isinstance(source, str | Path) else ", ".join(map(str, source))
        raise KeypointInputError(
            f"{where}: keypoints for {len(cams)} camera(s) "
            f"({', '.join(cam.path.name for cam in cams)}) but {c} video(s) ({videos}); give "
            "one keypoint folder or file per video, in the videos' order"
        )
    names = cams[0].names
    for cam in cams[1:]:
        if [canonical_name(n) for n in cam.names] != [canonical_name(n) for n in names]:
            raise KeypointInputError(
                f"{cam.path}: keypoints {', '.join(cam.names)} but {cams[0].path.name} has "
                f"{', '.join(names)}; every camera needs the same keypoint set"
            )
    for cam in cams:
        if cam.path.is_file() and person not in (None, 0):
            raise KeypointInputError(
                f"{cam.path}: a TRC file holds one person; pass that person's file "
                f"(person={person})"
            )
    matches, spec_name = match_keypoints(names, reference, spec, where=str(cams[0].path))
    columns = [m.column for m in matches]
    t = features.num_frames
    frames = start + step * np.arange(t)
    sil = features.observation.silhouette[0] > 0.5  # (T', C, H, W)
    out = np.zeros((t, c, len(columns), 3))
    notes = [video.note] if video.note else []
    for i, cam in enumerate(cams):
        _check_frames(cam, video, i, frames, step)
        people = [
            _to_working(cam.people[f - cam.first_frame][:, columns], video.scale) for f in frames
        ]
        chosen = _choose(people, sil[:, i].numpy(), None if cam.path.is_file() else person)
        ok = _confident(chosen)
        out[:, i][ok] = np.concatenate([chosen[ok, :2], np.clip(chosen[ok, 2:], 0.0, 1.0)], -1)
        if cam.note:
            notes.append(cam.note)
    which = "person " + str(person) if person is not None else "the person on the silhouette"
    notes.append(
        f"2-D keypoints from {', '.join(cam.path.name for cam in cams)} ({spec_name} names; "
        f"{which}): {len(matches)} joints matched "
        f"({', '.join(f'{m.keypoint}={m.joint}' for m in matches)})"
    )
    kp = torch.from_numpy(out).to(features.observation.silhouette.dtype)[None]
    obs = dataclasses.replace(features.observation, keypoints=kp)
    features = dataclasses.replace(
        features, observation=obs, keypoint_joints=[m.joint for m in matches]
    )
    return dataclasses.replace(video, features=features, note="; ".join(notes))
