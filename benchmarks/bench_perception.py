"""Person detection throughput on the bundled real videos: frames per second.

The frames are decoded and downscaled to ``--width`` (640 px: the detector's default) first,
then timed, each on the same frames in the same run:

* MediaPipe Pose with its person mask (``motion.perception.MediaPipePose``, the default of
  ``motion register``), and without the mask (MediaPipe's own graph, segmentation off);
* the anchor: OpenCV's MOG2 background subtraction alone (what ``motion register`` did
  before it had a detector), and the full :func:`motion.perception.detect_videos` run
  (decoding the native frames, resizing, writing the files) for the end-to-end figure.

The target of issue 36: >= 15 frames per second at 640 px wide on 2 cores.

Usage: python benchmarks/bench_perception.py [--frames 100] [--width 640] [--threads 2]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import warnings
from pathlib import Path

import cv2
import numpy as np

from motion.perception import MediaPipePose, PerceptionSettings, detect_videos

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "video"
VIDEOS = {
    "pose2sim cam01 (1080 x 1920)": SHARED / "pose2sim_balancing_trial" / "cam01.mp4",
    "sports2d demo (1768 x 994)": SHARED / "sports2d_demo" / "demo.mp4",
}


def frames_at(path: Path, count: int, width: int) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    out = []
    while len(out) < count:
        ok, frame = cap.read()
        if not ok:
            break
        h, w = frame.shape[:2]
        s = min(1.0, width / w)
        if s < 1.0:
            frame = cv2.resize(frame, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
        out.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    cap.release()
    return out


def rate(fn, frames: list[np.ndarray]) -> float:
    fn(frames[0])  # start-up (graph, delegate) outside the timing
    start = time.perf_counter()
    for f in frames:
        fn(f)
    return len(frames) / (time.perf_counter() - start)


def mediapipe_without_mask():
    from mediapipe.python.solutions import pose

    graph = pose.Pose(static_image_mode=False, model_complexity=1, enable_segmentation=False)

    def run(frame):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            graph.process(frame)

    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--threads", type=int, default=2, help="OpenCV threads (the machine's 2)")
    args = ap.parse_args()
    cv2.setNumThreads(args.threads)
    print(f"frames/s at {args.width} px wide, {args.frames} frames, {os.cpu_count()} cores")
    print(
        f"{'video':32s} {'mediapipe+mask':>15s} {'mediapipe':>10s} {'MOG2':>8s} {'end-to-end':>11s}"
    )
    for name, path in VIDEOS.items():
        if not path.is_file():
            print(f"{name:32s} (missing: {path})")
            continue
        frames = frames_at(path, args.frames, args.width)
        with MediaPipePose() as detector:
            with_mask = rate(detector.detect, frames)
        without = rate(mediapipe_without_mask(), frames)
        mog2 = cv2.createBackgroundSubtractorMOG2()
        subtraction = rate(mog2.apply, frames)
        with tempfile.TemporaryDirectory() as out:
            run = detect_videos(
                [path], out, list(range(len(frames))), PerceptionSettings(width=args.width)
            )
        print(
            f"{name:32s} {with_mask:15.1f} {without:10.1f} {subtraction:8.1f} "
            f"{run.frames_per_second:11.1f}"
        )
    print("target: mediapipe+mask >= 15 frames/s (issue 36)")


if __name__ == "__main__":
    main()
