"""Command line of the motion package.

  python -m motion info FILE.bvh [--spec SPEC]
      describe a BVH file: rate, duration, units, skeleton and the body-part mapping
  python -m motion synth --reference REF.bvh [--student OTHER.bvh] --out DIR [key=value ...]
      write a synthetic sequence with its ground truth, e.g.
      fps=30 cameras=2 noise_px=2 replace=0.4,0.5 articulation=LeftLeg:20,RightArm:30
      size=320x240 videos=true seed=1  (python -m motion synth --help lists every setting)
  python -m motion register --reference REF.bvh --video V1.mp4 [--video V2.mp4 ...]
          [--calibration CAMS.toml] [--config SETTINGS.yaml] [--person X,Y] --out DIR [key=value ...]
      register the reference motion to the video(s): C, T and A per video frame, and a report
  python -m motion demo [--out DIR]
      the main job on bundled data: a synthetic video of one walker registered against another

Installed (pip install), the same commands are the console script `motionreg`:
`motionreg register ...` is `python -m motion register ...`.

Bad input prints one line, "error: ...", to stderr and exits with status 2; --debug shows
the traceback as well.
"""

from __future__ import annotations

import os

# FFmpeg inside OpenCV writes its own complaints ("moov atom not found") to stderr before our
# one-line error; bad input gets that line alone (set before cv2 is first imported)
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

import argparse
import sys
import textwrap
from pathlib import Path

from motion.bodyparts import BodyModel, BodyPartMappingError
from motion.bvh import read_bvh
from motion.cli import Parser, add_debug, run
from motion.kinematics import Skeleton
from motion.registration.cli import (
    add_demo_parser,
    add_register_parser,
    demo_command,
    register_command,
)
from motion.settings import describe
from motion.synth import CALIBRATION_FILE, SynthConfig, save_sequence, sequence_files, synthesize

__all__ = ["CONSOLE_SCRIPT", "info", "main", "parse_overrides"]

#: the console script of pyproject's ``[project.scripts]``, which runs :func:`main`
CONSOLE_SCRIPT = "motionreg"


def _body_lines(model: BodyModel) -> list[str]:
    """The body-part mapping explained: parts are capsules between two landmark roles;
    each role is the mean of the joints (or end sites) listed."""
    ends = model.part_roles.tolist()
    lines = [
        f"body parts: all {model.num_parts} mapped; each part is a capsule between two of "
        f"{len(model.roles)} landmark roles, and each role is placed at the mean of the "
        "joints (NAME.end: a joint's end site; NAME.tip: an end synthesized past a joint) listed under it",
        f"  parts ({model.num_parts}: from role -> to role):",
    ]
    for name, (a, b) in zip(model.part_names, ends, strict=True):
        lines.append(f"    {name}: {model.roles[a]} -> {model.roles[b]}")
    lines.append(f"  landmark roles ({len(model.roles)}: role: joints):")
    for role in model.roles:
        lines.append(f"    {role}: {' + '.join(model.mapping[role])}")
    return lines


def info(path: Path, spec: str | None) -> str:
    """A description of the BVH file at ``path`` (``spec``: a body-part spec to map with)."""
    bvh = read_bvh(path)
    skel = Skeleton.from_bvh(bvh)
    lines = [
        f"file: {path}",
        f"frames: {bvh.num_frames} at {bvh.frame_rate:.4g} Hz ({bvh.num_frames * bvh.frame_time:.2f} s)",
        f"joints: {skel.num_joints}, channels: {sum(len(c) for c in bvh.channels)}, "
        f"end sites: {len(bvh.end_sites)}",
        f"units: {skel.units_note}",
        "skeleton (joint <- parent: channels):",
    ]
    for j, name in enumerate(skel.names):
        parent = skel.names[skel.parents[j]] if skel.parents[j] >= 0 else "-"
        lines.append(f"  {j:3d} {name} <- {parent}: {' '.join(bvh.channels[j]) or '(none)'}")
    try:
        lines += _body_lines(BodyModel.from_skeleton(skel, spec))
    except BodyPartMappingError as err:
        lines.append(f"body parts: NOT all mapped: {err}")
    return "\n".join(lines)


def parse_overrides(items: list[str]) -> SynthConfig:
    """``key=value`` strings -> a checked :class:`SynthConfig` (see
    :meth:`SynthConfig.from_assignments`)."""
    return SynthConfig.from_assignments(items)


def _synth_epilog() -> str:
    return "\n".join(
        [
            "settings (key=value; lists separated by commas, size as WIDTHxHEIGHT, "
            "articulation as JOINT:DEGREES pairs):",
            *describe(SynthConfig),
        ]
    )


def _prog() -> str:
    """How the user called the command line, for its help and messages: ``motionreg``
    when run as the console script, else ``python -m motion``."""
    called = Path(sys.argv[0]).stem if sys.argv and sys.argv[0] else ""
    return CONSOLE_SCRIPT if called == CONSOLE_SCRIPT else "python -m motion"


def _parser(prog: str = "python -m motion") -> Parser:
    parser = Parser(prog=prog, description=__doc__)
    add_debug(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="{info,synth,register,demo}")
    p_info = sub.add_parser(
        "info",
        help="describe a BVH file: skeleton, rate, units, body parts",
        description=textwrap.fill(
            "Describe a BVH file: rate, duration, units, skeleton (joint <- parent: channels) "
            "and how its joints map to the body model's parts and landmark roles.",
            88,
        ),
    )
    add_debug(p_info, top=False)
    p_info.add_argument("file", type=Path, help="the BVH file")
    p_info.add_argument(
        "--spec", default=None, help="body-part spec file, or a bundled name (cmu_cgspeed, ...)"
    )
    p_synth = sub.add_parser(
        "synth",
        help="render a synthetic student sequence with ground truth",
        description=textwrap.fill(
            "Render a synthetic student sequence from a reference BVH: time warp, articulation "
            "offsets, path, body size, cameras, silhouettes, part labels, edges, intensity "
            "frames and 2-D joints, saved as DIR/sequence.npz + DIR/sequence.json (and "
            "DIR/camN.avi with videos=true).",
            88,
        ),
        epilog=_synth_epilog(),
    )
    add_debug(p_synth, top=False)
    p_synth.add_argument("--reference", type=Path, required=True, help="reference BVH file")
    p_synth.add_argument(
        "--student", type=Path, default=None, help="another performer's BVH (then no true C)"
    )
    p_synth.add_argument("--out", type=Path, required=True, help="output folder")
    p_synth.add_argument(
        "overrides", nargs="*", default=[], help="key=value settings (listed below)"
    )
    add_register_parser(sub)
    add_demo_parser(sub)
    return parser


def _command(args: argparse.Namespace) -> int:
    if args.command == "register":
        return register_command(args)
    if args.command == "demo":
        return demo_command(args)
    if args.command == "info":
        print(info(args.file, args.spec))
        return 0
    cfg = parse_overrides(args.overrides)
    seq = synthesize(args.reference, cfg, args.student)
    out = save_sequence(seq, args.out)
    files = sequence_files(seq.meta, out)
    print(
        f"wrote {seq.meta['num_video_frames']} frames from {len(seq.meta['cameras'])} "
        f"camera(s): {', '.join(str(f) for f in files)}"
    )
    if cfg.videos:  # the files save_sequence wrote: its videos and their calibration
        videos = " ".join(f"--video {f}" for f in files if f.suffix == ".avi")
        print(
            f"register it: python -m motion register --reference {args.reference} {videos} "
            f"--calibration {out / CALIBRATION_FILE} --out {out / 'registration'} "
            "(the pictures of the empty scene beside the videos are found by their names)"
        )
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run the command line (``argv`` without the program name); returns the exit status.
    The console script ``motionreg`` (pyproject's ``[project.scripts]``) calls it."""
    return run(_parser(_prog()), argv, _command)


if __name__ == "__main__":
    sys.exit(main())
