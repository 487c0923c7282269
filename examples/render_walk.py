"""Render the bundled CMU walk as body parts with its skeleton: docs/walk_parts.png.

Run: ``python examples/render_walk.py [OUT.png]``.
"""

from __future__ import annotations

import sys
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

BVH = Path(__file__).resolve().parents[1] / "motion" / "data" / "cmu_02_01_walk.bvh"


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


if __name__ == "__main__":
    print(main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs/walk_parts.png")))
