"""Observation-factor throughput: occlusion-aware part-hypotheses scored per second.

Scores 15 parts x K hypotheses of the bundled walk at 160 x 120 (the synthetic default; a body
~75 px tall) with ``BodyObservation(cues=[Silhouette(), Edges()])`` -- the rest of the body
rendered once per call as two depth layers, every hypothesis' sample points projected and
gathered -- beside two anchors measured in the same run:

* torch, whole body per hypothesis: the body re-rendered exactly with that hypothesis in
  place (``motion.render.label_map``), silhouette both ways and chamfer counted over pixels
  (what a straightforward occlusion-aware implementation does);
* OpenCV's C rasteriser in a Python loop: each hypothesis drawn as a thick ``cv2.line``
  capsule into a crop, silhouette overlap counted with NumPy and the chamfer read from a
  ``cv2.distanceTransform`` at its contour -- the fast thing a practitioner would write,
  without occlusion.

Usage: python benchmarks/bench_observation.py [--frames 8] [--particles 150] [--repeats 3]
       [--device cpu|cuda] [--quick] [--json PATH]

``--quick``: 4 frames, one round. ``--json PATH``: also write the figures as rows for
``benchmarks/report.py`` (docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
import torch
from report import parse_args, write_rows  # benchmarks/report.py, beside this script

from motion.body.observation import (
    BodyObservation,
    Edges,
    Observation,
    PartShapes,
    Silhouette,
    poses_from_segments,
)
from motion.bodyparts import BodyModel
from motion.bundled import WALK_02_01 as WALK
from motion.bvh import read_bvh
from motion.cameras import CameraRig
from motion.kinematics import Skeleton, forward_kinematics, local_rotations
from motion.render import label_map, project_parts, silhouette
from motion.runtime import retain_freed_memory
from pgm import SE3

H, W = 120, 160
#: ``--quick``: fewer frames, one round
QUICK = {"frames": 4, "repeats": 1}


def walk(frames: list[int]) -> tuple[torch.Tensor, BodyModel]:
    bvh = read_bvh(WALK)
    skeleton = Skeleton.from_bvh(bvh)
    model = BodyModel.from_skeleton(skeleton)
    motion = torch.from_numpy(bvh.motion_frames()[frames]).double()
    rot, root = local_rotations(skeleton, motion, bvh.channels)
    seg = model.segments(model.skeleton_points(skeleton, forward_kinematics(skeleton, rot, root)))
    centre = seg.reshape(len(frames), -1, 3).mean(1)
    return (seg - centre[:, None, None]).float(), model


def camera() -> CameraRig:
    k = torch.tensor([[[57.0, 0, W / 2], [0, 57.0, H / 2], [0, 0, 1]]])
    r = torch.diag(torch.tensor([1.0, -1.0, -1.0]))[None]
    size = torch.tensor([[W, H]], dtype=torch.float32)
    return CameraRig(k, r, torch.tensor([[0, 0, 5.0]]), torch.zeros(1, 5), size, ["c"], True)


def observed(seg: torch.Tensor, model: BodyModel, rig: CameraRig):
    """Silhouette and edge distance of each frame: (T, H, W) each."""
    sil = torch.stack([silhouette(project_parts(rig, s, model.radii), H, W)[0] for s in seg])
    dist = []
    for s in sil.numpy():
        edges = cv2.Canny(s.astype(np.uint8) * 255, 50, 150) > 0
        dist.append(cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, 5))
    return sil.float(), torch.from_numpy(np.stack(dist))


def ours(factor, x, nodes, estimates, sync) -> float:
    sync()
    t0 = time.perf_counter()
    factor.log_potential(x, nodes, estimates)
    sync()
    return time.perf_counter() - t0


def torch_whole_body(seg, model, rig, hyp_seg, sil, dist, count: int) -> float:
    """Seconds per hypothesis: re-render the body with each hypothesis of part j in place."""
    grid_sil = sil[0].reshape(-1)
    t0 = time.perf_counter()
    for i in range(count):
        j = i % 15
        body = seg[0].clone()
        body[j] = hyp_seg[0, j, i % hyp_seg.shape[2]]
        labels, _ = label_map(project_parts(rig, body, model.radii), H, W)
        mine = (labels[0] == j).reshape(-1)
        others = ((labels[0] >= 0) & (labels[0] != j)).reshape(-1)
        spill = (mine & (grid_sil == 0)).sum()
        explained = (mine & (grid_sil > 0) & ~others).sum()
        edge = labels[0] == j  # its visible outline: own pixels next to other labels
        inner = (
            edge[1:-1, 1:-1] & edge[:-2, 1:-1] & edge[2:, 1:-1] & edge[1:-1, :-2] & edge[1:-1, 2:]
        )
        border = edge[1:-1, 1:-1] & ~inner
        chamfer = dist[0, 1:-1, 1:-1][border].clamp(max=8).square().sum()
        float(spill - explained + chamfer)
    return (time.perf_counter() - t0) / count


def opencv_loop(projected, sil, dist, count: int) -> float:
    """Seconds per hypothesis: each capsule drawn with cv2.line (thick, round caps) in a
    48 px crop, overlap with the silhouette by NumPy, chamfer at the drawn contour."""
    ends = np.rint(projected.ends[:, 0].numpy()).astype(int)  # (P, K, 2, 2) pixels
    radii = projected.radii[:, 0].numpy()  # (P, K, 2)
    s = sil[0].numpy().astype(np.uint8)
    d = dist[0].numpy()
    crop = 48
    mask = np.zeros((crop, crop), np.uint8)
    t0 = time.perf_counter()
    for i in range(count):
        j, k = i % ends.shape[0], i % ends.shape[1]
        a, b = ends[j, k]
        ox, oy = (a + b) // 2 - crop // 2
        mask[:] = 0
        thick = max(1, int(np.rint(radii[j, k].mean() * 2)))
        cv2.line(mask, (int(a[0] - ox), int(a[1] - oy)), (int(b[0] - ox), int(b[1] - oy)), 1, thick)
        y0, x0 = max(oy, 0), max(ox, 0)
        y1, x1 = min(oy + crop, H), min(ox + crop, W)
        if y1 <= y0 or x1 <= x0:
            continue
        m = mask[y0 - oy : y1 - oy, x0 - ox : x1 - ox]
        window = s[y0:y1, x0:x1]
        spill = int((m & (1 - window)).sum())
        explained = int((m & window).sum())
        contour = m - cv2.erode(m, None)
        chamfer = float(np.minimum(d[y0:y1, x0:x1][contour > 0], 8).__pow__(2).sum())
        _ = spill - explained + chamfer
    return (time.perf_counter() - t0) / count


def main(argv: list[str] | None = None) -> list[dict]:
    """Runs the benchmark and prints its table; returns its figures as rows (see
    ``benchmarks/report.py``), also written to ``--json`` when given."""
    retain_freed_memory()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--particles", type=int, default=150)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    args = parse_args(parser, QUICK, argv)
    device = args.device
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    frames = list(range(30, 30 + 10 * args.frames, 10))
    seg, model = walk(frames)
    rig = camera()
    sil, dist = observed(seg, model, rig)
    shapes = PartShapes.from_segments(seg[0], model.radii)  # float32, as the segments
    poses = poses_from_segments(seg)  # (T, P, 7)
    t, p, k = len(frames), 15, args.particles
    g = torch.Generator().manual_seed(0)
    x = SE3().perturb(poses.reshape(1, t * p, 1, 7).expand(1, t * p, k, 7), (0.03, 0.3), g)
    obs = Observation(sil[None, :, None], edge_distance=dist[None, :, None])
    factor = BodyObservation(
        PartShapes(shapes.axis.to(device), shapes.radii.to(device)),
        rig.to(device),
        Observation(obs.silhouette.to(device), edge_distance=obs.edge_distance.to(device)),
        cues=[Silhouette(), Edges()],
    )
    xd = x.to(device)
    nodes = torch.arange(t * p, device=device)
    estimates = poses.reshape(1, t * p, 7).to(device)
    ours(factor, xd, nodes, estimates, sync)  # warm-up
    hyp_seg = shapes.segments(x[0].reshape(t, p, k, 7), torch.arange(p), trailing=1)
    projected = project_parts(rig, hyp_seg[0], model.radii[:, None].expand(p, k, 2).float())
    mine, whole, cv = [], [], []
    for _ in range(args.repeats):
        mine.append(ours(factor, xd, nodes, estimates, sync) / (t * p * k))
        whole.append(torch_whole_body(seg, model, rig, hyp_seg, sil, dist, 60))
        cv.append(opencv_loop(projected, sil, dist, 3000))
    best = {"ours": min(mine), "whole": min(whole), "cv": min(cv)}
    where = torch.cuda.get_device_name() if device.startswith("cuda") else device
    print(
        f"{p} parts x {k} hypotheses x {t} frames at {W} x {H}, one camera (torch "
        f"{torch.__version__}, {torch.get_num_threads()} CPU threads, ours on {where})"
    )
    print("| method | part-hypotheses / s | us each | vs OpenCV loop |")
    print("|---|---|---|---|")
    rows = (
        (
            "BodyObservation: occlusion-aware, sampled points (silhouette both ways + chamfer)",
            "ours",
        ),
        ("torch, whole body re-rendered per hypothesis (exact, occlusion-aware)", "whole"),
        ("OpenCV cv2.line capsule per hypothesis + NumPy (no occlusion)", "cv"),
    )
    for label, key in rows:
        sec = best[key]
        print(f"| {label} | {1 / sec:,.0f} | {sec * 1e6:.1f} | {best['cv'] / sec:.2f}x |")
    print("target: >= 25,000 per second on 2 cores and faster than the OpenCV loop")
    results = [
        dict(
            case=f"{p} parts x {k} hypotheses x {t} frames at {W} x {H}, on {where}",
            ours=label,
            value=1 / best[key],
            anchor=rows[-1][0],
            anchor_value=1 / best["cv"],
            units="part-hypotheses / s",
            better="higher",
        )
        for label, key in rows[:-1]
    ]
    return write_rows(args.json, results)


if __name__ == "__main__":
    main()
