"""The ``register`` and ``demo`` sub-commands of ``python -m motion`` (parsers and bodies).

``register`` is :func:`motion.registration.command.run_register` on the command line's
files (or, with ``--write-config PATH``, writes every setting with its default and meaning
to a YAML file for ``--config``: :func:`motion.registration.config.config_template`);
``demo`` renders a synthetic student video from the bundled walk of one performer (``motion
synth``, with its ``calibration.toml``) and registers the bundled walk of another against
it, as a user would, then prints where the report is.
"""

from __future__ import annotations

import argparse
import dataclasses
import errno
import textwrap
from pathlib import Path

from motion.cli import UsageError, add_debug
from motion.registration.command import RegisterJob, run_register, summary_lines
from motion.registration.config import RegisterConfig, config_template, load_config
from motion.synth import (
    BACKGROUND_SUFFIX,
    CALIBRATION_FILE,
    SynthConfig,
    save_sequence,
    synthesize,
)

__all__ = [
    "add_demo_parser",
    "add_register_parser",
    "demo_command",
    "register_command",
    "write_config",
]

DATA = Path(__file__).resolve().parents[1] / "data"
#: the demo's reference and student: two performers of the same action (CMU 02_01, 07_01)
DEMO_REFERENCE = DATA / "cmu_02_01_walk.bvh"
DEMO_STUDENT = DATA / "cmu_07_01_walk.bvh"
#: the demo's synthetic video (``motion synth`` settings): one camera, 25 fps, the student
#: turned 30 degrees from the camera's axis
DEMO_SYNTH = ["fps=25", "size=240x180", "focal_px=400", "yaw_deg=30", "videos=true"]
#: the demo's registration settings (fewer particles than the defaults: under 3 minutes)
DEMO_SETTINGS = (
    "refine.particles=60",
    "refine.iterations=4",
    "refine.restarts=1",
    # the synthetic scene is one flat colour: the median background against the clean plate
    # with a low threshold keeps the grey torso, which MOG2 would call a shadow
    "video.background=median",
    "video.threshold=12",
    # the rendered capsule figure is not a photographed person: the human-pose detector
    # misses it on some frames and misplaces its joints on others, so it would mislead more
    # than it observes (docs/decisions/001-person-detector.md)
    "perception.detector=none",
)

EXAMPLE = """\
example (a synthetic sequence is a complete input):
  python -m motion synth --reference motion/data/cmu_07_01_walk.bvh --out runs/student \\
      videos=true size=240x180 focal_px=400
  python -m motion register --reference motion/data/cmu_02_01_walk.bvh \\
      --video runs/student/cam1.avi --calibration runs/student/calibration.toml \\
      --background runs/student/cam1_background.png --out runs/registration \\
      refine.particles=60 video.background=median video.threshold=12 perception.detector=none
"""


def _settings_lines(obj, prefix: str = "") -> list[str]:
    """``key (default)`` of every setting, one per line, nested groups dotted."""
    lines = []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        name = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            lines += _settings_lines(value, f"{name}.")
        else:
            lines.append(f"  {name} = {value!r}")
    return lines


def _register_epilog() -> str:
    cfg = RegisterConfig()
    keys = (
        _settings_lines(cfg.video, "video.")
        + _settings_lines(cfg.perception, "perception.")
        + _settings_lines(cfg.registration)
        + _settings_lines(cfg.movement, "movement.")
        + _settings_lines(cfg.findings, "findings.")
    )
    return "\n".join(
        [
            EXAMPLE,
            "settings (key=value after the options, or the same keys in --config YAML; values "
            "are read as YAML; the stages' docstrings in motion/registration/ explain each, "
            "and --write-config PATH writes them all with their meanings):",
            *keys,
        ]
    )


def _person(text: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise UsageError(
            f"--person must be X,Y in video pixels (e.g. 640,360); got {text!r}"
        ) from None
    return x, y


#: the two forms of ``register`` (``--reference``, ``--video`` and ``--out`` are required
#: unless ``--write-config`` is given: :func:`register_command` checks)
REGISTER_USAGE = """\
%(prog)s [-h] [--debug] --reference REFERENCE --video VIDEO
           [--calibration CALIBRATION] [--config CONFIG] [--person X,Y]
           [--background BACKGROUND] [--keypoints KEYPOINTS] --out OUT [--quiet]
           [key=value ...]
       %(prog)s --write-config PATH [--force] [--config CONFIG] [key=value ...]"""

#: the options that only a registration takes (not ``--write-config``)
REGISTRATION_ONLY = (
    ("--reference", "reference"),
    ("--video", "video"),
    ("--out", "out"),
    ("--calibration", "calibration"),
    ("--person", "person"),
    ("--background", "background"),
    ("--keypoints", "keypoints"),
)


def add_register_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "register",
        usage=REGISTER_USAGE,
        help="register a reference motion to video: time warp, body transform, joint differences",
        description=textwrap.fill(
            "Register a 3-D reference motion (BVH) to a video of a student doing the same "
            "movement, seen by one or more static cameras: for every video frame, the "
            "reference frame it matches (C), the body's rotation and position (T) and how "
            "each joint differs (A). Writes registration.npz, summary.json, student.bvh, "
            "joint_angles.csv/.mot, an overlay video per camera and report.html to --out.",
            88,
        ),
        epilog=_register_epilog(),
    )
    add_debug(p, top=False)
    p.add_argument("--reference", type=Path, default=None, help="the reference motion (BVH)")
    p.add_argument(
        "--video",
        type=Path,
        action="append",
        default=None,
        help="a video of the student; repeat for each synchronised camera",
    )
    p.add_argument(
        "--calibration",
        type=Path,
        default=None,
        help="Pose2Sim-style calibration.toml of the cameras (required for 2+ cameras; "
        "without it one camera gets a nominal 55-degree field of view)",
    )
    p.add_argument("--config", type=Path, default=None, help="YAML file of settings (keys below)")
    p.add_argument(
        "--person",
        type=_person,
        default=None,
        metavar="X,Y",
        help="pixel near the person to follow in the first frame (default: the largest)",
    )
    p.add_argument(
        "--background",
        type=Path,
        action="append",
        default=[],
        help="a picture of the empty scene (clean plate), one per --video in the same order "
        "(default: the picture named after each video with _background.png beside it, as "
        "motion synth writes it, else the background is learnt from the video itself)",
    )
    p.add_argument(
        "--keypoints",
        type=Path,
        action="append",
        default=[],
        help="2-D joints as an extra observation: an OpenPose JSON folder or a Sports2D TRC "
        "per camera (repeat, in the --video order), or one folder of per-camera JSON folders",
    )
    p.add_argument("--out", type=Path, default=None, help="output folder (created)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument(
        "--write-config",
        type=Path,
        default=None,
        metavar="PATH",
        help="register nothing: write every setting with its default value and meaning to "
        "PATH, a YAML file to edit and give back with --config (with --config and key=value "
        "settings, their values); an existing PATH is kept unless --force",
    )
    p.add_argument(
        "--force", action="store_true", help="with --write-config: replace an existing PATH"
    )
    p.add_argument("overrides", nargs="*", default=[], help="key=value settings (listed below)")
    p.set_defaults(register_prog=p.prog)
    return p


def write_config(path: Path, cfg: RegisterConfig | None = None, force: bool = False) -> Path:
    """Write :func:`config_template` of ``cfg`` (default: the defaults) to ``path``; an
    existing file is replaced only with ``force``. Raises ``OSError`` naming ``path`` (its
    folder missing, it exists, it is a folder). Returns ``path``."""
    path = Path(path)
    folder = path.parent
    if not folder.is_dir():
        why = "is not a folder" if folder.exists() else "does not exist"
        raise FileNotFoundError(
            errno.ENOENT, f"cannot write it: the folder {folder} {why}", str(path)
        )
    if path.is_dir():
        raise IsADirectoryError(
            errno.EISDIR,
            "is a folder; give the settings file's name (e.g. settings.yaml)",
            str(path),
        )
    text = config_template(cfg)
    try:
        with open(path, "w" if force else "x", encoding="utf-8") as out:
            out.write(text)
    except FileExistsError:
        raise FileExistsError(
            errno.EEXIST, "already exists; --force replaces it", str(path)
        ) from None
    return path


def _usage_error(args: argparse.Namespace, message: str) -> UsageError:
    prog = args.register_prog
    return UsageError(f"{prog}: {message} (see {prog} --help)")


def write_config_command(args: argparse.Namespace) -> int:
    """``register --write-config PATH``: the settings file, no registration."""
    given = [option for option, dest in REGISTRATION_ONLY if getattr(args, dest)]
    if given:
        raise _usage_error(
            args,
            f"--write-config writes a settings file and registers nothing; leave out "
            f"{', '.join(given)}",
        )
    cfg = load_config(args.config, list(args.overrides))
    path = write_config(args.write_config, cfg, force=args.force)
    print(f"wrote the settings of motion register to {path} (give it back with --config {path})")
    return 0


def register_command(args: argparse.Namespace) -> int:
    if args.write_config is not None:
        return write_config_command(args)
    if args.force:
        raise _usage_error(args, "--force goes with --write-config (it replaces that file)")
    missing = [o for o, dest in REGISTRATION_ONLY[:3] if getattr(args, dest) is None]
    if missing:
        raise _usage_error(args, f"the following arguments are required: {', '.join(missing)}")
    job = RegisterJob(
        args.reference,
        list(args.video),
        args.out,
        args.calibration,
        args.config,
        tuple(args.overrides),
        args.person,
        tuple(args.background),
        tuple(args.keypoints),
    )
    outcome = run_register(job, show_progress=not args.quiet)
    print("\n".join(summary_lines(outcome)))
    return 0


def add_demo_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "demo",
        help="the main job on bundled data: one walker's synthetic video against another's walk",
        description=textwrap.fill(
            "Render a synthetic video of the bundled CMU walk 07_01 (subject 7) with "
            "`motion synth`, then register the bundled walk 02_01 (subject 2) to it with "
            "`motion register`, and print where the report is.",
            88,
        ),
    )
    add_debug(p, top=False)
    p.add_argument("--out", type=Path, default=Path("runs/demo"), help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("overrides", nargs="*", default=[], help="key=value registration settings")
    return p


def demo_command(args: argparse.Namespace) -> int:
    video_dir = args.out / "student_video"
    seq = synthesize(DEMO_STUDENT, SynthConfig.from_assignments(DEMO_SYNTH))
    save_sequence(seq, video_dir)
    print(f"rendered the student ({DEMO_STUDENT.name}) to {video_dir}")
    cameras = seq.meta["cameras"]
    job = RegisterJob(
        DEMO_REFERENCE,
        [video_dir / f"{name}.avi" for name in cameras],
        args.out / "registration",
        video_dir / CALIBRATION_FILE,
        None,
        (*DEMO_SETTINGS, *args.overrides),
        backgrounds=tuple(video_dir / f"{name}{BACKGROUND_SUFFIX}" for name in cameras),
    )
    outcome = run_register(job, show_progress=not args.quiet)
    print("\n".join(summary_lines(outcome)))
    print(f"open {outcome.files['report.html']} in a browser")
    return 0
