"""Perception: a person detector's 2-D joints and person mask from real video frames.

:mod:`motion.perception.detector` declares what a detector is (:class:`PersonDetector`,
its settings and the registry by name); :mod:`motion.perception.mediapipe_pose` is the
bundled one (MediaPipe Pose, weights inside its wheel, so it runs offline);
:func:`detect_videos` runs one over videos and writes OpenPose-format JSON and masks that
``motion register`` reads as it reads any detector's files
(:func:`motion.registration.keypoints.attach_keypoints`), cached for reruns.

Measured on this project's real videos (2 cores, the frames downscaled to 640 px wide,
100 frames each; ``benchmarks/bench_perception.py`` reruns the speed figures): MediaPipe Pose
with its mask runs at 17 frames per second on the Pose2Sim trial's cam01 (23 without the
mask) and 20 on the Sports2D demo, where background subtraction alone runs at 76 and 296.
Against the Pose2Sim trial's own OpenPose BODY_25B keypoints (4 cameras x 100 frames, the
nearest OpenPose person, both confident) the median distance is 17 px in its 1080 x 1920
frames, about 2 % of the person's 750 px height: shoulders 12-14, elbows 14-16, wrists 15-18,
knees 14-16, ankles 15, hips 25 (the two detectors place the hip joint differently).
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
