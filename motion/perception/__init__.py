"""Perception: a person detector's 2-D joints and person mask from real video frames.

:mod:`motion.perception.detector` declares what a detector is (:class:`PersonDetector`,
its settings and the registry by name); :mod:`motion.perception.mediapipe_pose` is the
bundled one (MediaPipe Pose, weights inside its wheel, so it runs offline);
:func:`detect_videos` runs one over videos and writes OpenPose-format JSON and masks that
``motion register`` reads as it reads any detector's files
(:func:`motion.registration.keypoints.attach_keypoints`), cached for reruns.

Measured on this project's real videos (2 cores, frames downscaled to 640 px wide, 100
frames each; ``benchmarks/bench_perception.py --accuracy`` reruns every figure): MediaPipe
Pose with its mask runs at 22 frames per second on the Pose2Sim trial's cam01 and 24 on the
Sports2D demo (14-16 end to end, decoding the native frames included), where background
subtraction alone runs at 83 and 300. Against the Pose2Sim trial's own OpenPose BODY_25B
keypoints (4 cameras x 100 frames, the nearest OpenPose person, both confident) the median
distance is 13.7 px without the hips in its 1080 x 1920 frames, about 1.7 % of the person's
780 px height (shoulders 12-13, elbows 13-14, wrists 14-16, knees 13-14, ankles 13-14); the
hips are 24 px apart (the two detectors place the hip joint differently).
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
