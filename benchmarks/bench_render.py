"""Rendering throughput: 15 parts x 1,000 hypotheses each at 128 x 128.

Prints the time to render, for each of the 15 body parts, 1,000 hypotheses of that part
composited against the rest of the body drawn once (`render_part_hypotheses`), beside
re-rendering the whole body for every hypothesis (`label_map` on 15 parts), same run.

Usage: python benchmarks/bench_render.py [--hypotheses 1000] [--full-sample 100] [--quick]
       [--json PATH]

``--quick``: 10 hypotheses per part rendered the slow way (instead of 100). ``--json PATH``:
also write the figures as rows for ``benchmarks/report.py`` (docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import time

import torch
from report import parse_args, write_rows  # benchmarks/report.py, beside this script

from motion.bodyparts import BodyModel
from motion.bundled import WALK_02_01
from motion.bvh import read_bvh
from motion.cameras import CameraRig
from motion.kinematics import Skeleton, forward_kinematics, local_rotations
from motion.render import ProjectedParts, label_map, project_parts, render_part_hypotheses
from motion.runtime import retain_freed_memory

#: ``--quick``: fewer hypotheses
QUICK = {"full_sample": 10}


def body_segments():
    bvh = read_bvh(WALK_02_01)
    skel = Skeleton.from_bvh(bvh)
    fk = forward_kinematics(
        skel, *local_rotations(skel, torch.from_numpy(bvh.motion[40]), bvh.channels)
    )
    model = BodyModel.from_skeleton(skel)
    seg = model.segments(model.skeleton_points(skel, fk)).float()
    seg = seg - seg.reshape(-1, 3).mean(0)
    return seg, model.radii.float()


def main(argv: list[str] | None = None) -> list[dict]:
    """Runs the benchmark and prints its table; returns its figures as rows (see
    ``benchmarks/report.py``), also written to ``--json`` when given."""
    retain_freed_memory()  # process-wide allocator setting (motion/runtime.py)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hypotheses", type=int, default=1000)
    parser.add_argument(
        "--full-sample", type=int, default=100, help="hypotheses rendered the slow way"
    )
    args = parse_args(parser, QUICK, argv)
    size = 128
    seg, radii = body_segments()
    height = float(seg[..., 1].max() - seg[..., 1].min())
    k = torch.tensor([[[100 / height, 0, size / 2], [0, -100 / height, size / 2], [0, 0, 1]]])
    rig = CameraRig(
        k,
        torch.eye(3)[None],
        torch.tensor([[0.0, 0.0, 5.0]]),
        torch.zeros(1, 5),
        torch.tensor([[size, size]]),
        ["ortho"],
        orthographic=True,
    )
    g = torch.Generator().manual_seed(0)
    p = seg.shape[0]
    n = args.hypotheses
    hyp = seg.unsqueeze(0) + 0.03 * torch.randn(n, p, 2, 3, generator=g)  # (N, P, 2, 3)
    proj = project_parts(rig, hyp, radii)  # (N, 1, P, 2, *)
    base = project_parts(rig, seg, radii)

    t0 = time.perf_counter()
    crops = []
    for part in range(p):
        keep = [i for i in range(p) if i != part]
        rest = ProjectedParts(base.ends[0, keep], base.radii[0, keep], base.depth[0, keep])
        _, rest_depth = label_map(rest, size, size)
        one = ProjectedParts(proj.ends[:, 0, part], proj.radii[:, 0, part], proj.depth[:, 0, part])
        # window: the largest extent any hypothesis of this part has, plus a margin
        extent = (one.ends[:, 1] - one.ends[:, 0]).norm(dim=-1) + 2 * one.radii.amax(-1)
        crop = int(extent.max().ceil()) + 4
        crops.append(crop)
        render_part_hypotheses(one, rest_depth, crop)
    ours = time.perf_counter() - t0

    m = args.full_sample
    t0 = time.perf_counter()
    for _part in range(p):  # each part's hypotheses, re-rendering the whole body
        full = ProjectedParts(proj.ends[:m, 0], proj.radii[:m, 0], proj.depth[:m, 0])
        label_map(full, size, size)
    naive = (time.perf_counter() - t0) * n / m
    print(
        f"15 parts x {n} hypotheses at {size} x {size} (torch {torch.__version__}, {torch.get_num_threads()} threads)"
    )
    print("| method | seconds | per part-hypothesis |")
    print("|---|---|---|")
    print(
        f"| crop ({min(crops)}-{max(crops)} px) + composite against the rest drawn once | {ours:.2f} | "
        f"{ours / (p * n) * 1e6:.0f} us |"
    )
    print(
        f"| whole body per hypothesis (measured on {m}, scaled) | {naive:.2f} | {naive / (p * n) * 1e6:.0f} us |"
    )
    print(f"speed-up {naive / ours:.1f}x")
    results = [
        dict(
            case=f"15 parts x {n} hypotheses at {size} x {size}",
            ours=f"crop ({min(crops)}-{max(crops)} px) + composite against the rest drawn once",
            value=ours / (p * n) * 1e6,
            anchor=f"whole body per hypothesis (measured on {m}, scaled)",
            anchor_value=naive / (p * n) * 1e6,
            units="us per part-hypothesis",
            better="lower",
        )
    ]
    return write_rows(args.json, results)


if __name__ == "__main__":
    main()
