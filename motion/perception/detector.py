"""The person detector's interface, its settings and the registry of detectors by name.

A detector is a class deriving from :class:`PersonDetector` that declares what it gives --
its keypoint set (a :data:`motion.registration.keypoints.KEYPOINT_SETS` name), its keypoint
spec (a ``motion/data/bodyparts`` file mapping landmark roles to its names) and whether it
gives a person mask -- and implements :meth:`PersonDetector.detect` on one RGB frame. Names
reach :func:`make_detector` through :func:`register_detector`; what a detector declares is
checked when it is registered, not discovered while frames are processed.

Pixels: ``u`` right, ``v`` down, integer coordinates at pixel centres (OpenCV's), in the
frame the detector was given.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from motion.registration.types import RegistrationError
from motion.settings import SettingError, Settings, setting

__all__ = [
    "DETECTORS",
    "DetectorUnavailable",
    "PerceptionSettings",
    "PerceptionSettingsError",
    "PersonDetection",
    "PersonDetector",
    "make_detector",
    "register_detector",
]


class DetectorUnavailable(RegistrationError):
    """A detector whose package or model is not installed (the message says how to install
    it, or to run without it)."""


class PerceptionSettingsError(SettingError):
    """A perception setting outside its type or range."""


@dataclass(frozen=True)
class PerceptionSettings(Settings):
    """What the person detector of ``motion register`` does (every field checked at
    construction)."""

    setting_error: ClassVar[type[SettingError]] = PerceptionSettingsError

    detector: str | None = setting(
        "mediapipe",
        "2-D joints and the person's mask from each frame when no --keypoints are given: "
        "mediapipe (MediaPipe Pose, whose weights ship in its wheel) or none (silhouettes "
        "from background subtraction only)",
        choices=("mediapipe",),
    )
    width: int = setting(
        640,
        "frames are downscaled to this width (never upscaled) before detection; the joints "
        "are written in the video's own pixels",
        ge=64,
        le=8192,
    )
    min_detection_confidence: float = setting(
        0.5, "a person is detected when the detector's score reaches this", ge=0, le=1
    )
    min_tracking_confidence: float = setting(
        0.5,
        "the person is followed from the previous frame while the tracking score reaches "
        "this (below it the whole frame is searched again)",
        ge=0,
        le=1,
    )
    smooth: bool = setting(
        False,
        "the detector's own smoothing of the joints and mask over frames (it lags the "
        "movement, so the joints trail the person; registration has its own temporal prior)",
    )
    fuse_mask: bool = setting(
        True,
        "the silhouette is the detector's soft person mask where it is about the background "
        "model's tracked person (its pieces touching the tracked region: shadows, "
        "reflections and bystanders dropped; motion.perception.fusion)",
    )
    mask_reach: float = setting(
        0.03,
        "the tracked region is dilated by this fraction of the image's larger side before "
        "the mask is compared with it (background subtraction loses thin limbs)",
        ge=0,
        le=1,
    )
    mask_agreement: float = setting(
        0.5,
        "the mask is about the tracked person when it and the tracked region overlap on "
        "this share of the smaller of the two (else the detector is on someone else)",
        ge=0,
        le=1,
    )
    cache: bool = setting(
        True,
        "keep the detections in the output folder's detections/ and reuse them when the "
        "videos, frames and these settings are the same",
    )


@dataclass(frozen=True)
class PersonDetection:
    """One person found in one frame.

    Attributes:
        keypoints: ``(K, 3)`` float64 ``u, v`` (frame pixels) and confidence in [0, 1], in the
            detector's keypoint order.
        mask: ``(H, W)`` float32 in [0, 1], the probability that a pixel is this person's
            (``None`` when the detector gives no mask).
    """

    keypoints: np.ndarray
    mask: np.ndarray | None = None


class PersonDetector(ABC):
    """Finds people in the frames of one video, in order (a detector may follow the person
    from frame to frame: :meth:`reset` before another video).

    Declared by each detector class:
        name: the ``detector=`` setting's value.
        keypoint_set: its keypoint set's name (:data:`motion.registration.keypoints.
            KEYPOINT_SETS`).
        spec: the keypoint spec naming its landmark roles (``motion/data/bodyparts``).
        gives_mask: whether :attr:`PersonDetection.mask` is filled.
        version: the detector and model's version (part of the detection cache's key).
    """

    name: ClassVar[str]
    keypoint_set: ClassVar[str]
    spec: ClassVar[str]
    gives_mask: ClassVar[bool] = False
    version: ClassVar[str] = ""

    @abstractmethod
    def detect(self, rgb: np.ndarray) -> list[PersonDetection]:
        """The people of one frame ``(H, W, 3)`` uint8 RGB (an empty list: nobody)."""

    def reset(self) -> None:  # noqa: B027 (a detector without state needs no reset)
        """Forget what earlier frames showed (the next frame is of another video)."""

    def close(self) -> None:  # noqa: B027 (a detector without resources has none to free)
        """Free the detector's resources."""

    def __enter__(self) -> PersonDetector:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: detector classes by their ``name`` (:func:`register_detector`)
DETECTORS: dict[str, type[PersonDetector]] = {}


def register_detector(cls: type[PersonDetector]) -> type[PersonDetector]:
    """Add a detector class to :data:`DETECTORS` (a class decorator), checking what it
    declares: a new name, a known keypoint set, a bundled spec naming every keypoint it
    maps by the set's names."""
    from motion.bodyparts import load_spec
    from motion.registration.keypoints import KEYPOINT_SETS

    for attr in ("name", "keypoint_set", "spec"):
        if not isinstance(getattr(cls, attr, None), str) or not getattr(cls, attr):
            raise TypeError(f"{cls.__name__}: a detector declares {attr} (a non-empty str)")
    if cls.name in DETECTORS:
        raise TypeError(f"{cls.__name__}: detector name {cls.name!r} is taken")
    if cls.keypoint_set not in KEYPOINT_SETS:
        raise TypeError(
            f"{cls.__name__}: keypoint_set {cls.keypoint_set!r} is not one of "
            f"{', '.join(KEYPOINT_SETS)}"
        )
    names = set(KEYPOINT_SETS[cls.keypoint_set])
    unknown = sorted({n for ns in load_spec(cls.spec).values() for n in ns} - names)
    if unknown:
        raise TypeError(
            f"{cls.__name__}: spec {cls.spec} names {', '.join(unknown)}, not in the "
            f"{cls.keypoint_set} keypoints"
        )
    DETECTORS[cls.name] = cls
    return cls


def make_detector(settings: PerceptionSettings) -> PersonDetector:
    """The detector ``settings.detector`` names, made with ``settings``.

    Raises:
        DetectorUnavailable: its package is not installed (how to install it in the message).
        PerceptionSettingsError: ``detector=None`` (there is nothing to make).
    """
    if settings.detector is None:
        raise PerceptionSettingsError("make_detector: detector=none makes no detector")
    factory: Callable[[PerceptionSettings], PersonDetector] = DETECTORS[settings.detector]
    return factory(settings)
