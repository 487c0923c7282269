"""Shared fixtures of the ``motion register`` tests: a tiny but real input (a synthetic video
of the bundled CMU 07_01 walk, its calibration.toml and clean plate, as ``motion synth``
writes them) and one cheap run of ``python -m motion register`` on it."""

from __future__ import annotations

import contextlib
import io
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from motion.__main__ import main
from motion.synth import BACKGROUND_SUFFIX, CALIBRATION_FILE, SynthConfig, save_sequence, synthesize

DATA = Path(__file__).resolve().parents[3] / "motion" / "data"
#: the reference registered (CMU 02_01) and the performer in the video (CMU 07_01)
REFERENCE = DATA / "cmu_02_01_walk.bvh"
STUDENT = DATA / "cmu_07_01_walk.bvh"
#: ``motion synth`` settings of the tiny input: 96 x 72 px at 12 fps (32 frames, 2.7 s)
SYNTH = ["videos=true", "size=96x72", "focal_px=160", "fps=12"]
#: registration settings that run in a few seconds on one core: few particles (the band of
#: C's states must fit in them), one BP pass, one stage-3 round; the median background
#: against the clean plate with a low threshold, as the demo does for the flat synthetic scene,
#: and no person detector (as the demo: it is made for photographed people, not capsules)
CHEAP = (
    "refine.particles=12",
    "refine.band=4",
    "refine.iterations=1",
    "refine.restarts=1",
    "refine.rounds=1",
    "video.background=median",
    "video.threshold=12",
    "perception.detector=none",
)


@dataclass(frozen=True)
class StudentVideo:
    """What ``motion synth videos=true`` wrote for one camera."""

    folder: Path
    video: Path
    calibration: Path
    background: Path


@dataclass(frozen=True)
class RegisterRun:
    """One ``python -m motion register`` run: its exit status, what it printed, how long it
    took, and its inputs and output folder."""

    rc: int
    stdout: str
    stderr: str
    seconds: float
    out: Path
    student: StudentVideo
    argv: list[str]


@pytest.fixture(scope="session")
def student_video(tmp_path_factory) -> StudentVideo:
    """The tiny synthetic input (one camera), made once per test session."""
    folder = tmp_path_factory.mktemp("student_video")
    seq = synthesize(STUDENT, SynthConfig.from_assignments(SYNTH))
    save_sequence(seq, folder)
    (name,) = seq.meta["cameras"]
    return StudentVideo(
        folder,
        folder / f"{name}.avi",
        folder / CALIBRATION_FILE,
        folder / f"{name}{BACKGROUND_SUFFIX}",
    )


def register_argv(student: StudentVideo, out: Path, *extra: str) -> list[str]:
    """The command line of a cheap register run on ``student`` writing to ``out``."""
    return [
        "register",
        "--reference",
        str(REFERENCE),
        "--video",
        str(student.video),
        "--calibration",
        str(student.calibration),
        "--background",
        str(student.background),
        "--out",
        str(out),
        "--quiet",
        *CHEAP,
        *extra,
    ]


@pytest.fixture(scope="session")
def register_run(student_video, tmp_path_factory) -> RegisterRun:
    """``motion register`` run once (session scope: the command tests and the report's
    browser check read the same outputs) with its stdout and stderr captured."""
    out = tmp_path_factory.mktemp("register") / "out"
    argv = register_argv(student_video, out)
    stdout, stderr = io.StringIO(), io.StringIO()
    start = time.perf_counter()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        rc = main(argv)
    seconds = time.perf_counter() - start
    return RegisterRun(rc, stdout.getvalue(), stderr.getvalue(), seconds, out, student_video, argv)
