"""Malformed configs, overrides and command lines of ``python -m experiments``: each case is
pinned to its one line on stderr and exit status 2 (never a traceback; ``--debug`` adds one);
valid oddities work; ``tiny`` never replaces an explicit value; the same seed gives
byte-identical accuracy files; the config reader survives truncations and byte flips."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import experiments.config as experiments_config
from experiments.__main__ import main
from experiments.config import ConfigError, load_config, parse_overrides
from experiments.runner import EXPERIMENTS, run_config
from experiments.stick_pose import TIMINGS, StickPoseConfig
from experiments.stick_time import StickTimeConfig
from tests.conftest import assert_message, cli_error_line

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "experiments" / "configs"
SCHEMAS = {k: v.schema for k, v in EXPERIMENTS.items()}
KNOWN = ", ".join(repr(name) for name in sorted(EXPERIMENTS))  # as the error lists them
METHODS = "'dtw', 'chain', 'robust', 'c2f', 'c2f_robust'"
ST_KEYS = ", ".join(f.name for f in dataclasses.fields(StickTimeConfig))
ST = "experiment: stick_time\n"


@pytest.fixture(autouse=True)
def _at_the_repository_root(monkeypatch):
    """The shipped configs name the bundled BVH relative to the repository root."""
    monkeypatch.chdir(ROOT)


def _error_line(capsys, argv: list[str]) -> str:
    return cli_error_line(capsys, main, argv)


FILE_CASES = [
    # (id, file content (None: no file), message with {f} for the file's path)
    ("no-file", None, "{f}: no such config file"),
    (
        "sweep-mapping",
        ST + "sweep: {corrupt: false}\n",
        "{f}:2: sweep must be a list of mappings, one per run, "
        "e.g. [{corrupt: false}, {corrupt: true}]; got {corrupt: false}",
    ),
    (
        "sweep-scalar",
        ST + "sweep: 3\n",
        "{f}:2: sweep must be a list of mappings, one per run, "
        "e.g. [{corrupt: false}, {corrupt: true}]; got 3",
    ),
    (
        "sweep-entry-scalar",
        ST + "sweep:\n  - corrupt\n",
        "{f}:2: sweep[0] must be a mapping of field: value, e.g. {corrupt: false}; got 'corrupt'",
    ),
    (
        "sweep-unknown-key",
        ST + "sweep:\n  - {fsp: 30}\n",
        f"{{f}}:3: sweep[0]: unknown key 'fsp' for StickTimeConfig (did you mean 'fps'?); "
        f"known: {ST_KEYS}",
    ),
    (
        "sweep-bad-value",
        ST + "sweep:\n  - {fps: -1}\n",
        "{f}:3: sweep[0]: fps must be in (0, 1000]; got -1",
    ),
    (
        "sweep-repeated",
        ST + "sweep:\n  - {corrupt: false}\n  - {corrupt: false}\n",
        "{f}:2: sweep[1] repeats sweep[0] (corrupt=False); expected each run once",
    ),
    (
        "experiment-list",
        "experiment: [stick_time]\n",
        f"{{f}}:1: experiment must be one of {KNOWN}; got ['stick_time']",
    ),
    (
        "experiment-unknown",
        "experiment: nonsense\n",
        f"{{f}}:1: unknown experiment 'nonsense'; known: {KNOWN}",
    ),
    (
        "no-experiment",
        "fps: 25\n",
        f"{{f}}: a config must be a mapping with an 'experiment' key ({KNOWN}); got {{fps: 25}}",
    ),
    (
        "empty",
        "",
        f"{{f}}: a config must be a mapping with an 'experiment' key ({KNOWN}); got an empty file",
    ),
    (
        "a-list",
        "- 1\n",
        f"{{f}}: a config must be a mapping with an 'experiment' key ({KNOWN}); got [1]",
    ),
    (
        "duplicate-key",
        ST + "fps: 30\nseed: 1\nfps: 25\n",
        "{f}:4: duplicate key 'fps' (first given on line 2); expected each key once",
    ),
    (
        "duplicate-key-in-sweep",
        ST + "sweep:\n  - {seed: 1, seed: 2}\n",
        "{f}:3: duplicate key 'seed' (first given on line 3); expected each key once",
    ),
    (
        "unknown-key",
        ST + "corupt: true\n",
        f"{{f}}:2: unknown key 'corupt' for StickTimeConfig (did you mean 'corrupt'?); known: {ST_KEYS}",
    ),
    ("wrong-type", ST + "noise: lots\n", "{f}:2: noise must be a number in [0, 1]; got 'lots'"),
    ("yaml-1.1-boolean", ST + "corrupt: yes\n", "{f}:2: corrupt must be true or false; got 'yes'"),
    ("out-of-range", ST + "max_step: 0\n", "{f}:2: max_step must be >= 1; got 0"),
    (
        "unknown-method",
        ST + "methods: [dtw, bogus]\n",
        f"{{f}}:2: methods[1] must be one of {METHODS}; got 'bogus'",
    ),
    (
        "missing-bvh",
        ST + "bvh: nowhere.bvh\n",
        f"{{f}}:2: bvh must name an existing file; got 'nowhere.bvh' (not found, relative to {ROOT})",
    ),
    ("not-yaml", ST + "fps: [25\n", r"re:{f}:3:1: not valid YAML: .+"),
    ("tab-indent", ST + "\tfps: 25\n", r"re:{f}:2:1: not valid YAML: .+"),
    ("not-utf8", b"experiment: stick_time\n\xff\n", "{f}:2: expected UTF-8 text; got byte 0xff"),
    ("control-char", ST + "\x01\n", "{f}:2: not valid YAML: character U+0001 is not allowed"),
    (
        "python-tag",
        ST + "bvh: !!python/name:os.system\n",
        r"re:{f}:2:6: not valid YAML: could not determine a constructor for the tag .*python/name.*",
    ),
    (
        "bad-tagged-value",
        ST + "fps: !!float x\n",
        r"re:{f}: not valid YAML: a tagged value cannot be read \(ValueError: .+\)",
    ),
]


@pytest.mark.parametrize(
    ("content", "expected"), [c[1:] for c in FILE_CASES], ids=[c[0] for c in FILE_CASES]
)
def test_malformed_config_files(tmp_path, capsys, content, expected):
    path = tmp_path / "bad.yaml"
    if isinstance(content, str):
        path.write_text(content)
    elif content is not None:
        path.write_bytes(content)
    message = _error_line(capsys, ["run", str(path), f"out_dir={tmp_path / 'out'}"])
    assert_message(
        message,
        expected.replace("{f}", re.escape(str(path)) if expected.startswith("re:") else str(path)),
    )


def test_a_folder_as_the_config_file(tmp_path, capsys):
    message = _error_line(capsys, ["run", str(tmp_path)])
    assert message == f"{tmp_path}: cannot read the config file (Is a directory)"


def _cfg(name: str) -> str:
    return str(CONFIGS / f"{name}.yaml")


OVERRIDE_CASES = [
    # (id, config, overrides, message; {cwd} and {cfg} are filled in)
    (
        "empty-value",
        "stick_time",
        ["fps="],
        "command line: fps must be a number in (0, 1000]; got nothing (an empty value)",
    ),
    ("negative-fps", "stick_time", ["fps=-25"], "command line: fps must be in (0, 1000]; got -25"),
    (
        "infinite-fps",
        "stick_time",
        ["fps=.inf"],
        "command line: fps must be a finite number; got inf",
    ),
    (
        "text-fps",
        "stick_time",
        ["fps=fast"],
        "command line: fps must be a number in (0, 1000]; got 'fast'",
    ),
    ("zero-frames", "stick_pose", ["frames=0"], "command line: frames must be >= 1; got 0"),
    ("negative-frames", "stick_pose", ["frames=-3"], "command line: frames must be >= 1; got -3"),
    (
        "fractional-frames",
        "stick_pose",
        ["frames=2.5"],
        "command line: frames must be an integer >= 1; got 2.5",
    ),
    (
        "unknown-method",
        "stick_time",
        ["methods=[dtw,bogus]"],
        f"command line: methods[1] must be one of {METHODS}; got 'bogus'",
    ),
    (
        "no-methods",
        "stick_time",
        ["methods=[]"],
        f"command line: methods must be a non-empty list of names from {METHODS}; got []",
    ),
    (
        "methods-not-a-list",
        "stick_time",
        ["methods=dtw"],
        f"command line: methods must be a non-empty list of names from {METHODS}; got 'dtw'",
    ),
    (
        "zero-distance",
        "stick_pose",
        ["camera_distance=0"],
        "command line: camera_distance must be in (0, 1000]; got 0",
    ),
    ("negative-noise", "stick_time", ["noise=-1"], "command line: noise must be in [0, 1]; got -1"),
    (
        "unknown-camera",
        "stick_pose",
        ["camera=fisheye"],
        "command line: camera must be one of 'perspective', 'orthographic'; got 'fisheye'",
    ),
    (
        "noise-level-out-of-range",
        "stick_pose",
        ["sweep_noise=[0.1,2]"],
        "command line: sweep_noise[1] must be in [0, 1]; got 2",
    ),
    (
        "yaml-1.1-boolean",
        "stick_pose",
        ["tiny=yes"],
        "command line: tiny must be true or false; got 'yes'",
    ),
    (
        "negative-seed",
        "stick_time",
        ["seed=-1"],
        "command line: seed must be in [0, 4294967295]; got -1",
    ),
    (
        "unknown-key",
        "stick_time",
        ["colour=red"],
        f"command line: unknown key 'colour' for StickTimeConfig; known: {ST_KEYS}",
    ),
    (
        "no-equals",
        "stick_time",
        ["fps"],
        "command line: expected key=value (e.g. seed=1); got 'fps'",
    ),
    ("no-key", "stick_time", ["=3"], "command line: expected key=value (e.g. seed=1); got '=3'"),
    (
        "key-twice",
        "stick_time",
        ["seed=1", "seed=2"],
        "command line: seed is given twice; expected each key once",
    ),
    (
        "not-yaml",
        "stick_time",
        ["methods=[dtw"],
        r"re:command line: methods=\[dtw: not valid YAML: .+",
    ),
    (
        "missing-bvh",
        "stick_time",
        ["bvh=nowhere.bvh"],
        "command line: bvh must name an existing file; got 'nowhere.bvh' (not found, relative to {cwd})",
    ),
    (
        "key-also-in-the-sweep",
        "stick_time",
        ["corrupt=false"],
        "command line: corrupt is also set by {cfg}:12: sweep[0]; expected each key in one place "
        "(drop corrupt= from the command line, or edit the sweep)",
    ),
    (
        "named-data-missing",
        "pose2sim_real",
        ["data=/nonexistent"],
        "data=/nonexistent: expected the shared data folder (with "
        "video/pose2sim_balancing_trial/calibration/Calib_qualisys.toml and "
        "keypoints/pose2sim_balancing_trial); got no such folder",
    ),
    # found once the data is read (before any heavy work)
    (
        "step-too-small",
        "stick_time",
        ["tiny=true", "max_step=1"],
        "max_step=1: 25 input frames cannot reach the last of 120 reference frames in steps of "
        "at most 1; expected max_step >= 5 (raise max_step or fps)",
    ),
    (
        "too-few-input-frames",
        "stick_time",
        ["tiny=true", "fps=1"],
        "fps=1: 1 input frame(s) from 120 reference frames at 120 Hz; expected at least 2: raise fps",
    ),
    (
        "more-frames-than-the-bvh",
        "stick_pose",
        ["frames=1000"],
        "frames=1000: motion/data/cmu_02_01_walk.bvh has 343 frames; expected at most 343",
    ),
    (
        "figure-behind-the-camera",
        "stick_pose",
        ["tiny=true", "camera_distance=0.1"],
        "camera_distance=0.1: landmarks reach depth -0.58 m from the camera; expected every "
        "landmark in front of it (raise camera_distance)",
    ),
    (
        "full-matrix-too-large",
        "stick_time",
        ["tiny=true", "full_matrix_max_cells=1"],
        "full_matrix_max_cells=1: the full cost matrix has 25 x 120 cells, more than that: use "
        "methods=[c2f] for long sequences (coarse-to-fine, no full matrix)",
    ),
]


@pytest.mark.parametrize(
    ("config", "overrides", "expected"),
    [c[1:] for c in OVERRIDE_CASES],
    ids=[c[0] for c in OVERRIDE_CASES],
)
def test_malformed_overrides(tmp_path, capsys, config, overrides, expected):
    argv = ["run", _cfg(config), f"out_dir={tmp_path}", *overrides]
    message = _error_line(capsys, argv)
    assert_message(message, expected.replace("{cwd}", os.getcwd()).replace("{cfg}", _cfg(config)))


USAGE_CASES = [
    (
        [],
        "python -m experiments: the following arguments are required: {run,summarise,list,demo} (see python -m experiments --help)",
    ),
    (
        ["bogus"],
        r"re:python -m experiments: argument \{run,summarise,list,demo\}: invalid choice: 'bogus' .*\(see python -m experiments --help\)",
    ),
    (
        ["run"],
        "python -m experiments run: the following arguments are required: config (see python -m experiments run --help)",
    ),
    (
        ["run", "x.yaml", "--frobnicate"],
        "python -m experiments: unrecognized arguments: --frobnicate (see python -m experiments --help)",
    ),
    (
        ["demo", "--seed", "-1"],
        "python -m experiments demo: argument --seed: expected an integer >= 0; got -1 (see python -m experiments demo --help)",
    ),
    (
        ["demo", "--seed", "x"],
        "python -m experiments demo: argument --seed: expected an integer >= 0; got 'x' (see python -m experiments demo --help)",
    ),
    (["demo", "--bvh", "nowhere.bvh"], "--bvh: expected an existing BVH file; got 'nowhere.bvh'"),
]


@pytest.mark.parametrize(
    ("argv", "expected"), USAGE_CASES, ids=lambda v: " ".join(v) if isinstance(v, list) else None
)
def test_malformed_command_lines(capsys, argv, expected):
    assert_message(_error_line(capsys, argv), expected)


def test_debug_shows_the_traceback_then_the_line(capsys, tmp_path):
    for argv in (
        ["--debug", "run", _cfg("stick_time"), "fps=-1"],
        ["run", _cfg("stick_time"), "fps=-1", "--debug"],
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("Traceback (most recent call last):")
        assert err.endswith("error: command line: fps must be in (0, 1000]; got -1\n")


def test_the_installed_entry_point_prints_one_line_and_exits_2(tmp_path):
    """The real ``python -m experiments`` (a subprocess: exit status and streams as a user sees
    them)."""
    bad = tmp_path / "bad.yaml"
    bad.write_text(ST + "fps: -25\n")
    out = subprocess.run(
        [sys.executable, "-m", "experiments", "run", str(bad)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert out.returncode == 2
    assert out.stderr == f"error: {bad}:2: fps must be in (0, 1000]; got -25\n"


def test_help_is_plain_text_and_lists_the_experiments_and_their_fields(capsys):
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "``" not in text and ":class:" not in text and ":func:" not in text
    headers = {line.split(" (")[0]: line for line in text.splitlines() if "; schema " in line}
    for name, exp in EXPERIMENTS.items():  # each lists its configs, its own first by name
        assert headers[name].endswith(f"; schema {exp.schema.__name__}):"), headers[name]
        assert f"experiments/configs/{name}.yaml" in headers[name], headers[name]
        assert exp.schema().out_dir == f"runs/{name}"  # the schema's NAME is its name here
    assert "experiments/configs/register_movements.yaml" in headers["register_synthetic"]
    assert "  seed, out_dir, tiny, bvh, fps, warp" in text  # every schema's, declared once
    assert main(["list"]) == 0
    listing = capsys.readouterr().out
    assert "  fps (default 25.0): a number in (0, 1000]\n      input frame rate in Hz" in listing
    assert (
        f"  methods (default ['dtw', 'chain', 'robust']): a non-empty list of names from {METHODS}"
        in listing
    )
    assert (
        "  tiny=true sets: frames=12, throughput_poses=200, throughput_rounds=1, sweep_noise=[0.0, 0.036]"
        in listing
    )
    assert (  # out_dir's default and tiny's meaning are each experiment's own
        "  out_dir (default 'runs/register_synthetic'): a string\n      output folder\n"
        "  tiny (default false): true or false\n"
        "      a quick run (8 frames, 30 particles, 2 iterations)\n"
    ) in listing
    assert main(["run", "--help"]) == 0
    assert "``" not in capsys.readouterr().out


def test_valid_oddities_work(tmp_path):
    """YAML 1.2 scalars (1e3 is a number, 010 is ten), integral floats for integers, numbers
    for strings, a UTF-8 byte-order mark, an empty sweep."""
    assert parse_overrides(["fps=1e3", "seed=010", "methods=[dtw, robust]", "out_dir=2024"]) == {
        "fps": 1000.0,
        "seed": 10,
        "methods": ["dtw", "robust"],
        "out_dir": 2024,
    }
    path = tmp_path / "odd.yaml"
    path.write_bytes(b"\xef\xbb\xbfexperiment: stick_pose\nframes: 1e1\nout_dir: 2024\nsweep: []\n")
    name, cfg, sweep = load_config(path, SCHEMAS, {"camera_distance": 7})
    assert (name, cfg.frames, cfg.out_dir, cfg.camera_distance, sweep) == (
        "stick_pose",
        10,
        "2024",
        7.0,
        [],
    )
    assert type(cfg.camera_distance) is float


def test_one_config_error_and_one_strict_reader_with_motion_register():
    """experiments' ConfigError and YAML reader are motion's (motion register's --config)."""
    import motion.registration.config
    import motion.settings
    import motion.settings_yaml

    assert ConfigError is motion.settings.ConfigError is motion.registration.config.ConfigError
    assert experiments_config.read_yaml is motion.settings_yaml.read_yaml


def test_tiny_never_replaces_an_explicit_value():
    """tiny=true reduces the file's values (throughput 10000 -> 200 poses) but every key
    given on the command line keeps its value."""
    path = CONFIGS / "stick_pose.yaml"
    _, cfg, _ = load_config(path, SCHEMAS, {"tiny": True})
    assert (cfg.frames, cfg.throughput_poses, cfg.throughput_rounds) == (12, 200, 1)
    _, cfg, _ = load_config(path, SCHEMAS, {"tiny": True, "frames": 20, "throughput_rounds": 2})
    assert (cfg.frames, cfg.throughput_poses, cfg.throughput_rounds) == (20, 200, 2)
    _, cfg, _ = load_config(path, SCHEMAS, {"frames": 20})
    assert (cfg.frames, cfg.throughput_poses, cfg.tiny) == (20, 10000, False)
    assert StickPoseConfig.TINY["frames"] == 12


def test_same_seed_same_accuracy_bytes_and_progress_without_a_terminal(tmp_path, capsys):
    """stick_pose draws random rotations, translations and noise: the same seed gives
    byte-identical metrics.json and per_frame.csv; the timings live in timings.json. Run
    without a terminal, progress comes as plain lines on stdout."""
    config = _cfg("stick_pose")
    assert main(["run", config, "tiny=true", f"out_dir={tmp_path / 'a'}"]) == 0
    out = capsys.readouterr().out
    assert (
        "stick_pose: throughput rounds: 0/1\n" in out
        and "stick_pose: throughput rounds: 1/1 (" in out
    )
    run_config(config, {"tiny": True, "out_dir": str(tmp_path / "b")})
    run_config(config, {"tiny": True, "out_dir": str(tmp_path / "c"), "seed": 1})
    a, b, c = (tmp_path / d for d in "abc")
    for name in ("metrics.json", "per_frame.csv"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert (a / "metrics.json").read_bytes() != (
        c / "metrics.json"
    ).read_bytes()  # the seed matters
    timings = json.loads((a / "timings.json").read_text())
    assert set(timings) == set(TIMINGS) and all(v > 0 for v in timings.values())
    assert not set(TIMINGS) & set(json.loads((a / "metrics.json").read_text()))


# ------------------------------------------------------------------------------- fuzzing

SOURCES = [(CONFIGS / f"{n}.yaml").read_bytes() for n in ("stick_time", "stick_pose")]
SPECIAL = b":[]{}-,#&*!|>'\"%@` \t\n"


@st.composite
def _mutated(draw) -> bytes:
    """A valid config, truncated and/or with a few bytes flipped, replaced or inserted."""
    data = draw(st.sampled_from(SOURCES))
    if draw(st.booleans()):
        data = data[: draw(st.integers(0, len(data)))]
    for _ in range(draw(st.integers(0, 4))):
        if not data:
            break
        i = draw(st.integers(0, len(data) - 1))
        kind = draw(st.sampled_from(["bit", "byte", "special", "insert"]))
        if kind == "bit":
            new = bytes([data[i] ^ (1 << draw(st.integers(0, 7)))])
        elif kind == "byte":
            new = bytes([draw(st.integers(0, 255))])
        else:
            new = bytes([draw(st.sampled_from(SPECIAL))])
        data = data[:i] + new + data[i + (kind != "insert") :]
    return data


@settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=_mutated())
def test_fuzzed_config_files_give_a_config_error_or_a_valid_config(tmp_path, data):
    path = tmp_path / "fuzz.yaml"
    path.write_bytes(data)
    try:
        name, cfg, sweep = load_config(path, SCHEMAS)
    except ConfigError as err:
        assert "\n" not in str(err) and str(err)
        return
    assert isinstance(cfg, SCHEMAS[name])
    cfg.validate()  # the returned config holds to its schema
    assert all(isinstance(entry, dict) for entry in sweep)


@settings(max_examples=200, deadline=None)
@given(
    key=st.sampled_from(
        [f.name for f in dataclasses.fields(StickTimeConfig)] + ["experiment", "x"]
    ),
    text=st.text(max_size=12),
)
def test_fuzzed_overrides_give_a_config_error_or_a_valid_config(key, text):
    try:
        overrides = parse_overrides([f"{key}={text}"])
        _, cfg, _ = load_config(CONFIGS / "stick_time.yaml", SCHEMAS, overrides)
    except ConfigError as err:
        assert "\n" not in str(err)
        return
    cfg.validate()


def test_tiny_runs_a_sweeps_first_and_last_entries_after_checking_them_all(tmp_path):
    """A long sweep stays a quick check under tiny: every entry is validated (a bad one in
    the middle still fails) but only the first and last run."""
    entries = "".join(f"  - {{seed: {s}}}\n" for s in range(5))
    path = tmp_path / "sweep.yaml"
    path.write_text(f"experiment: stick_time\nsweep:\n{entries}")
    assert [e["seed"] for e in load_config(path, SCHEMAS, {"tiny": True})[2]] == [0, 4]
    assert [e["seed"] for e in load_config(path, SCHEMAS)[2]] == [0, 1, 2, 3, 4]
    path.write_text(f"experiment: stick_time\nsweep:\n{entries}  - {{fps: -1}}\n  - {{seed: 9}}\n")
    with pytest.raises(ConfigError, match=r"sweep\[5\]"):
        load_config(path, SCHEMAS, {"tiny": True})


def test_tiny_reduces_a_sweep_entrys_own_values_too(tmp_path):
    """A sweep entry's own value of a key that tiny reduces (a whole video, ``frames: 0`` in
    register_movements) does not undo tiny; entries that then coincide run once."""
    path = tmp_path / "sweep.yaml"
    path.write_text(
        "experiment: stick_pose\nsweep:\n  - {seed: 0, frames: 40}\n  - {seed: 1}\n"
        "  - {seed: 2, frames: 50}\n"
    )
    assert load_config(path, SCHEMAS, {"tiny": True})[2] == [
        {"seed": 0, "frames": 12},
        {"seed": 2, "frames": 12},
    ]
    assert [e.get("frames") for e in load_config(path, SCHEMAS)[2]] == [40, None, 50]
    path.write_text("experiment: stick_pose\nsweep:\n  - {frames: 40}\n  - {frames: 50}\n")
    assert load_config(path, SCHEMAS, {"tiny": True})[2] == [{"frames": 12}]
