"""Person detection throughput on the bundled real videos: frames per second.

The frames are decoded and downscaled to ``--width`` (640 px: the detector's default) first,
then timed, each on the same frames in the same run:

* MediaPipe Pose with its person mask (``motion.perception.MediaPipePose``, the default of
  ``motion register``), and without the mask (MediaPipe's own graph, segmentation off);
* the anchor: OpenCV's MOG2 background subtraction alone (what ``motion register`` did
  before it had a detector), and the full :func:`motion.perception.detect_videos` run
  (decoding the native frames, resizing, writing the files) for the end-to-end figure.

The target of issue 36: >= 15 frames per second at 640 px wide on 2 cores.

With ``--accuracy`` it also scores the detector's joints (:func:`detect_videos` with the
defaults, as ``motion register`` runs it) against the Pose2Sim trial's own OpenPose BODY_25B
keypoints, an independent detector: per camera and joint, the median distance in the
videos' pixels to the nearest OpenPose person, both confident (MediaPipe visibility > 0.5,
OpenPose > 0.3), with JSON file ``i`` taken for video frame ``i`` (as ``--keypoints`` reads
them) and, for comparison, for frame ``i + 1``.

Usage: python benchmarks/bench_perception.py [--frames 100] [--width 640] [--threads 2]
       [--accuracy] [--quick] [--json PATH]

``--quick``: 20 frames. ``--json PATH``: also write the throughput figures as rows for
``benchmarks/report.py`` (docs/benchmarks.md).
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
from report import parse_args, write_rows  # benchmarks/report.py, beside this script

from motion.keypoints import BODY_25B, MEDIAPIPE_POSE_33
from motion.perception import MediaPipePose, PerceptionSettings, detect_videos
from motion.registration.keypoints import read_openpose_people

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SHARED = DATA / "video"
OPENPOSE = DATA / "keypoints" / "pose2sim_balancing_trial" / "pose2d_openpose_body25b"
#: the joints both detectors have (MediaPipe's and OpenPose's hips follow other conventions)
JOINTS = ["LShoulder", "RShoulder", "LElbow", "RElbow", "LWrist", "RWrist", "LHip", "RHip",
          "LKnee", "RKnee", "LAnkle", "RAnkle"]  # fmt: skip
#: ``--quick``: fewer frames
QUICK = {"frames": 20}
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


def gaps_to_openpose(ours, theirs, frames: int, shift: int) -> np.ndarray:
    """``(F, J)`` pixel distances (NaN: not both confident) of our joints at video frame
    ``f`` to OpenPose's file ``f - shift``'s nearest person."""
    mp = [MEDIAPIPE_POSE_33.index(k) for k in JOINTS]
    op = [BODY_25B.index(k) for k in JOINTS]
    rows = []
    for f in range(max(0, shift), min(frames, theirs.num_frames + shift)):
        row = np.full(len(JOINTS), np.nan)
        people = theirs.people[f - shift][:, op]
        if len(ours.people[f]) and len(people):
            mine = ours.people[f][0, mp]
            near = np.nanmedian(np.linalg.norm(people[..., :2] - mine[:, :2], axis=-1), 1)
            person = people[int(np.nanargmin(near))]
            ok = (mine[:, 2] > 0.5) & (person[:, 2] > 0.3)
            row[ok] = np.linalg.norm(mine[ok, :2] - person[ok, :2], axis=-1)
        rows.append(row)
    return np.array(rows)


def accuracy(frames: int, width: int) -> None:
    cams = sorted(OPENPOSE.glob("cam*_json"))
    videos = [SHARED / "pose2sim_balancing_trial" / f"{c.name[:-5]}.mp4" for c in cams]
    with tempfile.TemporaryDirectory() as out:
        run = detect_videos(videos, out, list(range(frames)), PerceptionSettings(width=width))
        ours = [read_openpose_people(c.folder) for c in run.cameras]
    theirs = [read_openpose_people(c) for c in cams]
    print(f"\nMediaPipe joints vs the Pose2Sim trial's OpenPose BODY_25B ({frames} frames, px)")
    table = {}
    for shift in (0, 1):
        per_cam = [gaps_to_openpose(o, t, frames, shift) for o, t in zip(ours, theirs, strict=True)]
        table[shift] = per_cam
        cells = ", ".join(
            f"{c.name[:-5]} {np.nanmedian(g):.1f}" for c, g in zip(cams, per_cam, strict=True)
        )
        every = np.concatenate(per_cam)
        no_hips = every[:, [i for i, k in enumerate(JOINTS) if "Hip" not in k]]
        print(
            f"  file i = frame i{' + 1' if shift else ''}: {cells}; all {np.nanmedian(every):.1f}"
            f", without hips {np.nanmedian(no_hips):.1f}"
        )
    every = np.concatenate(table[0])
    print("  per joint (file i = frame i): " + ", ".join(
        f"{k} {np.nanmedian(every[:, i]):.1f}" for i, k in enumerate(JOINTS)
    ))  # fmt: skip
    heights = []
    for t in theirs:
        for people in t.people[:frames]:
            for p in people:
                ok = p[:, 2] > 0.3
                if ok.sum() > 10:
                    heights.append(np.ptp(p[ok, 1]))
    print(f"  the tallest OpenPose person spans {np.percentile(heights, 90):.0f} px (90th pct)")
    print("  target (issue 36): median <= 8 px")


def main(argv: list[str] | None = None) -> list[dict]:
    """Runs the benchmark and prints its table; returns its throughput figures as rows (see
    ``benchmarks/report.py``), also written to ``--json`` when given."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--threads", type=int, default=2, help="OpenCV threads (the machine's 2)")
    ap.add_argument("--accuracy", action="store_true", help="also score against OpenPose")
    args = parse_args(ap, QUICK, argv)
    results, notes = [], []
    cv2.setNumThreads(args.threads)
    print(f"frames/s at {args.width} px wide, {args.frames} frames, {os.cpu_count()} cores")
    print(
        f"{'video':32s} {'mediapipe+mask':>15s} {'mediapipe':>10s} {'MOG2':>8s} {'end-to-end':>11s}"
    )
    for name, path in VIDEOS.items():
        if not path.is_file():
            print(f"{name:32s} (missing: {path})")
            notes.append(f"{name}: not measured (missing: {path})")
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
        case = f"{name}, {len(frames)} frames at {args.width} px wide"
        anchor = "OpenCV MOG2 background subtraction"
        results += [
            dict(case=case, ours="MediaPipe Pose with its person mask", value=with_mask,
                 anchor=anchor, anchor_value=subtraction, units="frames/s", better="higher"),
            dict(case=case, ours="MediaPipe Pose without the mask", value=without,
                 anchor=anchor, anchor_value=subtraction, units="frames/s", better="higher"),
            dict(case=case, ours="detect_videos end to end (decode, resize, write)",
                 value=run.frames_per_second, anchor=None, anchor_value=None,
                 units="frames/s", better="higher"),
        ]  # fmt: skip
    print("target: mediapipe+mask >= 15 frames/s (issue 36)")
    if args.accuracy:
        accuracy(args.frames, args.width)
    return write_rows(args.json, results, notes)


if __name__ == "__main__":
    main()
