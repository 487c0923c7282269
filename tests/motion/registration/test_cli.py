"""The command line around ``motion register``: ``--write-config`` (a commented YAML file of
every setting that ``--config`` reads back) and the ``motionreg`` console script."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml

import motion.__main__ as cli_main
from motion.__main__ import main
from motion.registration.config import (
    RegisterConfig,
    _flatten,
    _leaf_keys,
    config_template,
    load_config,
    user_key,
)
from motion.settings import Settings

ROOT = Path(__file__).resolve().parents[3]
#: a template line that names a setting: ``  key: value`` or ``  # key: VALUE (not settable...``
KEY_LINE = re.compile(r"^(?P<indent> *)(?P<off># )?(?P<key>[a-z_][a-z0-9_]*):(?: (?P<rest>.*))?$")


def _write(tmp_path, capsys, *extra: str, name: str = "settings.yaml") -> Path:
    path = tmp_path / name
    assert main(["register", "--write-config", str(path), *extra]) == 0
    out = capsys.readouterr().out
    assert str(path) in out and "--config" in out
    return path


def _template_keys(text: str) -> dict[str, str]:
    """Dotted key -> its line, for every setting the template names (set or commented out),
    nesting read from the indentation."""
    keys: dict[str, str] = {}
    stack: list[str] = []
    for line in text.splitlines():
        m = KEY_LINE.match(line)
        if not m:
            continue
        depth = len(m["indent"]) // 2
        stack = [*stack[:depth], m["key"]]
        keys[".".join(stack)] = line
    return keys


def _settable(value) -> bool:
    return value is None or isinstance(value, bool | int | float | str | list | tuple | dict)


def _user_leaves() -> dict[str, object]:
    """Every leaf setting of RegisterConfig by the key the user writes, with its default."""
    cfg = RegisterConfig()
    out = {}
    for key in _leaf_keys(cfg):
        value = cfg
        for name in key.split("."):
            value = getattr(value, name)
        out[user_key(key)] = value
    return out


def test_written_template_loads_back_to_exactly_the_defaults(tmp_path, capsys):
    path = _write(tmp_path, capsys)
    loaded = load_config(path)
    # (repr: the annealing schedules inside, pgm.Geometric, do not define ==; repr also tells
    # 1 from 1.0 and a tuple from a list)
    assert repr(loaded) == repr(RegisterConfig())
    assert path.read_text(encoding="utf-8") == config_template()


def test_template_names_every_setting_with_its_meaning(tmp_path, capsys):
    text = _write(tmp_path, capsys).read_text(encoding="utf-8")
    named = _template_keys(text)
    leaves = _user_leaves()
    assert set(leaves) <= set(named), sorted(set(leaves) - set(named))
    # what YAML can hold is set (and nothing else); the rest is named in a comment
    loaded = _flatten(yaml.safe_load(text))
    assert set(loaded) == {k for k, v in leaves.items() if _settable(v)}
    unsettable = {k for k, v in leaves.items() if not _settable(v)}
    assert unsettable >= {"stage1.dtype", "refine.connection.schedule"}
    for key in unsettable:
        assert named[key].lstrip().startswith("# ") and "(not settable in a file)" in named[key]
    # the shortcuts the command line takes: stage1, refine, scale and seed at the top level
    assert {"seed", "scale", "refine.particles", "stage1.yaw_starts"} <= set(loaded)


def _comments_above(text: str, key_line: str, after: str | None = None) -> str:
    """The comment lines right above ``key_line`` (the first after the line ``after``),
    joined as one text."""
    lines = text.splitlines()
    i = lines.index(key_line, lines.index(after) if after else 0)
    above = []
    while i > 0 and lines[i - 1].lstrip().startswith("# "):
        i -= 1
        above.insert(0, lines[i].lstrip()[2:])
    return " ".join(above)


def test_each_meaning_is_the_settings_own_or_its_docstring_entry():
    text = config_template()
    named = _template_keys(text)
    cfg = RegisterConfig()
    # settings fields (motion.settings.setting) carry their own one-line meaning
    groups = {
        "video": cfg.video,
        "perception": cfg.perception,
        "stage1": cfg.registration.stage1,
        "refine": cfg.registration.refine,
        "polish": cfg.registration.polish,
        "movement": cfg.movement,
        "findings": cfg.findings,
    }
    for prefix, group in groups.items():
        assert isinstance(group, Settings)
        for f in dataclasses.fields(group):
            if dataclasses.is_dataclass(getattr(group, f.name)):
                continue  # a group (below)
            doc = " ".join(f.metadata["setting"].doc.split())
            line = named[f"{prefix}.{f.name}"]
            assert _comments_above(text, line, after=f"{prefix}:") == doc, f.name
    assert isinstance(cfg.registration, Settings)
    assert _comments_above(text, named["seed"]) == "seed of every random draw"
    # the plain dataclasses inside refine (motion.body.graph's Connections, Temporal): the
    # first sentence of the docstring's entry, else of its text naming the field
    assert _comments_above(text, named["refine.connection.pos_std"]) == (
        "metres, the joints' spread before annealing"
    )
    assert _comments_above(text, named["refine.temporal.pos_std"]) == (
        "metres, how far a part may move from one frame to the next (a random walk: no "
        "velocity is assumed)"
    )
    assert _comments_above(text, named["refine.temporal.rot_std"]) == (
        "radians, how far a part may turn from one frame to the next"
    )
    # a group names the class that documents it
    assert "motion.registration.refine.RefineSettings" in _comments_above(text, "refine:")


def test_given_settings_are_written_with_their_defaults_beside(tmp_path, capsys):
    base = tmp_path / "base.yaml"
    base.write_text("video:\n  width: 240\n", encoding="utf-8")
    path = _write(tmp_path, capsys, "--config", str(base), "refine.particles=60", "seed=3")
    text = path.read_text(encoding="utf-8")
    assert "  particles: 60  # default: 100" in text.splitlines()
    assert "seed: 3  # default: 0" in text.splitlines()
    expected = load_config(base, ["refine.particles=60", "seed=3"])
    assert repr(load_config(path)) == repr(expected)


def _error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("error: ") and captured.err.count("\n") == 1
    return captured.err[len("error: ") : -1]


def test_an_existing_file_is_kept_unless_force(tmp_path, capsys):
    path = tmp_path / "settings.yaml"
    path.write_text("refine:\n  particles: 40\n", encoding="utf-8")
    message = _error(capsys, ["register", "--write-config", str(path)])
    assert message == f"{path}: already exists; --force replaces it"
    assert path.read_text(encoding="utf-8") == "refine:\n  particles: 40\n"
    _write(tmp_path, capsys, "--force")
    assert repr(load_config(path)) == repr(RegisterConfig())


def test_a_missing_folder_is_refused_naming_it(tmp_path, capsys):
    folder = tmp_path / "nowhere"
    path = folder / "settings.yaml"
    message = _error(capsys, ["register", "--write-config", str(path)])
    assert message == f"{path}: cannot write it: the folder {folder} does not exist"
    assert not folder.exists()
    message = _error(capsys, ["register", "--write-config", str(tmp_path)])
    assert message.startswith(f"{tmp_path}: is a folder")


def test_write_config_registers_nothing_and_register_still_needs_its_inputs(tmp_path, capsys):
    prog = "python -m motion register"
    message = _error(
        capsys, ["register", "--write-config", str(tmp_path / "s.yaml"), "--video", "v.mp4"]
    )
    assert message == (
        f"{prog}: --write-config writes a settings file and registers nothing; leave out "
        f"--video (see {prog} --help)"
    )
    assert not (tmp_path / "s.yaml").exists()
    # as argparse says it for required options
    assert _error(capsys, ["register"]) == (
        f"{prog}: the following arguments are required: --reference, --video, --out "
        f"(see {prog} --help)"
    )
    assert _error(capsys, ["register", "--video", "v.mp4"]) == (
        f"{prog}: the following arguments are required: --reference, --out (see {prog} --help)"
    )
    argv = ["register", "--reference", "r.bvh", "--video", "v.mp4", "--out", "o", "--force"]
    assert _error(capsys, argv).startswith(f"{prog}: --force goes with --write-config")
    # a bad setting is the settings' one-line error, and nothing is written
    message = _error(
        capsys, ["register", "--write-config", str(tmp_path / "s.yaml"), "refine.particlez=3"]
    )
    assert message.startswith("command line: unknown setting 'refine.particlez'")
    assert not (tmp_path / "s.yaml").exists()


def test_help_shows_both_forms_and_every_group(capsys):
    assert main(["register", "--help"]) == 0
    out = capsys.readouterr().out
    assert "python -m motion register --write-config PATH [--force]" in out
    for key in ("movement.max_stalled", "findings.method_error_deg", "refine.particles"):
        assert key in out


# --------------------------------------------------------------------------- console script


def test_console_script_runs_main():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"][
        "scripts"
    ]
    assert scripts == {cli_main.CONSOLE_SCRIPT: "motion.__main__:main"}


def test_console_script_names_itself_in_messages(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["/somewhere/bin/motionreg"])
    assert _error(capsys, ["register"]).startswith("motionreg register: the following arguments")
    monkeypatch.setattr(sys, "argv", ["/somewhere/motion/__main__.py"])
    assert _error(capsys, ["register"]).startswith("python -m motion register: the following")


def test_installed_console_script(tmp_path):
    script = Path(sys.executable).parent / cli_main.CONSOLE_SCRIPT
    if not script.exists():
        pytest.skip(f"{script} not installed (pip install -e . installs it)")
    path = tmp_path / "settings.yaml"
    done = subprocess.run(
        [str(script), "register", "--write-config", str(path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert repr(load_config(path)) == repr(RegisterConfig())
    done = subprocess.run([str(script), "register"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    assert done.stderr.startswith("error: motionreg register: the following arguments are required")
