"""Command line: ``python -m motion info FILE.bvh [--spec SPEC]``.

Exits non-zero with a one-line reason on bad input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from motion.bodyparts import BodyModel, BodyPartMappingError
from motion.bvh import BVHError, read_bvh
from motion.kinematics import Skeleton, SkeletonError


def info(path: Path, spec: str | None) -> str:
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
        model = BodyModel.from_skeleton(skel, spec)
        lines.append(f"body parts: all {model.num_parts} mapped")
        for role in model.roles:
            lines.append(f"  {role}: {' + '.join(model.mapping[role])}")
    except BodyPartMappingError as err:
        lines.append(f"body parts: NOT all mapped: {err}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m motion", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p_info = sub.add_parser("info", help="describe a BVH file: skeleton, rate, units, body parts")
    p_info.add_argument("file", type=Path)
    p_info.add_argument("--spec", default=None, help="body-part spec file or bundled name")
    args = parser.parse_args(argv)
    try:
        if args.command == "info":
            print(info(args.file, args.spec))
    except (OSError, BVHError, SkeletonError, BodyPartMappingError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
