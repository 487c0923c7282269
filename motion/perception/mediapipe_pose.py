"""MediaPipe Pose (BlazePose GHUM, "full" model) as a :class:`PersonDetector`.

The ``mediapipe`` 0.10.14 wheel carries the legacy ``solutions.pose`` graph with its pose
detector and its full landmark model (``pose_landmark_full.tflite``) inside, so it runs
offline; its lite and heavy landmark models are downloaded on first use, so only
``model_complexity=1`` is used here. One person per frame: the detector finds a person, then
follows them from frame to frame (the region of interest from the previous landmarks) until
its tracking score drops under ``min_tracking_confidence``.

Per landmark the confidence is MediaPipe's *visibility* (the probability that the point is
in view and not occluded); pixels are ``u = x W - 0.5``, ``v = y H - 0.5`` from its
normalised ``x, y`` (0 and 1 at the image's outer edges). The mask is its segmentation
output, the probability that a pixel is the person's. MediaPipe's smoothing over frames is
off unless ``smooth`` is set (it lags the movement).

Installed without its dependencies (it pins ``opencv-contrib-python``, which would shadow
``opencv-python-headless``): the ``perception`` extra has what it imports.
"""

from __future__ import annotations

import warnings
from typing import ClassVar

import numpy as np

from motion.features import native_stderr_silenced
from motion.perception.detector import (
    DetectorUnavailable,
    PerceptionSettings,
    PersonDetection,
    PersonDetector,
    register_detector,
)

__all__ = ["INSTALL", "MediaPipePose"]

#: how to install the detector (the Makefile does it)
INSTALL = (
    "pip install -e '.[perception]' && pip install --no-deps mediapipe==0.10.14 (the "
    "Makefile's set-up does both)"
)
#: the version the wheel must have: later wheels no longer bundle the legacy models
VERSION = "0.10.14"


def _pose_module():
    """``mediapipe.python.solutions.pose``, or :class:`DetectorUnavailable` saying why."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import mediapipe
            from mediapipe.python.solutions import pose
    except ImportError as err:
        raise DetectorUnavailable(
            f"the mediapipe person detector is not installed ({err}); install it with "
            f"{INSTALL}, or give 2-D joints with --keypoints, or turn detection off with "
            "perception.detector=none"
        ) from None
    if mediapipe.__version__ != VERSION:
        raise DetectorUnavailable(
            f"mediapipe {mediapipe.__version__} is installed but the detector needs "
            f"{VERSION}, whose wheel bundles the pose models (later ones download them); "
            f"install it with {INSTALL}"
        )
    return pose


@register_detector
class MediaPipePose(PersonDetector):
    """MediaPipe Pose: 33 landmarks (:data:`motion.keypoints.MEDIAPIPE_POSE_33`) and a soft
    person mask per frame, one person."""

    name: ClassVar[str] = "mediapipe"
    keypoint_set: ClassVar[str] = "mediapipe33"
    spec: ClassVar[str] = "mediapipe_pose33"
    gives_mask: ClassVar[bool] = True
    version: ClassVar[str] = f"mediapipe {VERSION} pose_landmark_full"

    def __init__(self, settings: PerceptionSettings | None = None):
        self.settings = PerceptionSettings() if settings is None else settings
        self._pose = _pose_module()
        self._graph = None

    def _start(self):
        with native_stderr_silenced():  # TensorFlow Lite's start-up lines
            return self._pose.Pose(
                static_image_mode=False,
                model_complexity=1,
                smooth_landmarks=self.settings.smooth,
                enable_segmentation=True,
                smooth_segmentation=self.settings.smooth,
                min_detection_confidence=self.settings.min_detection_confidence,
                min_tracking_confidence=self.settings.min_tracking_confidence,
            )

    def detect(self, rgb: np.ndarray) -> list[PersonDetection]:
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(
                f"detect needs an (H, W, 3) uint8 RGB frame; got {rgb.shape} {rgb.dtype}"
            )
        first = self._graph is None
        if first:
            self._graph = self._start()
        with warnings.catch_warnings():
            # protobuf 5 deprecates the message API MediaPipe's packet reader calls
            warnings.simplefilter("ignore", UserWarning)
            if first:
                with native_stderr_silenced():
                    result = self._graph.process(np.ascontiguousarray(rgb))
            else:
                result = self._graph.process(np.ascontiguousarray(rgb))
        if result.pose_landmarks is None:
            return []
        h, w = rgb.shape[:2]
        points = np.array(
            [(p.x * w - 0.5, p.y * h - 0.5, p.visibility) for p in result.pose_landmarks.landmark],
            dtype=np.float64,
        )
        points[:, 2] = np.clip(points[:, 2], 0.0, 1.0)
        mask = result.segmentation_mask
        mask = None if mask is None else np.clip(np.asarray(mask, dtype=np.float32), 0.0, 1.0)
        return [PersonDetection(points, mask)]

    def reset(self) -> None:
        self.close()

    def close(self) -> None:
        if self._graph is not None:
            self._graph.close()
            self._graph = None
