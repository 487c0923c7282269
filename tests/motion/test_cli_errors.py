"""Bad input to ``python -m motion`` and to ``SynthConfig``: each case is pinned to its one line
on stderr and exit status 2 (never a traceback; ``--debug`` adds one); help is plain text and
lists synth's settings; ``info`` explains parts and roles; ``synth`` says what it wrote."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from motion.__main__ import main
from motion.synth import SynthConfig, SynthConfigError
from tests.conftest import assert_message, cli_error_line
from tests.motion.test_bvh import BUNDLED

ROOT = Path(__file__).resolve().parents[2]
SETTINGS = ", ".join(f.name for f in dataclasses.fields(SynthConfig))
B = str(BUNDLED)


def _error_line(capsys, argv: list[str]) -> str:
    return cli_error_line(capsys, main, argv)


SYNTH_CASES = [
    # (id, settings, message) -- {B} is the bundled BVH
    (
        "replace-one-number",
        ["replace=0.5"],
        "synth: replace must be a list of 2 numbers in [0, 1], e.g. 0.4,0.5, or none; got [0.5]",
    ),
    (
        "replace-order",
        ["replace=0.5,0.4"],
        "synth: replace must be start,end with start < end and end + (end - start) <= 1 (the "
        "replacing frames follow the stretch); got [0.5, 0.4]",
    ),
    (
        "replace-beyond-the-end",
        ["replace=0.5,0.9"],
        "synth: replace must be start,end with start < end and end + (end - start) <= 1 (the "
        "replacing frames follow the stretch); got [0.5, 0.9]",
    ),
    (
        "path-two-numbers",
        ["path_m=1,2"],
        "synth: path_m must be a list of 3 numbers, e.g. 0.5,0,0; got [1, 2]",
    ),
    ("infinite-fps", ["fps=inf"], "synth: fps must be a finite number; got inf"),
    ("nan-fps", ["fps=nan"], "synth: fps must be a finite number; got nan"),
    ("zero-fps", ["fps=0"], "synth: fps must be in (0, 1000]; got 0"),
    (
        "empty-fps",
        ["fps="],
        "synth: fps must be a number in (0, 1000]; got nothing (an empty value)",
    ),
    ("text-fps", ["fps=fast"], "synth: fps must be a number in (0, 1000]; got 'fast'"),
    (
        "articulation-without-degrees",
        ["articulation=LeftLeg"],
        "synth: articulation must be a mapping of name: a number in [0, 180], "
        "e.g. LeftLeg:20,RightArm:30; got 'LeftLeg'",
    ),
    (
        "articulation-text-degrees",
        ["articulation=LeftLeg:x"],
        "synth: articulation['LeftLeg'] must be a number in [0, 180]; got 'x'",
    ),
    (
        "articulation-too-large",
        ["articulation=LeftLeg:200"],
        "synth: articulation['LeftLeg'] must be in [0, 180]; got 200",
    ),
    (
        "articulation-joint-twice",
        ["articulation=LeftLeg:1,LeftLeg:2"],
        "synth: articulation names 'LeftLeg' twice; got 'LeftLeg:1,LeftLeg:2'",
    ),
    ("negative-noise", ["noise_px=-5"], "synth: noise_px must be >= 0; got -5"),
    (
        "size-one-number",
        ["size=320"],
        "synth: size must be a list of 2 integers in [8, 4096], e.g. 320x240; got [320]",
    ),
    ("size-too-small", ["size=4x4"], "synth: size[0] must be in [8, 4096]; got 4"),
    ("size-text", ["size=axb"], "synth: size[0] must be an integer in [8, 4096]; got 'a'"),
    ("no-cameras", ["cameras=0"], "synth: cameras must be in [1, 64]; got 0"),
    (
        "fractional-cameras",
        ["cameras=1.5"],
        "synth: cameras must be an integer in [1, 64]; got 1.5",
    ),
    ("not-a-boolean", ["videos=maybe"], "synth: videos must be true or false; got 'maybe'"),
    ("warp-one", ["warp=1"], "synth: warp must be in [0, 1); got 1"),
    ("zero-distance", ["camera_distance_m=0"], "synth: camera_distance_m must be > 0; got 0"),
    ("negative-seed", ["seed=-1"], "synth: seed must be in [0, 4294967295]; got -1"),
    (
        "unknown-setting",
        ["colour=red"],
        f"synth: unknown setting 'colour' for SynthConfig; known: {SETTINGS}",
    ),
    (
        "misspelt-setting",
        ["fsp=30"],
        f"synth: unknown setting 'fsp' for SynthConfig (did you mean 'fps'?); known: {SETTINGS}",
    ),
    ("no-equals", ["fps"], "synth: expected a setting as key=value (e.g. fps=30); got 'fps'"),
    ("setting-twice", ["seed=1", "seed=2"], "synth: seed is given twice"),
    # found once the reference is read (before anything is rendered)
    (
        "unknown-joint",
        ["articulation=LeftLegg:20"],
        "re:articulation: {B} has no joint 'LeftLegg' \\(did you mean 'LeftLeg'\\?\\); "
        "its joints: Hips, LHipJoint, .+, RThumb",
    ),
    (
        "camera-inside-the-body",
        ["camera_distance_m=0.2"],
        "camera_distance_m=0.2: joint Head is at depth -0.01 m from camera cam1 in video frame "
        "40; expected every joint in front of every camera (raise camera_distance_m, or lower "
        "body_scale)",
    ),
    (
        "images-too-large",
        ["fps=1000", "size=4096x4096"],
        "cameras=1 x 2850 frames x size=4096x4096 would need about 1068.8 GiB of images; "
        "expected at most 8 GiB (lower size, cameras or fps)",
    ),
    (
        "replace-covers-no-frame",
        ["fps=1", "replace=0.4,0.5"],
        "replace=0.4,0.5 covers no frame of the 3-frame video; expected a stretch of at least "
        "one frame (raise fps or widen replace)",
    ),
]


@pytest.mark.parametrize(
    ("overrides", "expected"), [c[1:] for c in SYNTH_CASES], ids=[c[0] for c in SYNTH_CASES]
)
def test_malformed_synth_settings(tmp_path, capsys, overrides, expected):
    argv = ["synth", "--reference", B, "--out", str(tmp_path / "out"), *overrides]
    assert_message(_error_line(capsys, argv), expected.replace("{B}", re.escape(B)))
    assert not (tmp_path / "out").exists()  # nothing written


FILE_CASES = [
    (["info", "/nonexistent.bvh"], "/nonexistent.bvh: No such file or directory"),
    (
        ["synth", "--reference", "/nonexistent.bvh", "--out", "OUT"],
        "/nonexistent.bvh: No such file or directory",
    ),
    (
        ["synth", "--reference", B, "--student", "/nonexistent.bvh", "--out", "OUT"],
        "/nonexistent.bvh: No such file or directory",
    ),
]

USAGE_CASES = [
    (
        [],
        "python -m motion: the following arguments are required: {info,synth,register,demo} "
        "(see python -m motion --help)",
    ),
    (
        ["bogus"],
        r"re:python -m motion: argument \{info,synth,register,demo\}: invalid choice: 'bogus' .*"
        r"\(see python -m motion --help\)",
    ),
    (
        ["info"],
        "python -m motion info: the following arguments are required: file "
        "(see python -m motion info --help)",
    ),
    (
        ["synth"],
        "python -m motion synth: the following arguments are required: --reference, --out "
        "(see python -m motion synth --help)",
    ),
    (
        ["info", B, "--frobnicate"],
        "python -m motion: unrecognized arguments: --frobnicate (see python -m motion --help)",
    ),
]


@pytest.mark.parametrize(("argv", "expected"), FILE_CASES + USAGE_CASES)
def test_missing_files_and_malformed_command_lines(tmp_path, capsys, argv, expected):
    argv = [str(tmp_path / "out") if a == "OUT" else a for a in argv]
    assert_message(_error_line(capsys, argv), expected)


def test_debug_shows_the_traceback_then_the_line(capsys):
    for argv in (["--debug", "info", "/nonexistent.bvh"], ["info", "/nonexistent.bvh", "--debug"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("Traceback (most recent call last):")
        assert err.endswith("error: /nonexistent.bvh: No such file or directory\n")


def test_the_installed_entry_point_prints_one_line_and_exits_2(tmp_path):
    """The real ``python -m motion`` (a subprocess: exit status and streams as a user sees)."""
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "motion",
            "synth",
            "--reference",
            B,
            "--out",
            str(tmp_path),
            "fps=inf",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert (out.returncode, out.stderr) == (
        2,
        "error: synth: fps must be a finite number; got inf\n",
    )


def test_help_is_plain_text_and_synth_help_lists_every_setting(capsys):
    assert main(["--help"]) == 0
    top = capsys.readouterr().out
    assert main(["synth", "--help"]) == 0
    synth = capsys.readouterr().out
    for text in (top, synth):
        assert "``" not in text and ":class:" not in text and ":func:" not in text
    for f in dataclasses.fields(SynthConfig):
        assert f"\n  {f.name} (default " in synth, f.name
        assert " ".join(f.metadata["setting"].doc.split()[:4]) in " ".join(synth.split()), f.name
    assert "  fps (default 25): a number in (0, 1000]\n" in synth
    assert "  size (default 160x120): a list of 2 integers in [8, 4096], e.g. 320x240\n" in synth
    assert (
        "  replace (default none): a list of 2 numbers in [0, 1], e.g. 0.4,0.5, or none\n" in synth
    )


def test_info_explains_parts_and_the_landmark_roles_they_are_built_from(capsys):
    assert main(["info", B]) == 0
    out = capsys.readouterr().out
    assert (
        "body parts: all 15 mapped; each part is a capsule between two of 20 landmark roles, "
        "and each role is placed at the mean of the joints" in out
    )
    assert "  parts (15: from role -> to role):\n    pelvis: hips -> spine\n" in out
    assert "    thigh_l: hip_l -> knee_l\n" in out
    assert "  landmark roles (20: role: joints):\n" in out and "    knee_l: LeftLeg\n" in out


def test_synth_says_what_it_wrote(tmp_path, capsys):
    out = tmp_path / "seq"
    argv = ["synth", "--reference", B, "--out", str(out)]
    assert main([*argv, "size=16x12", "focal_px=30", "fps=5", "cameras=2", "videos=true"]) == 0
    names = ("sequence.npz", "sequence.json", "cam1.avi", "cam2.avi")
    names += ("cam1_background.png", "cam2_background.png", "calibration.toml")
    files = [out / n for n in names]
    assert capsys.readouterr().out == (
        f"wrote 15 frames from 2 camera(s): {', '.join(str(f) for f in files)}\n"
        f"register it: python -m motion register --reference {B} --video {files[2]} --video "
        f"{files[3]} --calibration {files[6]} --out {out / 'registration'} (the pictures of the "
        "empty scene beside the videos are found by their names)\n"
    )
    assert all(f.is_file() for f in files)


def test_settings_may_come_on_either_side_of_an_option(tmp_path, capsys):
    """key=value settings before and after other options all count, where argparse would
    take the first run and call the rest unrecognised (one given twice is still refused); an
    unrecognised argument that is no setting is still one usage line."""
    out = tmp_path / "seq"
    argv = ["synth", "fps=5", "--reference", B, "size=16x12", "--out", str(out), "focal_px=30"]
    assert main(argv) == 0
    assert capsys.readouterr().out.startswith("wrote 15 frames from 1 camera(s)")
    meta = json.loads((out / "sequence.json").read_text())
    assert meta["video_rate_hz"] == 5
    assert meta["config"]["size"] == [16, 12] and meta["config"]["focal_px"] == 30
    assert main([*argv, "fps=7"]) == 2
    assert "fps is given twice" in capsys.readouterr().err
    assert main(["info", B, "fps=5"]) == 2  # info takes no settings
    assert "unrecognized arguments: fps=5" in capsys.readouterr().err


def test_synth_config_checks_itself():
    """The same checks from Python: at construction and by validate()."""
    with pytest.raises(SynthConfigError, match=r"^SynthConfig: noise_px must be >= 0; got -5$"):
        SynthConfig(noise_px=-5)
    with pytest.raises(ValueError, match=r"^SynthConfig: fps must be a finite number; got inf$"):
        SynthConfig(fps=float("inf"))
    with pytest.raises(SynthConfigError, match=r"^SynthConfig: size must be a list of 2"):
        SynthConfig(size=[64])
    cfg = SynthConfig(fps=30, size=(64, 48), articulation={"LeftLeg": 20})
    assert (cfg.fps, cfg.size, cfg.articulation) == (30.0, [64, 48], {"LeftLeg": 20.0})
    assert type(cfg.fps) is float
    cfg.path_m = [0.0, 1.0]
    with pytest.raises(SynthConfigError, match=r"path_m must be a list of 3 numbers"):
        cfg.validate()
    assert SynthConfig.from_assignments(["replace=none", "camera_distance_m=none"]).replace is None


@settings(max_examples=200, deadline=None)
@given(
    key=st.sampled_from([f.name for f in dataclasses.fields(SynthConfig)] + ["x"]),
    text=st.text(max_size=16),
)
def test_fuzzed_synth_settings_give_a_setting_error_or_a_valid_config(key, text):
    try:
        cfg = SynthConfig.from_assignments([f"{key}={text}"])
    except SynthConfigError as err:
        assert "\n" not in str(err)
        return
    cfg.validate()


# A small valid BVH (two joints, three frames) to truncate and flip for the info command.
SMALL_BVH = b"""HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT Spine
  {
    OFFSET 0 5 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    End Site
    {
      OFFSET 0 5 0
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.0083333
0 30 0 0 0 0 0 0 0
1 30 0 0 10 0 5 0 0
2 30 0 0 20 0 10 0 0
"""


@st.composite
def _mutated_bvh(draw) -> bytes:
    data = SMALL_BVH
    if draw(st.booleans()):
        data = data[: draw(st.integers(0, len(data)))]
    for _ in range(draw(st.integers(0, 3))):
        if not data:
            break
        i = draw(st.integers(0, len(data) - 1))
        data = (
            data[:i]
            + bytes([draw(st.sampled_from(b"0123456789.-e{} \nXZ\x00\xff"))])
            + data[i + 1 :]
        )
    return data


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=_mutated_bvh())
def test_info_never_prints_a_traceback_on_a_damaged_bvh(tmp_path, capsys, data):
    path = tmp_path / "damaged.bvh"
    path.write_bytes(data)
    status = main(["info", str(path)])
    err = capsys.readouterr().err
    assert status in (0, 2)
    assert err == "" if status == 0 else (err.startswith("error: ") and err.count("\n") == 1)
