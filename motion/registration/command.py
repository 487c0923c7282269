"""``python -m motion register``: videos and a reference BVH in, the registration's files out.

:func:`run_register` is the whole job, in order: read the settings, check the output folder
can be written, read the reference and the calibration (one camera per video), check the
reference is long enough for the videos as their containers describe them, turn the videos
into features, check that they fit together (durations, cameras), register (progress bars
per stage), then write every output into a staging folder inside ``out`` and move the files
into place only when all of them are written -- bad input never leaves a partial result that
looks like one (nor an output folder the run created).

Outputs (:data:`OUTPUT_FILES`): ``registration.npz``, ``summary.json``, ``student.bvh``,
``joint_angles.csv``, ``joint_angles.mot``, ``overlay_<camera>.mp4`` per camera and
``report.html``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from motion.bodyparts import BodyPartMappingError
from motion.cameras import CameraRig, load_pose2sim_calibration
from motion.draw import write_video
from motion.features import native_stderr_silenced
from motion.perception.fusion import fuse_silhouettes
from motion.perception.run import DetectionRun, detect_videos, masks_at
from motion.registration.cameras import initialise_cameras
from motion.registration.config import RegisterConfig, load_config, settings_dict
from motion.registration.export import (
    TRUSTED_FIT,
    RegistrationSummary,
    joint_angles,
    joints_trusted,
    leg_lengths_m,
    proportion_words,
    save_registration,
    student_kinematics,
    summarise,
    write_joint_angles_csv,
    write_mot,
    write_student_bvh,
)
from motion.registration.keypoints import attach_keypoints
from motion.registration.movement import check_movement
from motion.registration.pipeline import register
from motion.registration.render import body_poses, points_in_view, side_by_side_frames
from motion.registration.report import ReportInputs, write_report
from motion.registration.types import Reference, Registration, RegistrationError
from motion.registration.video import (
    VideoInput,
    VideoSettings,
    features_from_videos,
    with_silhouettes,
)

__all__ = ["OUTPUT_FILES", "RegisterJob", "RegisterOutcome", "run_register", "summary_lines"]

#: overlay videos are at least this many pixels high: working frames (often 240 px) are
#: upscaled and the bodies drawn at that size, so a knee can be seen
OVERLAY_MIN_HEIGHT = 720

#: what each output file is, for the report and the summary
OUTPUT_FILES = {
    "registration.npz": "C, T and A per video frame, fit, G (numpy arrays)",
    "summary.json": "the numbers of the summary, per-joint differences, settings, timings",
    "student.bvh": "the recovered motion on the reference skeleton (any BVH viewer)",
    "joint_angles.csv": "per frame and clinical joint angle (OpenSim names): reference, student, "
    "difference, its uncertainty and the method's error",
    "joint_angles.mot": "the same as an OpenSim-style motion table",
    "report.html": "this report",
}

#: the shortest reference, relative to the video's duration, that registration accepts: the
#: monotone C can play the reference at most this many times slower than real time
MIN_REFERENCE_FRACTION = 0.4


@dataclass(frozen=True)
class RegisterJob:
    """One ``motion register`` run.

    Attributes:
        reference: the reference BVH.
        videos: one video per camera (synchronised).
        out: the output folder (created).
        calibration: a Pose2Sim-style ``calibration.toml`` (``None``: one uncalibrated camera).
        config: a YAML file of settings (``None``: defaults).
        overrides: ``key=value`` settings (after ``config``).
        person: ``(x, y)`` pixels near the person to follow in the first frame.
        backgrounds: a picture of each camera's empty scene (a clean plate), or none.
        keypoints: 2-D joints from files, one folder or file per camera in the videos' order
            (:func:`motion.registration.keypoints.attach_keypoints`), or none.
    """

    reference: Path
    videos: list[Path]
    out: Path
    calibration: Path | None = None
    config: Path | None = None
    overrides: tuple[str, ...] = ()
    person: tuple[float, float] | None = None
    backgrounds: tuple[Path, ...] = ()
    keypoints: tuple[Path, ...] = ()


@dataclass(frozen=True)
class RegisterOutcome:
    """What a run wrote: the result, its summary and the files (name -> path)."""

    registration: Registration
    summary: object
    files: dict[str, Path]


def _missing_folders(out: Path) -> list[Path]:
    """``out`` and its ancestors that do not exist yet, deepest first (the folders a run
    creates, and removes again if it fails before writing anything)."""
    out = out.absolute()
    missing = []
    for p in [out, *out.parents]:
        if p.exists() or p.is_symlink():
            break
        missing.append(p)
    return missing


def _check_writable(out: Path) -> None:
    """Create ``out`` (and its parents) and write a file there, or say why not."""
    for p in [out, *out.parents]:
        if p.exists() and not p.is_dir():
            what = "is" if p == out else f"cannot be created: {p} is"
            raise RegistrationError(
                f"{out}: the output folder {what} a file, not a folder; give another --out"
            )
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out, prefix=".write-test-"):
            pass
    except OSError as err:
        raise RegistrationError(
            f"{out}: the output folder cannot be written ({err.strerror or err})"
        ) from None


def _remove_if_empty(folders: list[Path]) -> None:
    """Remove the ``folders`` (deepest first) that a failed run created, if still empty."""
    for p in folders:
        try:
            p.rmdir()
        except OSError:
            return


def _read_reference(path: Path) -> Reference:
    try:
        return Reference.from_bvh(path)
    except BodyPartMappingError as err:
        # the mapper's advice to pass a spec file is for `motion info --spec`: register
        # reads the joints by their names only
        why = " ".join(str(err).split()).split(" Pass a spec file")[0].rstrip(". ")
        raise RegistrationError(
            f"{path}: its joints do not give every body part the body spec needs ({why}); "
            "motion register needs a human skeleton whose joint names a bundled body-part "
            "spec knows (motion/data/bodyparts/); `python -m motion info "
            f"{path}` shows its skeleton and what maps"
        ) from None


def _read_rig(path: Path | None, videos: list[Path]) -> CameraRig | None:
    """The calibration's cameras, one per video, checked here before any video is decoded:
    the file as it reads (:func:`motion.cameras.load_pose2sim_calibration`), the rig as stage
    0 checks a given calibration (:func:`motion.registration.cameras.initialise_cameras`,
    route 1: intrinsics, rotations, finite values, image sizes, unique names), then one
    camera per video; every error a line naming the file. Whether each video's frame size
    matches its camera's ``size`` is checked when the videos are read
    (:func:`motion.features.read_camera_videos`, naming the video)."""
    if path is None:
        return None
    rig = load_pose2sim_calibration(path)
    try:
        rig = initialise_cameras(rig).rig
    except RegistrationError as err:
        raise RegistrationError(f"{path}: {err}") from None
    if rig.num_cameras != len(videos):
        raise RegistrationError(
            f"{path}: the calibration has {rig.num_cameras} camera(s) ({', '.join(rig.names)}) "
            f"but {len(videos)} video(s) were given ({', '.join(p.name for p in videos)}); "
            "give one --video per calibrated camera, in the calibration's order"
        )
    return rig


def _container_frames(path: Path, settings: VideoSettings) -> tuple[int, float] | None:
    """The frames kept and their rate as the video's container says (``None`` when it
    does not say, or the file cannot be opened: :func:`features_from_videos` then reports
    it), from ``start``, ``count``, ``step`` and ``frame_rate`` -- without decoding."""
    if not path.is_file():
        return None
    with native_stderr_silenced():  # a bad file is reported once, by the reader proper
        cap = cv2.VideoCapture(str(path))
        try:
            if not cap.isOpened():
                return None
            total = int(max(cap.get(cv2.CAP_PROP_FRAME_COUNT), 0))
            fps = float(cap.get(cv2.CAP_PROP_FPS))
        finally:
            cap.release()
    rate = settings.frame_rate or (fps if math.isfinite(fps) else 0.0)
    if total <= 0 or not rate > 0:
        return None
    kept = len(range(settings.start, total, settings.step))
    if settings.count is not None:
        kept = min(kept, settings.count)
    return kept, rate / settings.step


def _check_durations(reference: Reference, frames: int, rate: float, slack: float = 1.0) -> None:
    """The reference must last at least :data:`MIN_REFERENCE_FRACTION` of the video's
    ``frames`` at ``rate`` (``slack`` < 1 tolerates a container's estimated count)."""
    ref_s = reference.num_frames / reference.frame_rate
    vid_s = frames / rate
    if frames and ref_s < MIN_REFERENCE_FRACTION * vid_s * slack:
        most = int(ref_s / MIN_REFERENCE_FRACTION * rate)
        raise RegistrationError(
            f"{reference.name}: the reference lasts {ref_s:.2f} s but the video {vid_s:.2f} s: "
            f"it can be aligned to at most about {most} of the {frames} video frames, "
            f"and the rest would not be aligned; choose the video's stretch with "
            f"video.start= and video.count= (e.g. video.count={most})"
        )


def _progress(enabled: bool) -> Callable[[Iterable, str, int], Iterator]:
    def bar(items: Iterable, desc: str, total: int | None = None) -> Iterator:
        return iter(tqdm(items, desc=desc, total=total, disable=not enabled, file=sys.stderr))

    return bar


def _log(enabled: bool) -> Callable[[str], None]:
    def write(message: str) -> None:
        if enabled:
            tqdm.write(message, file=sys.stderr)

    return write


def _write_outputs(
    stage: Path,
    job: RegisterJob,
    cfg: RegisterConfig,
    reference: Reference,
    video: VideoInput,
    reg: Registration,
    show: bool,
    detection: DetectionRun | None = None,
):
    rate = video.features.frame_rate
    rig = video.features.cameras
    angles = joint_angles(reg, reference, rate, video.start, video.step)
    seen = points_in_view(rig, student_kinematics(reg, reference).positions)
    movement = check_movement(
        reg.C,
        reg.T_translation,
        reference.root,
        reference.frame_rate,
        rate,
        reg.G,
        cfg.movement,
        legs_m=leg_lengths_m(reg, reference),
        in_view=video.features.within_sides(),
    )
    if len(video.held) == len(video.paths):  # no camera saw the whole body: say so by each reason
        names = ", ".join(p.name for p in video.held)
        movement = movement.read_from(
            f"read from silhouettes that miss parts of the body (the warning on {names})"
        )
    # a frame is trusted where its fit is good, the coordinate's bones are in view, and the
    # reference has a counterpart (not an end held at C's first or last reference frame)
    frames_trusted = (reg.fit >= TRUSTED_FIT) & ~movement.held(reg.num_frames)
    trusted = joints_trusted(angles, reference, seen) & frames_trusted[:, None]
    summary = summarise(
        reg,
        reference,
        angles,
        rate,
        settings_dict(cfg),
        trusted=trusted,
        movement=movement,
        findings=cfg.findings,
        cameras=rig.num_cameras,
        partial_silhouettes=[p.name for p in video.held],
    )
    if detection is not None:
        summary = dataclasses.replace(summary, detection=detection.summary())
    files = {}
    files["registration.npz"] = save_registration(reg, stage / "registration.npz")
    (stage / "summary.json").write_text(summary.to_json(), encoding="utf-8")
    files["summary.json"] = stage / "summary.json"
    files["student.bvh"] = write_student_bvh(reg, reference, rate, stage / "student.bvh")
    errors = {c: cfg.findings.method_error(c, rig.num_cameras) for c in angles.coordinates}
    files["joint_angles.csv"] = write_joint_angles_csv(angles, stage / "joint_angles.csv", errors)
    files["joint_angles.mot"] = write_mot(angles, stage / "joint_angles.mot")
    poses = body_poses(reg, reference)
    described = dict(OUTPUT_FILES)
    captions = [
        (f"student {t:.2f} s", f"reference {int(c) / reference.frame_rate:.2f} s")
        for t, c in zip(angles.time_s.tolist(), reg.C.tolist(), strict=True)
    ]
    for c, name in enumerate(rig.names):
        path = stage / f"overlay_{name}.mp4"
        pictures = side_by_side_frames(
            video.frames[c], rig, c, poses, captions, min_height=OVERLAY_MIN_HEIGHT
        )
        shown = tqdm(
            pictures,
            desc=f"overlay {name}",
            total=reg.num_frames,
            disable=not show,
            file=sys.stderr,
        )
        files[path.name] = write_video(path, shown, rate)
        described[path.name] = (
            f"camera {name}: the registered body over the video, the reference beside it"
        )
    inputs = ReportInputs(
        reg,
        summary,
        angles,
        poses,
        video.frames,
        rig,
        [p.name for p in job.videos],
        trusted.numpy(),
        {described[n]: n for n in [*files, "report.html"]},
    )
    files["report.html"] = write_report(stage / "report.html", inputs)
    return summary, files


def _publish(stage: Path, out: Path, files: dict[str, Path]) -> dict[str, Path]:
    """Move the staged files into ``out`` (each replaces an older file of the same name)."""
    final = {}
    for name, path in files.items():
        target = out / name
        os.replace(path, target)
        final[name] = target
    shutil.rmtree(stage, ignore_errors=True)
    return final


def run_register(job: RegisterJob, show_progress: bool = True) -> RegisterOutcome:
    """Run ``motion register`` (see the module's docstring); raises a ``ValueError``
    subclass or ``OSError`` with a one-line message on bad input, before writing anything
    (an output folder it had to create is removed again)."""
    created = _missing_folders(Path(job.out))
    try:
        return _run(job, show_progress)
    except BaseException:
        _remove_if_empty(created)
        raise


def _run(job: RegisterJob, show_progress: bool) -> RegisterOutcome:
    # the cheap checks first (settings, files, the videos' containers), then the decoding
    cfg = load_config(job.config, list(job.overrides))
    given = {}
    if job.person is not None:
        given["person"] = list(job.person)
    if job.backgrounds:
        given["backgrounds"] = [str(p) for p in job.backgrounds]
    if given:
        cfg = dataclasses.replace(cfg, video=dataclasses.replace(cfg.video, **given))
    _check_writable(job.out)
    reference = _read_reference(job.reference)
    rig = _read_rig(job.calibration, job.videos)
    probed = _container_frames(job.videos[0], cfg.video)
    if probed is not None:
        _check_durations(reference, *probed, slack=0.9)
    video = features_from_videos(job.videos, rig, cfg.video)
    _check_durations(reference, video.features.num_frames, video.features.frame_rate)
    detection = None
    if job.keypoints:
        source = job.keypoints[0] if len(job.keypoints) == 1 else list(job.keypoints)
        video = attach_keypoints(video, source, reference)
    elif cfg.perception.detector is not None:
        video, detection = _detect(job, cfg, reference, video, show_progress)
    log = _log(show_progress)
    if video.note:
        log(video.note)
    reg = register(
        reference,
        video.features,
        settings=cfg.registration,
        progress=_progress(show_progress),
        log=log,
    )
    if video.note:
        reg.notes["cameras"] = video.note
    if detection is not None:
        reg.timings["detection"] = detection.seconds
    reg.warnings[:0] = video.warnings
    stage = Path(tempfile.mkdtemp(dir=job.out, prefix=".partial-"))
    try:
        summary, files = _write_outputs(
            stage, job, cfg, reference, video, reg, show_progress, detection
        )
    except OSError as err:
        shutil.rmtree(stage, ignore_errors=True)
        if err.filename is not None and Path(err.filename).parent == stage:
            # name the file as it would have been presented, not the staging folder's copy
            raise OSError(err.errno, err.strerror, str(job.out / Path(err.filename).name)) from err
        raise
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return RegisterOutcome(reg, summary, _publish(stage, job.out, files))


#: the detections' folder inside the output folder (kept for reruns: a cache, not a result)
DETECTIONS_FOLDER = "detections"


def _detect(
    job: RegisterJob,
    cfg: RegisterConfig,
    reference: Reference,
    video: VideoInput,
    show_progress: bool,
) -> tuple[VideoInput, DetectionRun]:
    """The videos' kept frames through the person detector (:mod:`motion.perception`), its
    joints attached as the keypoint observation."""
    frames = video.start + video.step * np.arange(video.features.num_frames)
    job.out.mkdir(parents=True, exist_ok=True)
    run = detect_videos(
        job.videos,
        job.out / DETECTIONS_FOLDER,
        frames.tolist(),
        cfg.perception,
        progress=_progress(show_progress),
    )
    video = attach_keypoints(
        video,
        [cam.folder for cam in run.cameras],
        reference,
        convention=run.keypoint_set,
        spec=run.spec,
    )
    fps = run.frames_per_second
    speed = "reused from an earlier run" if fps is None else f"{fps:.1f} frames/s"
    found = ", ".join(f"{c.video.name} {c.detected}/{len(run.frames)}" for c in run.cameras)
    notes = [video.note, f"person detector {run.detector} ({speed}): a person in {found} frames"]
    if cfg.perception.fuse_mask:
        video, used = _fused(video, run, frames, cfg)
        notes.append(
            "silhouettes: the detector's mask, where it agrees with the tracked region, in "
            + ", ".join(
                f"{c.video.name} {n}/{len(frames)}" for c, n in zip(run.cameras, used, strict=True)
            )
            + " frames (background subtraction alone in the others)"
        )
    return dataclasses.replace(video, note="; ".join(n for n in notes if n)), run


def _fused(
    video: VideoInput, run: DetectionRun, frames: np.ndarray, cfg: RegisterConfig
) -> tuple[VideoInput, list[int]]:
    """The video's silhouettes fused with the detector's masks
    (:func:`motion.perception.fusion.fuse_silhouettes`); the frames fused per camera."""
    sil = video.features.observation.silhouette[0].numpy() > 0.5  # (T', C, H, W)
    h, w = sil.shape[-2:]
    reach = round(cfg.perception.mask_reach * max(h, w))
    fused, used = np.empty(sil.shape, dtype=np.float32), []
    for c, cam in enumerate(run.cameras):
        masks, found = masks_at(cam, frames.tolist(), video.scale, (w, h))
        fused[:, c], took = fuse_silhouettes(
            sil[:, c], masks, found, reach, cfg.perception.mask_agreement
        )
        used.append(int(took.sum()))
    return with_silhouettes(video, fused, cfg.video), used


def _size_words(s: RegistrationSummary) -> str:
    if s.G_measured:
        words = f"body size G {s.G:.3f}"
    else:
        words = "body size not measured (one perspective camera cannot tell it from depth)"
    if s.proportions:
        words += "; proportions: " + (proportion_words(s.proportions) or "the reference's")
    return words


def _fit_caveat(s: RegistrationSummary) -> str:
    """What the fit was measured against, where no camera saw the whole body."""
    return "" if s.whole_body_seen else ", against silhouettes that miss parts of the body"


def summary_lines(outcome: RegisterOutcome) -> list[str]:
    """The one-screen summary printed at the end."""
    s = outcome.summary
    reg = outcome.registration
    lines = [
        f"registered {s.num_video_frames} video frames against {Path(s.reference).name} "
        f"({sum(reg.timings.values()):.0f} s)",
        f"  starts at {s.reference_start_s:.2f} s of the reference (video {s.video_start_s:.2f}"
        f" s, frame {s.video_frames[0]}); speed ratio {s.speed_ratio:.2f} (reference seconds "
        "per video second)",
        f"  fit (silhouette IoU) {s.silhouette_iou_mean:.2f}{_fit_caveat(s)}; {_size_words(s)}",
    ]
    reasons = s.movement.get("reasons", [])  # first among the warnings
    if not s.motions_match:
        lines.insert(
            1,
            "  the student does not seem to perform the reference's movement, so no joint "
            "difference is stated:",
        )
        lines[2:2] = [f"    {w}" for w in reasons]
    lines += [f"  warning: {w}" for w in s.warnings[len(reasons) :]]
    stated = [d for d in s.largest_differences if d["stated"]]
    if stated:
        lines.append("  largest joint differences:")
        lines += [f"    {d['text']}" for d in stated[:3]]
    withheld = [d for d in s.largest_differences if not d["stated"]] if s.motions_match else []
    if withheld and not s.whole_body_seen:  # one reason for all: say it once
        lines.append(f"  no joint difference is stated: {withheld[0]['why']}")
    else:
        lines += [f"  not stated: {d['text']} ({d['why']})" for d in withheld]
    out = next(iter(outcome.files.values())).parent
    lines.append(
        f"  wrote {len(outcome.files)} files to {out}: report {outcome.files['report.html']}"
    )
    return lines
