"""Perception: a person detector's 2-D joints and person mask from real video frames.

:mod:`motion.perception.detector` declares what a detector is (:class:`PersonDetector`,
its settings and the registry by name); :mod:`motion.perception.mediapipe_pose` is the
bundled one (MediaPipe Pose, weights inside its wheel, so it runs offline);
:func:`detect_videos` runs one over videos and writes OpenPose-format JSON and masks that
``motion register`` reads as it reads any detector's files
(:func:`motion.registration.keypoints.attach_keypoints`), cached for reruns.

Its speed and its agreement with another detector on this project's real videos are in
docs/decisions/001-person-detector.md and 004-tuning-evidence.md
(``benchmarks/bench_perception.py --accuracy`` reruns every figure).
"""

from motion.perception.detector import (
    DETECTORS,
    DetectorUnavailable,
    PerceptionSettings,
    PerceptionSettingsError,
    PersonDetection,
    PersonDetector,
    make_detector,
    register_detector,
)
from motion.perception.mediapipe_pose import MediaPipePose
from motion.perception.run import CameraDetections, DetectionRun, detect_videos, read_masks

__all__ = [
    "DETECTORS",
    "CameraDetections",
    "DetectionRun",
    "DetectorUnavailable",
    "MediaPipePose",
    "PerceptionSettings",
    "PerceptionSettingsError",
    "PersonDetection",
    "PersonDetector",
    "detect_videos",
    "make_detector",
    "read_masks",
    "register_detector",
]
