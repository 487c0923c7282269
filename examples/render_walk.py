"""Render the bundled CMU walk as body parts with its skeleton (the README's picture).

Run: ``python examples/render_walk.py [OUT.png]`` (default ``runs/walk_parts.png``), or
``python examples/render_walk.py --docs`` to refresh the tracked ``docs/walk_parts.png``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from motion.bodyparts import BodyModel
from motion.bvh import read_bvh
from motion.cameras import CameraRig
from motion.draw import contact_sheet, draw_parts, draw_skeleton
from motion.kinematics import Skeleton, forward_kinematics, local_rotations
from motion.render import ProjectedParts, project_parts

ROOT = Path(__file__).resolve().parents[1]
BVH = ROOT / "motion" / "data" / "cmu_02_01_walk.bvh"
DEFAULT_OUT = Path("runs/walk_parts.png")
DOCS_OUT = ROOT / "docs" / "walk_parts.png"


def main(out: Path) -> Path:
    bvh = read_bvh(BVH)
    skel = Skeleton.from_bvh(bvh)
    frames = np.linspace(1, bvh.num_frames - 1, 8).round().astype(int)
    fk = forward_kinematics(
        skel, *local_rotations(skel, torch.from_numpy(bvh.motion[frames]), bvh.channels)
    )
    model = BodyModel.from_skeleton(skel)
    # a camera that follows the walker: remove the root's horizontal travel (world Y is up)
    travel = fk.positions[:, :1].clone()
    travel[..., 1] = 0
    fk.positions = fk.positions - travel
    seg = model.segments(model.skeleton_points(skel, fk))  # (F, P, 2, 3)
    # a perspective camera 4.5 m to the side, looking at the body's centre
    centre = fk.positions.reshape(-1, 3).mean(0)
    size = 240
    rot = torch.tensor([[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)
    t = -(rot @ centre) + torch.tensor([0.0, 0.0, 4.5], dtype=torch.float64)
    k = torch.tensor([[[420.0, 0, size / 2], [0, 420.0, size / 2], [0, 0, 1]]], dtype=torch.float64)
    rig = CameraRig(
        k,
        rot[None],
        t[None],
        torch.zeros(1, 5, dtype=torch.float64),
        torch.tensor([[size, size]], dtype=torch.float64),
        ["side"],
    )
    parts = project_parts(rig, seg, model.radii)
    joints, _ = rig.project(fk.positions)
    tiles = []
    for i in range(len(frames)):
        img = np.full((size, size, 3), 245, dtype=np.uint8)
        one = ProjectedParts(parts.ends[i, 0], parts.radii[i, 0], parts.depth[i, 0])
        img = draw_parts(img, one, alpha=0.85)
        img = draw_skeleton(
            img, joints[i, 0].numpy(), skel.parents.tolist(), colour=(40, 40, 40), thickness=1
        )
        tiles.append(img)
    sheet = contact_sheet(tiles, columns=4, captions=[f"frame {f}" for f in frames])
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return out


def _out_path(argv: list[str] | None = None) -> Path:
    """The output path from the command line: OUT.png, --docs, or the default."""
    parser = argparse.ArgumentParser(description="Render the bundled CMU walk as body parts.")
    parser.add_argument(
        "out", nargs="?", type=Path, default=DEFAULT_OUT, help=f"PNG to write ({DEFAULT_OUT})"
    )
    parser.add_argument(
        "--docs", action="store_true", help=f"write the tracked {DOCS_OUT.relative_to(ROOT)}"
    )
    args = parser.parse_args(argv)
    if args.docs and args.out != DEFAULT_OUT:
        parser.error("give either OUT.png or --docs, not both")
    return DOCS_OUT if args.docs else args.out


if __name__ == "__main__":
    print(f"wrote {main(_out_path())}")
