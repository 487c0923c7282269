"""Command line.

``python -m motion info FILE.bvh [--spec SPEC]``: describe a BVH file.
``python -m motion synth --reference REF.bvh [--student OTHER.bvh] [key=value ...] --out DIR``:
write a synthetic sequence; keys are :class:`motion.synth.SynthConfig` fields, e.g.
``fps=30 cameras=2 noise_px=2 replace=0.4,0.5 articulation=LeftLeg:20,RightArm:30
size=320x240 videos=true seed=1``.

Exits non-zero with a one-line reason on bad input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from motion.bodyparts import BodyModel, BodyPartMappingError
from motion.bvh import BVHError, read_bvh
from motion.kinematics import Skeleton, SkeletonError
from motion.synth import SynthConfig, save_sequence, synthesize


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


def parse_overrides(items: list[str]) -> SynthConfig:
    """``key=value`` strings -> :class:`SynthConfig` (unknown keys and bad values fail)."""
    cfg = SynthConfig()
    fields = SynthConfig.__dataclass_fields__
    for item in items:
        if "=" not in item:
            raise ValueError(f"expected key=value, got {item!r}")
        key, value = item.split("=", 1)
        if key not in fields:
            raise ValueError(f"unknown setting {key!r}; known: {', '.join(fields)}")
        current = getattr(cfg, key)
        if key == "articulation":
            parsed = {k: float(v) for k, v in (p.split(":") for p in value.split(",") if p)}
        elif key == "size":
            parsed = [int(v) for v in value.lower().split("x")]
        elif key in ("path_m", "replace"):
            parsed = None if value.lower() == "none" else [float(v) for v in value.split(",")]
        elif isinstance(current, bool):
            if value.lower() not in ("true", "false", "1", "0"):
                raise ValueError(f"{key} must be true or false; got {value!r}")
            parsed = value.lower() in ("true", "1")
        elif key == "camera_distance_m":
            parsed = None if value.lower() == "none" else float(value)
        else:
            parsed = type(current)(value)
        setattr(cfg, key, parsed)
    cfg.validate()
    return cfg


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m motion", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p_info = sub.add_parser("info", help="describe a BVH file: skeleton, rate, units, body parts")
    p_info.add_argument("file", type=Path)
    p_info.add_argument("--spec", default=None, help="body-part spec file or bundled name")
    p_synth = sub.add_parser("synth", help="render a synthetic student sequence with ground truth")
    p_synth.add_argument("--reference", type=Path, required=True)
    p_synth.add_argument("--student", type=Path, default=None)
    p_synth.add_argument("--out", type=Path, required=True)
    p_synth.add_argument("overrides", nargs="*", help="key=value settings (SynthConfig fields)")
    args = parser.parse_args(argv)
    try:
        if args.command == "info":
            print(info(args.file, args.spec))
        elif args.command == "synth":
            cfg = parse_overrides(args.overrides)
            seq = synthesize(args.reference, cfg, args.student)
            out = save_sequence(seq, args.out)
            print(
                f"wrote {out / 'sequence.npz'} ({seq.meta['num_video_frames']} frames, "
                f"{len(seq.meta['cameras'])} cameras) and {out / 'sequence.json'}"
            )
    except (OSError, ValueError, KeyError, BVHError, SkeletonError, BodyPartMappingError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
