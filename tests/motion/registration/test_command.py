"""``python -m motion register`` end to end: a real (tiny) input run once through the command
line, every output read back; bad input answered with one line naming the file, before the
expensive work and without leaving outputs; the settings parser (config.py)."""

from __future__ import annotations

import csv
import dataclasses
import html
import itertools
import json
import math
import os
import re
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest
from markupsafe import escape

import motion.registration.command as command
import motion.registration.export as export
from motion.__main__ import main
from motion.angles import COORDINATES
from motion.bvh import read_bvh, write_bvh
from motion.draw import write_video
from motion.registration.config import ConfigError, RegisterConfig, load_config, override
from motion.registration.export import FindingSettings, load_registration
from motion.registration.types import Reference
from motion.synth import (
    BACKGROUND_SUFFIX,
    CALIBRATION_FILE,
    SynthConfig,
    load_sequence,
    save_sequence,
    synthesize,
)
from tests.conftest import SHARED_DATA, requires_shared_data
from tests.motion.registration.conftest import (
    REFERENCE,
    SYNTH,
    StudentVideo,
    register_argv,
)
from tests.motion.registration.test_keypoints import _body25b, _write_trc

ROBOT_ARM = REFERENCE.parent / "examples" / "robot_arm.bvh"


def _frames(path: Path) -> list[np.ndarray]:
    """Every frame of a video, decoded (RGB)."""
    cap = cv2.VideoCapture(str(path))
    frames = []
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    finally:
        cap.release()
    return frames


@pytest.fixture(scope="module")
def video_frames(student_video) -> int:
    """The number of frames of the student video (decoded, not the container's word)."""
    return len(_frames(student_video.video))


@pytest.fixture(scope="module")
def summary(register_run) -> dict:
    return json.loads((register_run.out / "summary.json").read_text(encoding="utf-8"))


# --------------------------------------------------------------------------- a good run


def test_register_exits_0_and_presents_exactly_its_files(register_run):
    assert register_run.rc == 0, register_run.stderr
    expected = {*command.OUTPUT_FILES, "overlay_cam1.mp4"}
    # nothing else: no staging (.partial-*) folder, no write test file
    assert set(os.listdir(register_run.out)) == expected
    assert all((register_run.out / n).stat().st_size > 0 for n in expected)
    assert register_run.stderr == ""  # --quiet: no progress bars, no notes


def test_printed_summary_names_the_report(register_run, summary):
    out = register_run.stdout
    assert f"report {register_run.out / 'report.html'}" in out
    assert f"registered {summary['num_video_frames']} video frames against" in out
    assert "speed ratio" in out and "starts at" in out and "time offset" not in out
    # one perspective camera: the size is not a measurement, and not shown as one
    assert summary["G_measured"] is False and "body size G" not in out
    assert "body size not measured (one perspective camera" in out


def test_summary_json(summary, video_frames):
    assert summary["num_video_frames"] == video_frames
    assert summary["video_rate_hz"] == pytest.approx(12.0)
    c = summary["c_frames"]
    assert len(c) == video_frames
    assert all(isinstance(x, int) for x in c)
    assert all(b >= a for a, b in itertools.pairwise(c)), "C must be monotone"
    num_reference = Reference.from_bvh(REFERENCE).num_frames
    assert 0 <= c[0] and c[-1] < num_reference
    per_joint = summary["per_joint_mean_abs_deg"]
    assert per_joint and all(
        isinstance(k, str) and isinstance(v, float) and math.isfinite(v) and v >= 0
        for k, v in per_joint.items()
    )
    assert 0.0 <= summary["silhouette_iou_mean"] <= 1.0
    # another subject's walk is the reference's movement: nothing to warn about
    assert summary["motions_match"] is True and summary["warnings"] == []
    movement = summary["movement"]
    assert movement["reference_travel_m"] > 0.5 and movement["reasons"] == []
    assert 0.5 <= movement["student_travel_m"] / movement["reference_travel_m"] <= 2
    # each difference stated or withheld for a reason of its own (the movements match);
    # the inference measured every one's uncertainty
    found = summary["largest_differences"]
    assert found and all(d["stated"] is (d["why"] == "") for d in found)
    assert all(d["why"].startswith(("only ", "its interval (")) for d in found if not d["stated"])
    assert all(isinstance(d["uncertainty_deg"], float) and d["uncertainty_deg"] > 0 for d in found)
    # one clock: frames from the start of the video (no video.start here), one "starts at"
    assert summary["video_frames"] == list(range(video_frames))
    assert summary["video_start_s"] == 0.0
    assert summary["reference_start_s"] == summary["c_frames"][0] / summary["reference_rate_hz"]
    assert "time_offset_s" not in summary
    assert math.isfinite(summary["speed_ratio"]) and summary["speed_ratio"] > 0
    # the settings of the run, as given on the command line
    settings = summary["settings"]
    assert settings["registration"]["refine"]["particles"] == 12
    assert settings["registration"]["refine"]["band"] == 4
    assert settings["video"]["background"] == "median"
    assert settings["video"]["threshold"] == 12.0
    assert len(settings["video"]["backgrounds"]) == 1


def test_registration_npz_matches_the_summary(register_run, summary, video_frames):
    reg = load_registration(register_run.out / "registration.npz")
    assert reg.C.tolist() == summary["c_frames"]
    assert reg.num_frames == video_frames
    assert reg.fit.shape == (video_frames,)
    assert float(reg.fit.mean()) == pytest.approx(summary["silhouette_iou_mean"], abs=1e-6)


def test_student_bvh_reads_back(register_run, video_frames):
    student = read_bvh(register_run.out / "student.bvh")
    reference = read_bvh(REFERENCE)
    assert student.num_frames == video_frames
    assert student.frame_rate == pytest.approx(12.0)
    assert student.names == reference.names
    assert student.parents.tolist() == reference.parents.tolist()
    assert np.isfinite(student.motion).all()


def test_joint_angles_csv_has_a_row_per_frame_and_coordinate(register_run, summary, video_frames):
    """One row per frame and clinical coordinate (OpenSim's names), those of the summary."""
    with (register_run.out / "joint_angles.csv").open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    coordinates = list(summary["per_joint_mean_abs_deg"])
    assert coordinates == COORDINATES  # the walk's parts estimate every one
    assert len(rows) == video_frames * len(coordinates)
    assert [r["coordinate"] for r in rows[: len(coordinates)]] == coordinates
    assert sorted({int(r["frame"]) for r in rows}) == list(range(video_frames))
    for r in rows:
        diff = float(r["difference_deg"])
        student, reference = float(r["student_deg"]), float(r["reference_deg"])
        assert diff == pytest.approx(student - reference, abs=1e-6)
    # each coordinate's method error, as the findings count it (1 camera)
    rules = FindingSettings()
    for r in rows[: len(coordinates)]:
        assert float(r["method_error_deg"]) == pytest.approx(rules.method_error(r["coordinate"], 1))
        assert float(r["uncertainty_deg"]) > 0


def test_mot_parses(register_run, summary, video_frames):
    lines = (register_run.out / "joint_angles.mot").read_text(encoding="utf-8").splitlines()
    end = lines.index("endheader")
    header = dict(line.split("=", 1) for line in lines[1:end] if "=" in line)
    columns = lines[end + 1].split("\t")
    rows = [[float(x) for x in line.split("\t")] for line in lines[end + 2 :]]
    assert header["inDegrees"] == "yes"
    assert int(header["nRows"]) == len(rows) == video_frames
    assert int(header["nColumns"]) == len(columns) == 1 + 3 * len(summary["per_joint_mean_abs_deg"])
    assert columns[0] == "time"
    assert all(len(r) == len(columns) for r in rows)
    times = np.array([r[0] for r in rows])
    np.testing.assert_allclose(times, np.arange(video_frames) / 12.0, atol=1e-8)


def test_overlay_video_has_every_frame(register_run, video_frames):
    path = register_run.out / "overlay_cam1.mp4"
    cap = cv2.VideoCapture(str(path))
    try:
        assert cap.isOpened()
        assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(12.0)
        assert cap.get(cv2.CAP_PROP_FRAME_HEIGHT) >= command.OVERLAY_MIN_HEIGHT
    finally:
        cap.release()
    assert len(_frames(path)) == video_frames


class _Links(HTMLParser):
    """Every src/href attribute and every <img>'s src of a page."""

    def __init__(self):
        super().__init__()
        self.links: list[tuple[str, str, str]] = []
        self.images: list[str] = []

    def handle_starttag(self, tag, attrs):
        for name, value in attrs:
            if name in ("src", "href"):
                self.links.append((tag, name, value or ""))
        if tag == "img":
            self.images.append(dict(attrs).get("src") or "")


def test_report_is_self_contained_and_says_the_findings(register_run, summary):
    text = (register_run.out / "report.html").read_text(encoding="utf-8")
    page = _Links()
    page.feed(text)
    remote = [link for link in page.links if link[2].lower().startswith(("http:", "https:", "//"))]
    assert not remote, remote
    assert page.images and all(src.startswith("data:image/png;base64,") for src in page.images)
    # the other links point at the files beside the report, and those exist
    for tag, _, value in page.links:
        if tag == "a":
            assert (register_run.out / value).is_file(), value
    assert "http://" not in text and "https://" not in text
    assert "<script" not in text.lower()
    findings = summary["largest_differences"]
    assert findings, "the walk of another performer differs somewhere"
    for d in findings:
        assert html.escape(d["text"]) in text


def test_a_report_without_a_trusted_frame_says_so(register_run, tmp_path, monkeypatch):
    """Where no frame fits well enough (here: the bar raised above any IoU), the report does
    not claim that no joint differs: it says no frame can be read, and why that may be."""
    monkeypatch.setattr(command, "TRUSTED_FIT", 1.01)
    monkeypatch.setattr(export, "TRUSTED_FIT", 1.01)
    out = tmp_path / "out"
    assert main(register_argv(register_run.student, out)) == 0
    text = (out / "report.html").read_text(encoding="utf-8")
    assert "No frame fits well enough to read joint differences from" in text
    assert "No joint differs from the reference" not in text
    assert json.loads((out / "summary.json").read_text())["largest_differences"] == []


def test_silhouettes_missing_the_body_hedge_the_fit_and_withhold_the_findings(
    register_run, tmp_path, monkeypatch, capsys
):
    """Where the only camera's silhouettes miss parts of the body (its median background holds
    the person: forced here on the clean run's input, warning and all, so that only the
    flag differs), the printed fit and the report's card say what the fit was measured
    against, and every difference is withheld for that reason, printed once (the clean run
    gives each its own; test_export checks that a stated one is withheld)."""
    features_from_videos = command.features_from_videos
    warning = "cam.avi: the person stays over the same pixels ..."

    def held(paths, rig, settings):
        video = features_from_videos(paths, rig, settings)
        return dataclasses.replace(
            video, held=list(video.paths), warnings=[*video.warnings, warning]
        )

    monkeypatch.setattr(command, "features_from_videos", held)
    capsys.readouterr()
    assert main(register_argv(register_run.student, tmp_path / "out")) == 0
    printed = capsys.readouterr().out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text(encoding="utf-8"))
    name = register_run.student.video.name
    assert summary["whole_body_seen"] is False and summary["partial_silhouettes"] == [name]
    assert warning in summary["warnings"] and summary["motions_match"]
    findings = summary["largest_differences"]
    assert findings and all(not d["stated"] for d in findings)
    assert all(d["why"].startswith("no camera's silhouettes show the whole body") for d in findings)
    assert "against silhouettes that miss parts of the body" in printed
    assert printed.count("no joint difference is stated: no camera's silhouettes") == 1
    assert "not stated:" not in printed and "largest joint differences" not in printed
    text = (tmp_path / "out" / "report.html").read_text(encoding="utf-8")
    assert "(uncertain)</div>" in text and "Withheld: no camera's silhouettes" in text
    for d in findings:
        assert str(escape(d["text"])) in text  # shown for inspection, not as findings
    assert '<ol class="findings">' not in text


def test_every_time_is_on_the_source_videos_clock(register_run, tmp_path, capsys):
    """video.start=4, video.step=2 at 12 fps: frame t' is source frame 4 + 2 t' at
    (4 + 2 t') / 12 s in summary.json, the CSV, the .mot, the findings, the printed summary
    and the report's "Starts at" card."""
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(register_argv(register_run.student, out, "video.start=4", "video.step=2")) == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    n = summary["num_video_frames"]
    frames = [4 + 2 * t for t in range(n)]
    assert summary["video_frames"] == frames and summary["video_rate_hz"] == pytest.approx(6.0)
    assert summary["video_start_s"] == pytest.approx(4 / 12)
    with (out / "joint_angles.csv").open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert sorted({int(r["frame"]) for r in rows}) == frames
    for r in rows:
        assert float(r["time_s"]) == pytest.approx(int(r["frame"]) / 12, abs=1e-9)
    mot = (out / "joint_angles.mot").read_text().splitlines()
    body = mot[mot.index("endheader") + 2 :]
    assert [float(line.split("\t")[0]) for line in body] == pytest.approx([f / 12 for f in frames])
    for d in summary["largest_differences"]:
        assert 4 / 12 - 1e-9 <= d["start_s"] <= d["end_s"] <= frames[-1] / 12 + 1e-9
    start = summary["reference_start_s"]
    assert f"starts at {start:.2f} s of the reference (video 0.33 s, frame 4)" in printed
    text = (out / "report.html").read_text(encoding="utf-8")
    assert f"{start:.2f} s</div>" in text and "video at 0.33 s" in text and "(frame 4)" in text


@requires_shared_data()
@pytest.mark.parametrize("movement", ["09_01", "02_04", "02_03"], ids=["run", "jump", "jog"])
def test_another_movement_is_said_first_and_no_difference_is_stated(movement, tmp_path, capsys):
    """A CMU run, jump or jog (another subject, ../shared/data) against the bundled walk: the
    summary, the printed lines and the report say first that the movements differ, and no
    joint difference is stated (they stay in summary.json with stated false and why). The
    jog covers no more ground per stride than a long-striding walker: its gait (the Froude
    numbers, over the whole video or its fastest second) tells it apart."""
    seq = synthesize(
        SHARED_DATA / "bvh" / "cmu_cgspeed" / f"{movement}.bvh", SynthConfig.from_assignments(SYNTH)
    )
    save_sequence(seq, tmp_path / "in")
    (name,) = seq.meta["cameras"]
    folder = tmp_path / "in"
    student = StudentVideo(
        folder,
        folder / f"{name}.avi",
        folder / CALIBRATION_FILE,
        folder / f"{name}{BACKGROUND_SUFFIX}",
    )
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(register_argv(student, out)) == 0
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert summary["motions_match"] is False
    reasons = summary["movement"]["reasons"]
    assert reasons and summary["warnings"][: len(reasons)] == reasons
    if movement == "02_03":  # by its gait alone: over the whole video or its fastest second
        assert reasons == [r for r in reasons if "Froude number" in r and "run" in r]
        gait = summary["movement"]
        assert max(gait["student_froude"], gait["student_froude_peak"]) >= 0.5
    assert all(d["stated"] is False and d["why"] for d in summary["largest_differences"])
    printed = capsys.readouterr().out.splitlines()
    assert printed[1].strip().startswith("the student does not seem to perform the reference")
    assert printed[2].strip() == reasons[0]
    assert "largest joint differences" not in "\n".join(printed)
    text = (out / "report.html").read_text(encoding="utf-8")
    assert "does not seem to perform the reference's movement" in text
    assert str(escape(reasons[0])) in text and "Withheld:" in text
    for d in summary["largest_differences"]:
        assert str(escape(d["text"])) not in text


def test_register_help_lists_the_settings(capsys):
    assert main(["register", "--help"]) == 0
    out = capsys.readouterr().out
    assert "refine.particles" in out and "video.background" in out and "stage1." in out


# --------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def bad(student_video, tmp_path_factory) -> dict[str, Path]:
    """Broken inputs derived from the good one."""
    d = tmp_path_factory.mktemp("bad_input")
    frames = _frames(student_video.video)
    files = {}
    files["text.mp4"] = d / "text.mp4"
    files["text.mp4"].write_text("this is not a video\n", encoding="utf-8")
    files["empty.avi"] = d / "empty.avi"  # a valid container without a frame
    writer = cv2.VideoWriter(str(files["empty.avi"]), cv2.VideoWriter_fourcc(*"MJPG"), 12, (96, 72))
    writer.release()
    files["zero.mp4"] = d / "zero.mp4"
    files["zero.mp4"].write_bytes(b"")
    files["short.avi"] = write_video(d / "short.avi", frames[:20], 12)
    files["fast.avi"] = write_video(d / "fast.avi", frames, 24)
    plate = cv2.cvtColor(cv2.imread(str(student_video.background)), cv2.COLOR_BGR2RGB)
    files["empty_scene.avi"] = write_video(d / "empty_scene.avi", [plate] * len(frames), 12)
    text = student_video.calibration.read_text(encoding="utf-8")
    files["no_matrix.toml"] = d / "no_matrix.toml"
    files["no_matrix.toml"].write_text(
        "\n".join(line for line in text.splitlines() if not line.startswith("matrix")) + "\n"
    )
    cam1, metadata = text.split("[metadata]")
    cam2 = cam1.replace("[cam1]", "[cam2]").replace('"cam1"', '"cam2"')
    files["two_cameras.toml"] = d / "two_cameras.toml"
    files["two_cameras.toml"].write_text(f"{cam1}{cam2}[metadata]{metadata}", encoding="utf-8")
    # the loader refuses a non-finite K; stage 0's check of the rig, two cameras of one name
    files["nan_matrix.toml"] = d / "nan_matrix.toml"
    files["nan_matrix.toml"].write_text(re.sub(r"matrix = \[\[[^,]+", "matrix = [[nan", text))
    same = cam1.replace("[cam1]", "[cam2]")
    files["same_names.toml"] = d / "same_names.toml"
    files["same_names.toml"].write_text(f"{cam1}{same}[metadata]{metadata}", encoding="utf-8")
    files["big_size.toml"] = d / "big_size.toml"  # the video is 96 x 72 px
    files["big_size.toml"].write_text(re.sub(r"size = \[[^]]*\]", "size = [192.0, 144.0]", text))
    files["a_file"] = d / "a_file"
    files["a_file"].write_text("a regular file\n")
    reference = read_bvh(REFERENCE)  # 344 frames at 120 Hz: 2.9 s, the video 2.7 s
    files["short_reference.bvh"] = write_bvh(
        dataclasses.replace(reference, motion=reference.motion[:60]), d / "short_reference.bvh"
    )
    files["other_markers.trc"] = d / "other_markers.trc"
    uv = np.random.default_rng(0).uniform(0, 90, (len(frames), 2, 2))  # pixels
    _write_trc(files["other_markers.trc"], uv, ["Foo", "Bar"], 12.0)
    return files


def _argv(
    student,
    out: Path,
    *,
    reference: Path = REFERENCE,
    videos: list[Path] | None = None,
    calibration: Path | str | None = "default",
    backgrounds: list[Path] | None = None,
    keypoints: list[Path] = (),
    extra: tuple[str, ...] = (),
) -> list[str]:
    argv = ["register", "--reference", str(reference)]
    for v in videos or [student.video]:
        argv += ["--video", str(v)]
    calibration = student.calibration if calibration == "default" else calibration
    if calibration is not None:
        argv += ["--calibration", str(calibration)]
    for b in [student.background] if backgrounds is None else backgrounds:
        argv += ["--background", str(b)]
    for k in keypoints:
        argv += ["--keypoints", str(k)]
    fixed = ["refine.particles=12", "refine.band=4", "perception.detector=none"]
    return [*argv, "--out", str(out), "--quiet", *fixed, *extra]


#: the rest of the conftest's cheap settings (_argv gives the particles and the band)
CHEAP_TAIL = (
    "refine.iterations=1",
    "refine.restarts=1",
    "refine.rounds=1",
    "video.background=median",
    "video.threshold=12",
)


def _fail(*args, **kwargs):
    raise AssertionError("bad input must be refused before this is called")


#: id -> (the command line's changes, the file the message names, what it says, whether
#: the refusal may come from reading the videos, features_from_videos, rather than before)
BAD = {
    "unreadable video": (
        lambda s, b: {"videos": [b["text.mp4"]]},
        "text.mp4",
        "cannot open this video",
        True,
    ),
    "zero-length video": (
        lambda s, b: {"videos": [b["empty.avi"]]},
        "empty.avi",
        "has no frames",
        True,
    ),
    "empty file as video": (
        lambda s, b: {"videos": [b["zero.mp4"]]},
        "zero.mp4",
        "cannot open this video",
        True,
    ),
    "missing video": (
        lambda s, b: {"videos": [b["text.mp4"].with_name("nowhere.mp4")]},
        "nowhere.mp4",
        "no such video file",
        True,
    ),
    "reference without the body's joints": (
        lambda s, b: {"reference": ROBOT_ARM},
        "robot_arm.bvh",
        "no hips",
        False,
    ),
    "videos of different frame counts": (
        lambda s, b: {
            "videos": [s.video, b["short.avi"]],
            "calibration": b["two_cameras.toml"],
            "backgrounds": [],
        },
        "short.avi",
        "different frame counts",
        True,
    ),
    "videos of different rates": (
        lambda s, b: {
            "videos": [s.video, b["fast.avi"]],
            "calibration": b["two_cameras.toml"],
            "backgrounds": [],
        },
        "fast.avi",
        "different frame rates",
        True,
    ),
    "calibration without matrix": (
        lambda s, b: {"calibration": b["no_matrix.toml"]},
        "no_matrix.toml",
        "has no 'matrix'",
        False,
    ),
    "calibration with a non-finite K": (
        lambda s, b: {"calibration": b["nan_matrix.toml"]},
        "nan_matrix.toml",
        "camera [cam1] 'matrix' must be finite; got [[nan,",
        False,
    ),
    "calibration whose cameras share a name": (
        lambda s, b: {"calibration": b["same_names.toml"]},
        "same_names.toml",
        "camera names must be unique; repeated: ['cam1']",
        False,
    ),
    "calibration of another image size than the video": (
        lambda s, b: {"calibration": b["big_size.toml"]},
        "cam1.avi",
        "frames are 96 x 72 px but the calibration says 192 x 144",
        True,
    ),
    "calibration of another camera count": (
        lambda s, b: {"calibration": b["two_cameras.toml"]},
        "two_cameras.toml",
        "2 camera(s)",
        False,
    ),
    "two videos without calibration": (
        lambda s, b: {"videos": [s.video, s.video], "calibration": None, "backgrounds": []},
        "cam1.avi",
        "no calibration",
        True,
    ),
    "output folder under a file": (
        lambda s, b: {"out": b["a_file"] / "sub"},
        "a_file",
        "is a file, not a folder",
        False,
    ),
    "output folder is a file": (
        lambda s, b: {"out": b["a_file"]},
        "a_file",
        "is a file, not a folder",
        False,
    ),
    "no person in the video": (
        lambda s, b: {"videos": [b["empty_scene.avi"]]},
        "empty_scene.avi",
        "no person found",
        True,
    ),
    "reference much shorter than the video": (
        lambda s, b: {"reference": b["short_reference.bvh"]},
        "short_reference.bvh",
        "the reference lasts 0.49 s but the video 2.67 s",
        False,
    ),
    "keypoints of another marker set": (
        lambda s, b: {"keypoints": [b["other_markers.trc"]]},
        "other_markers.trc",
        "Foo, Bar",
        True,
    ),
    "unknown setting": (
        lambda s, b: {"extra": ("refine.particlez=3",)},
        "command line",
        "unknown setting 'refine.particlez' (did you mean refine.particles?)",
        False,
    ),
    "setting of the wrong type": (
        lambda s, b: {"extra": ("refine.particles=abc",)},
        "command line",
        "refine.particles must be an integer >= 2; got 'abc'",
        False,
    ),
    "settings that do not fit together": (
        lambda s, b: {"extra": ("refine.band=12",)},
        "command line",
        "must fit in the 12 particles",
        False,
    ),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_is_one_line_naming_the_file(
    case, student_video, bad, tmp_path, capsys, monkeypatch
):
    change, names, says, reads_videos = BAD[case]
    changes = change(student_video, bad)
    out = changes.pop("out", tmp_path / "out")
    # refused before the registration proper (and, where the videos need not be read for
    # it, before they are decoded)
    monkeypatch.setattr(command, "register", _fail)
    if not reads_videos:
        monkeypatch.setattr(command, "features_from_videos", _fail)
    rc = main(_argv(student_video, out, **changes))
    captured = capsys.readouterr()
    assert rc == 2, captured
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    assert "Traceback" not in captured.err
    line = lines[0]
    assert line.startswith("error: "), line
    assert names in line and says in line, line
    assert captured.out == ""
    # nothing presented: not even the output folder the run would have created
    if out.is_relative_to(tmp_path):
        assert not out.exists()
    assert bad["a_file"].read_text() == "a regular file\n"


def test_unreadable_video_prints_nothing_but_the_line(student_video, bad, tmp_path, capfd):
    assert main(_argv(student_video, tmp_path / "out", videos=[bad["text.mp4"]])) == 2
    err = capfd.readouterr().err
    assert len(err.splitlines()) == 1, err


def test_missing_joints_message_names_roles_and_the_specs(student_video, tmp_path, capsys):
    assert main(_argv(student_video, tmp_path / "out", reference=ROBOT_ARM)) == 2
    line = capsys.readouterr().err.strip()
    for role in ("hips", "knee_l", "shoulder_r"):
        assert role in line
    assert "Base" in line  # the joints it does have
    assert "motion/data/bodyparts/" in line and "python -m motion info" in line


def test_short_reference_is_refused_before_decoding(student_video, bad, tmp_path, monkeypatch):
    """The reference's length is checked against the video's container (frame count and
    rate), so a long video is not decoded only to be refused; ``video.count`` that fits is
    accepted as far as that check goes."""
    monkeypatch.setattr(command, "features_from_videos", _fail)
    argv = _argv(student_video, tmp_path / "out", reference=bad["short_reference.bvh"])
    assert main(argv) == 2

    class Decoded(Exception):
        pass

    def decoded(*args, **kwargs):
        raise Decoded

    monkeypatch.setattr(command, "features_from_videos", decoded)
    with pytest.raises(Decoded):
        main([*argv, "video.count=14"])


def test_bad_input_leaves_an_existing_folder_as_it_was(student_video, bad, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    assert main(_argv(student_video, out, videos=[bad["text.mp4"]])) == 2
    assert sorted(os.listdir(out)) == ["notes.txt"]


def test_failure_while_writing_outputs_presents_nothing(
    student_video, register_run, tmp_path, capsys, monkeypatch
):
    """An error after the registration (here the report) leaves no output and no staging
    folder: the files are moved into place only when all are written."""
    reg = load_registration(register_run.out / "registration.npz")
    monkeypatch.setattr(command, "register", lambda *a, **k: reg)

    def disk_full(path, inputs):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(command, "write_report", disk_full)
    out = tmp_path / "out"
    out.mkdir()
    assert main(register_argv(student_video, out)) == 2
    err = capsys.readouterr().err
    assert err == f"error: {out / 'report.html'}: No space left on device\n"
    assert os.listdir(out) == []


# --------------------------------------------------------------------------- settings


def test_nested_yaml_and_dotted_keys_give_the_same_settings(tmp_path):
    nested = tmp_path / "nested.yaml"
    nested.write_text(
        "video:\n  width: 240\n  background: median\n"
        "refine:\n  particles: 40\n  connection:\n    pos_std: 0.03\n"
        "stage1:\n  yaw_starts: 4\nseed: 3\n"
    )
    dotted = tmp_path / "dotted.yaml"
    dotted.write_text(
        "video.width: 240\nvideo.background: median\nrefine.particles: 40\n"
        "refine.connection.pos_std: 0.03\nstage1.yaw_starts: 4\nseed: 3\n"
    )
    overrides = [
        "video.width=240",
        "video.background=median",
        "refine.particles=40",
        "refine.connection.pos_std=0.03",
        "stage1.yaw_starts=4",
        "seed=3",
    ]
    a, b, c = load_config(nested), load_config(dotted), load_config(None, overrides)
    # (repr: the annealing schedules inside, pgm.Geometric, do not define ==)
    assert repr(a) == repr(b) == repr(c)
    assert repr(a) != repr(RegisterConfig())
    assert a.video.width == 240 and a.video.background == "median"
    assert a.registration.refine.particles == 40
    assert a.registration.refine.connection.pos_std == 0.03
    assert a.registration.stage1.yaw_starts == 4 and a.registration.seed == 3
    # the full path works as well as the shortcut
    assert (
        load_config(None, ["registration.refine.particles=40"]).registration.refine.particles == 40
    )
    # an empty file is the defaults
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert repr(load_config(empty)) == repr(RegisterConfig())


def test_later_settings_win(tmp_path):
    path = tmp_path / "settings.yaml"
    path.write_text("refine:\n  particles: 40\n  iterations: 2\n")
    cfg = load_config(path, ["refine.particles=50", "refine.particles=60"])
    assert cfg.registration.refine.particles == 60  # the last override
    assert cfg.registration.refine.iterations == 2  # from the file, not overridden


def test_settings_checked_together_may_come_in_any_order():
    """RefineSettings checks the band of C against the particles: each order works, and
    only the final values are checked."""
    for items in (
        ["refine.particles=12", "refine.band=4"],
        ["refine.band=4", "refine.particles=12"],
    ):
        refine = load_config(None, items).registration.refine
        assert (refine.particles, refine.band) == (12, 4)
    with pytest.raises(ConfigError, match=r"command line: .*must fit in the 12 particles"):
        load_config(None, ["refine.particles=12"])


def test_float_field_given_an_int_and_tuple_given_a_list():
    cfg = load_config(
        None, ["video.threshold=12", "refine.prior_pos_std=1", "stage1.reference_up=[0, 0, 1]"]
    )
    assert cfg.video.threshold == 12.0 and isinstance(cfg.video.threshold, float)
    assert isinstance(cfg.registration.refine.prior_pos_std, float)
    assert cfg.registration.stage1.reference_up == (0.0, 0.0, 1.0)
    assert all(isinstance(x, float) for x in cfg.registration.stage1.reference_up)
    with pytest.raises(
        ConfigError, match=r"^command line: stage1.reference_up must be a list of 3 numbers; got"
    ):
        load_config(None, ["stage1.reference_up=[0, 1]"])
    with pytest.raises(ConfigError, match=r"video.person\[1\] must be a number; got 'x'"):
        load_config(None, ["video.person=[10, x]"])
    with pytest.raises(ConfigError, match=r"refine.particles must be an integer >= 2; got 2.5"):
        load_config(None, ["refine.particles=2.5"])
    with pytest.raises(ConfigError, match=r"refine.particles must be an integer >= 2; got true"):
        load_config(None, ["refine.particles=true"])


def test_none_where_allowed_and_only_there():
    cfg = load_config(
        None, ["video.width=none", "video.count=null", "scale=none", "video.count=10"]
    )
    assert cfg.video.width is None and cfg.video.count == 10 and cfg.registration.scale is None
    assert load_config(None, ["scale=1.1", "scale=none"]).registration.scale is None
    with pytest.raises(ConfigError, match=r"refine.particles must be an integer >= 2; got nothing"):
        load_config(None, ["refine.particles=none"])
    with pytest.raises(ConfigError, match=r"refine.particles must be an integer >= 2; got nothing"):
        load_config(None, ["refine.particles="])


@pytest.mark.parametrize(
    ("item", "suggestion"),
    [
        ("refine.particlez=3", "refine.particles"),
        ("particles=3", "refine.particles"),
        ("refin.particles=3", "refine.particles"),
        ("video.widht=200", "video.width"),
        ("seeed=1", "seed"),
        ("refine.connection.pos_sdt=0.1", "refine.connection.pos_std"),
    ],
)
def test_unknown_key_suggests_the_close_one(item, suggestion):
    with pytest.raises(ConfigError) as err:
        load_config(None, [item])
    message = str(err.value)
    key = item.split("=")[0]
    assert message.startswith(f"command line: unknown setting {key!r} (did you mean {suggestion}")
    assert "\n" not in message


def test_unknown_key_in_a_file_names_the_file(tmp_path):
    path = tmp_path / "settings.yaml"
    path.write_text("refine:\n  particlez: 3\n")
    with pytest.raises(ConfigError, match=rf"^{path}:2: unknown setting 'refine.particlez'"):
        load_config(path)


def test_group_key_given_a_scalar_and_a_scalar_given_sub_keys(tmp_path):
    with pytest.raises(ConfigError, match=r"refine is a group of settings.*refine\.particles"):
        load_config(None, ["refine=3"])
    with pytest.raises(ConfigError, match=r"video is a group of settings.*video\.width"):
        load_config(None, ["video=none"])
    path = tmp_path / "settings.yaml"
    path.write_text("refine:\n  connection: 0.5\n")
    with pytest.raises(ConfigError, match=rf"^{path}:2: refine.connection is a group of settings"):
        load_config(path)
    with pytest.raises(ConfigError, match=r"seed is a single setting, it has no sub-settings"):
        load_config(None, ["seed.value=1"])


def test_bad_files_and_assignments(tmp_path):
    listing = tmp_path / "list.yaml"
    listing.write_text("- refine.particles: 3\n")
    with pytest.raises(ConfigError, match=r"expected a mapping of settings; got list"):
        load_config(listing)
    broken = tmp_path / "broken.yaml"
    broken.write_text("refine: [1, 2\n")
    with pytest.raises(ConfigError, match=r"broken.yaml:2:1: not valid YAML"):
        load_config(broken)
    with pytest.raises(ConfigError, match=r"expected a setting as key=value"):
        load_config(None, ["refine.particles"])
    with pytest.raises(ConfigError, match=r"background must be one of 'mog2', 'median'"):
        load_config(None, ["video.background=mog"])


def test_settings_files_are_read_strictly_and_errors_name_the_line(tmp_path):
    """The reader of experiments' configs (motion.settings_yaml): duplicate keys refused,
    YAML 1.2 scalars, a bad value named by its key, file and line; one ConfigError class."""
    import motion.settings

    assert ConfigError is motion.settings.ConfigError  # experiments.config's too
    twice = tmp_path / "twice.yaml"
    twice.write_text("refine:\n  particles: 40\n  particles: 50\n")
    with pytest.raises(ConfigError, match=rf"^{twice}:3: duplicate key 'particles' \(first"):
        load_config(twice)
    ranges = tmp_path / "ranges.yaml"
    ranges.write_text("video:\n  width: 240\nstage1:\n  yaw_starts: 0\n")
    with pytest.raises(ConfigError) as err:
        load_config(ranges)
    assert str(err.value) == f"{ranges}:4: stage1.yaw_starts must be >= 1; got 0"
    with pytest.raises(ConfigError, match=r"^command line: stage1.fix_start must be true or false"):
        load_config(None, ["stage1.fix_start=yes"])  # YAML 1.2: only true/false are booleans
    cfg = load_config(None, ["stage1.lm_damping=1e-3", "findings.method_error_deg=0"])
    assert cfg.registration.stage1.lm_damping == 0.001  # YAML 1.2: 1e-3 is a number
    assert cfg.findings.method_error_deg == 0.0
    with pytest.raises(ConfigError, match=r"^command line: movement.max_fast must be in \(0, 1\]"):
        load_config(None, ["movement.max_fast=2"])
    with pytest.raises(ConfigError, match=r"^command line: Stage1Settings: refine_starts must be"):
        load_config(None, ["stage1.refine_starts=9"])


def test_override_one_key():
    cfg = override(RegisterConfig(), "registration.refine.particles", 30)
    assert cfg.registration.refine.particles == 30
    assert cfg.registration.refine.iterations == RegisterConfig().registration.refine.iterations


def test_keypoint_files_join_the_observation(student_video, tmp_path, capsys):
    """--keypoints: OpenPose BODY_25B files of the video's true 2-D joints are read, matched
    to the reference's joints, and said in the summary's notes."""
    seq = load_sequence(student_video.folder)
    folder = tmp_path / "cam1_json"
    folder.mkdir()
    names = seq.meta["joint_names"]
    for f, uv in enumerate(seq.arrays["joints2d"][0]):
        person = {"person_id": [-1], "pose_keypoints_2d": _body25b(uv, names)}
        doc = {"version": 1.3, "people": [person]}
        (folder / f"cam1.{f:04d}.json").write_text(json.dumps(doc))
    out = tmp_path / "out"
    assert main(_argv(student_video, out, keypoints=[folder], extra=CHEAP_TAIL)) == 0, (
        capsys.readouterr()
    )
    notes = json.loads((out / "summary.json").read_text())["notes"]
    assert "2-D keypoints from cam1_json" in notes["cameras"]
    assert "LKnee=LeftLeg" in notes["cameras"] and "14 joints matched" in notes["cameras"]
