"""Observation factors: point-sampled scores against exact rasterisation, cue by cue.

The independent answer is the pixel grid: every capsule rasterised exactly with
``motion.render.capsule_sdf`` at every pixel, the rest of the body by ``label_map`` without
the part, and counts taken over pixels. The factor never rasterises; its sample points must
reproduce those counts.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from motion.body.observation import (
    BodyObservation,
    Edges,
    Intensity,
    Joints2D,
    NonPenetration,
    Observation,
    PartShapes,
    SampleLayout,
    Silhouette,
    body_layers,
    poses_from_segments,
    segment_distance,
)
from motion.render import (
    ProjectedParts,
    _grid,
    capsule_sdf,
    label_map,
    outline_points,
    project_parts,
    silhouette,
)
from pgm import SE3, AnnealingStep, Geometric
from tests.motion.body.conftest import F64, every_cue_scene, side_camera, walk_segments

H, W = 120, 160
K = 20


@pytest.fixture(scope="module")
def scene():
    """The walk at frame 30 as truth, its silhouette, and 20 perturbed hypotheses per part."""
    seg, model = walk_segments([30])
    poses = poses_from_segments(seg)  # (1, P, 7)
    shapes = PartShapes.from_segments(seg[0], model.radii)
    rig = side_camera()
    sil = silhouette(project_parts(rig, seg[0], model.radii), H, W)[0].to(F64)
    g = torch.Generator().manual_seed(0)
    x = SE3().perturb(poses[:, :, None].expand(1, 15, K, 7), (0.03, 0.3), g)
    return seg[0], poses, shapes, rig, sil, x, model


def _exact(scene, j, rest_parts=None):
    """Exact per-pixel coverage of part j's hypotheses: cover (K, H*W), own (in front of the
    rest without j), and whether the rest covers each pixel."""
    seg, _, shapes, rig, _, x, model = scene
    others = [i for i in range(15) if i != j] if rest_parts is None else rest_parts
    if others:
        _, rest_depth = label_map(project_parts(rig, seg[others], model.radii[others]), H, W)
        rest_depth = rest_depth[0].reshape(-1)
    else:
        rest_depth = torch.full((H * W,), math.inf, dtype=F64)
    hyp = project_parts(
        rig, shapes.segments(x[0, j], torch.full((K,), j)), model.radii[j].expand(K, 2)
    )
    sdf, t = capsule_sdf(_grid(H, W, seg), hyp.ends[0], hyp.radii[0])
    z = hyp.depth[0, :, :1] + t * (hyp.depth[0, :, 1:] - hyp.depth[0, :, :1])
    cover = sdf <= 0
    return cover, cover & (z < rest_depth), torch.isfinite(rest_depth)


def _factor(scene, cues, **kw):
    _, _, shapes, rig, sil, _, _ = scene
    obs = kw.pop("obs", None) or Observation(sil[None, None, None])
    return BodyObservation(shapes, rig, obs, cues=cues, **kw)


def test_sampled_silhouette_terms_equal_pixel_counts(scene):
    """Both silhouette directions per hypothesis against exact pixel counts: the mean error
    is ~2 % of the part's area (measured 2.0 %); single hypotheses stay within 15 % of their
    area plus 4 px (a 13 px^2 hand is 2-3 pixels wide: its count moves by whole pixels)."""
    _, poses, _, _, sil, x, _ = scene
    f = _factor(scene, [Silhouette()])
    samples = f.samples(x, torch.arange(15), poses)
    inner = samples.interior
    s = inner.gather(f.obs.silhouette)
    spill = (inner.weight * inner.own * (1 - s)).sum(-1)[0, :, 0]  # (P, K)
    explained = (inner.weight * inner.inside * s * ~inner.rest_covered).sum(-1)[0, :, 0]
    errs, areas = [], []
    for j in range(15):
        cover, own, rest = _exact(scene, j)
        flat = sil.reshape(-1)
        exact_spill = (own * (1 - flat)).sum(-1)
        exact_explained = (cover * flat * ~rest).sum(-1)
        area = cover.sum(-1).to(F64)
        for got, want in ((spill[j], exact_spill), (explained[j], exact_explained)):
            err = (got - want).abs()
            assert (err <= 0.15 * area + 4).all(), (j, err, area)
            errs.append(err)
            areas.append(area)
    assert torch.cat(errs).sum() / torch.cat(areas).sum() < 0.04


def test_silhouette_score_ranks_hypotheses_like_the_pixels(scene):
    _, poses, _, _, sil, x, _ = scene
    f = _factor(scene, [Silhouette(outside=1.0, uncovered=1.0)])
    score = f.log_potential(x, torch.arange(15), poses)[0]  # (P, K)
    exact = torch.stack(
        [
            (
                lambda c, o, r: (
                    (c * sil.reshape(-1) * ~r).sum(-1) - (o * (1 - sil.reshape(-1))).sum(-1)
                )
            )(*_exact(scene, j))
            for j in range(15)
        ]
    ).to(F64)
    r = torch.corrcoef(torch.stack([score.flatten(), exact.flatten()]))[0, 1]
    assert r > 0.97, r


def test_a_part_hidden_behind_the_body_neither_gains_nor_loses(scene):
    """A forearm moved 30 cm behind the torso (along the camera's depth), where the torso
    covers it: it owns no pixel, explains none, and its silhouette score is 0."""
    seg, poses, _, _, _, _, model = scene
    f = _factor(scene, [Silhouette()])
    torso = model.part_names.index("torso")
    forearm = model.part_names.index("forearm_l")
    hidden = poses[:, forearm].clone()
    centre = seg[torso].mean(0)
    hidden[:, :3] = centre - torch.tensor([0.0, 0.05, 0.3], dtype=F64)  # behind: -z is away
    hidden[:, 3:] = torch.tensor([0.7071, 0.7071, 0.0, 0.0], dtype=F64)  # pointing down (-y)
    x = hidden[:, None, None].expand(1, 1, 1, 7)
    inner = f.samples(x, torch.tensor([forearm]), poses).interior
    assert inner.inside.all() and not inner.own.any() and inner.rest_covered.all()
    assert f.log_potential(x, torch.tensor([forearm]), poses).abs().max() == 0
    unaware = _factor(scene, [Silhouette()], occlusion=False)
    assert unaware.samples(x, torch.tensor([forearm]), poses).interior.own.all()


@pytest.mark.parametrize("shift", [0.0, 1.3], ids=["inside", "leaving-the-image"])
def test_body_layers_equal_label_maps(scene, shift):
    """The two-layer render: the nearest surface is label_map's; the rest without part j
    (second layer where j is nearest) is label_map without j -- also for a body half out of
    the image (its box clamped to the image)."""
    seg, _, _, rig, _, _, model = scene
    seg = seg + torch.tensor([shift, 0.0, 0.0], dtype=F64)
    parts = project_parts(rig, seg[None, None], model.radii)  # (1, 1, C, P, ...)
    layers = body_layers(parts, H, W, rows=7)  # bands that do not divide H
    labels, depth = label_map(project_parts(rig, seg, model.radii), H, W)
    torch.testing.assert_close(layers.near[0, 0], depth)
    strict = layers.near[0, 0] < layers.second[0, 0]  # where two parts tie, either may win
    assert torch.equal(layers.label[0, 0][strict], labels[strict])
    assert (~strict & torch.isfinite(depth)).sum() < 5
    for j in (1, 4, 10):
        others = [i for i in range(15) if i != j]
        rest_labels, rest = label_map(project_parts(rig, seg[others], model.radii[others]), H, W)
        mine = layers.label[0, 0, 0] == j
        without = torch.where(mine, layers.second[0, 0, 0], layers.near[0, 0, 0])
        torch.testing.assert_close(without, rest[0])
        # the front part of the rest: the second layer's label where j is nearest
        front = torch.where(mine, layers.second_label[0, 0, 0], layers.label[0, 0, 0])
        want = torch.where(rest_labels[0] >= 0, torch.tensor(others)[rest_labels[0]], -1)
        # where two surfaces tie in depth either may come first: a few pixels
        assert (front != want).sum() < 5, (front != want).sum()


def test_body_layers_break_depth_ties_by_part_index_not_by_rounding():
    """Two capsules meeting at a joint at one depth (the wedge around the joint has both at
    the joint's depth): whichever of them a rounding error makes nearer by 1e-12 m, the
    label there is the lower part index, and the depths kept are the true ones (the cause
    of CPU and CUDA disagreeing on the Intensity cue's covered colour); a real gap of
    1 mm still decides."""
    ends = torch.tensor([[[20.0, 30.0], [40.0, 30.0]], [[40.0, 30.0], [40.0, 50.0]]], dtype=F64)
    radii = torch.full((2, 2), 6.0, dtype=F64)
    for eps in (1e-12, -1e-12):
        depth = torch.tensor([[4.0, 5.0], [5.0 + eps, 6.0]], dtype=F64)
        layers = body_layers(
            ProjectedParts(ends[None, None, None], radii, depth[None, None, None]), 60, 60
        )
        wedge = (44, 26)  # u, v: beyond both segments' ends, inside both caps
        v, u = wedge[1], wedge[0]
        assert (
            int(layers.label[0, 0, 0, v, u]) == 0 and int(layers.second_label[0, 0, 0, v, u]) == 1
        )
        # each layer keeps its own part's true depth
        assert float(layers.near[0, 0, 0, v, u]) == 5.0
        assert float(layers.second[0, 0, 0, v, u]) == 5.0 + eps
    deeper = torch.tensor([[4.0, 5.0], [5.0 - 1e-3, 6.0]], dtype=F64)  # a real gap still wins
    layers = body_layers(
        ProjectedParts(ends[None, None, None], radii, deeper[None, None, None]), 60, 60
    )
    assert int(layers.label[0, 0, 0, 26, 44]) == 1


@pytest.mark.parametrize("draw", range(3))
def test_every_cue_scores_the_same_under_rounding_of_the_poses(draw):
    """The CUDA test's scene (``test_observation_cuda``) on the CPU, with every hypothesis and
    rest pose changed by a relative 1e-14 -- a few float64 ulps, as another device's
    arithmetic rounds them (its sine, cosine and square root are not the CPU's to the last
    bit): every score moves by under 1e-9. Where two parts meet at a joint their depths
    are equal up to that rounding; with the nearest chosen by rounding, as before
    ``DEPTH_TIE_BREAK``, the same change moved 11 of the 1,200 scores by up to 6.3 (the
    Intensity cue's covered colour), the CUDA disagreement an H200 showed (10 of 1,200)."""
    x, rest, score = every_cue_scene()
    base = score(x, rest)
    g = torch.Generator().manual_seed(draw)
    jitter = [1 + 1e-14 * torch.randn(t.shape, dtype=F64, generator=g) for t in (x, rest)]
    moved = score(x * jitter[0], rest * jitter[1])
    torch.testing.assert_close(moved, base, rtol=1e-9, atol=1e-9)


def test_a_hypothesis_the_camera_cannot_image_is_impossible_not_a_crash(scene):
    """NaN and infinite poses (what a diverged solver hands over) score -inf -- potential
    0, which particle BP accepts -- instead of being cast to pixel indices (an IndexError
    before); the finite hypotheses beside them score exactly as without them."""
    _, poses, _, _, _, x, _ = scene
    f = _factor(scene, [Silhouette()])
    clean = f.log_potential(x, torch.arange(15), poses)
    broken = x.clone()
    broken[0, 3, 1, 0] = float("nan")  # a position
    broken[0, 4, 2, 5] = float("inf")  # a quaternion entry
    got = f.log_potential(broken, torch.arange(15), poses)
    assert float(got[0, 3, 1]) == -math.inf and float(got[0, 4, 2]) == -math.inf
    keep = torch.ones_like(got, dtype=torch.bool)
    keep[0, 3, 1] = keep[0, 4, 2] = False
    torch.testing.assert_close(got[keep], clean[keep], rtol=0, atol=0)


def test_a_rest_part_the_camera_cannot_image_covers_nothing(scene):
    """A NaN estimate of one part in the rest of the body: every score equals the one with
    that part moved 1 km to the side, out of every image (covering nothing)."""
    _, poses, _, _, _, x, _ = scene
    f = _factor(scene, [Silhouette()])
    lost, away = poses.clone(), poses.clone()
    lost[0, 5, :3] = float("nan")
    away[0, 5, 0] += 1000.0
    nodes = torch.arange(15)
    torch.testing.assert_close(
        f.log_potential(x, nodes, lost), f.log_potential(x, nodes, away), rtol=0, atol=1e-12
    )


def test_edge_cue_equals_the_mean_edge_distance_along_the_outline(scene):
    """Occlusion off, one part at a time: the outline term equals the length-weighted mean
    of the truncated squared distance along the exact capsule outline (500 points of
    motion.render.outline_points, an independent parametrisation) within 5 %."""
    _, poses, shapes, rig, sil, x, model = scene
    edges = cv2.Canny((sil.numpy() * 255).astype(np.uint8), 50, 150) > 0
    dist = cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    dist_t = torch.from_numpy(dist).to(F64)
    obs = Observation(sil[None, None, None], edge_distance=dist_t[None, None, None])
    cue = Edges(weight=1.0, truncate=8.0)
    f = _factor(scene, [cue], obs=obs, occlusion=False, layout=SampleLayout(side=24, arc=12))
    samples = f.samples(x, torch.arange(15), poses)
    got = -cue.score(samples, obs)[0, :, 0] / samples.outline.weight.sum(-1)[0, :, 0]
    for j in (0, 3, 9, 12):
        hyp = project_parts(
            rig, shapes.segments(x[0, j], torch.full((K,), j)), model.radii[j].expand(K, 2)
        )
        pts, _ = outline_points(ProjectedOne(hyp), per_part=500)
        u = pts[..., 0].round().long().clamp(0, W - 1)
        v = pts[..., 1].round().long().clamp(0, H - 1)
        inside = (
            (pts[..., 0].round() >= 0)
            & (pts[..., 0].round() < W)
            & (pts[..., 1].round() >= 0)
            & (pts[..., 1].round() < H)
        )
        d = torch.where(inside, dist_t[v, u], torch.full_like(dist_t[v, u], 8.0)).clamp(max=8.0)
        want = (d / 8.0).square().mean(-1)
        torch.testing.assert_close(got[j], want, atol=0.02, rtol=0.05)


def ProjectedOne(parts):
    """The (K,) hypotheses of one camera as parts (outline_points takes one image)."""
    from motion.render import ProjectedParts

    return ProjectedParts(parts.ends[0], parts.radii[0], parts.depth[0])


@pytest.mark.parametrize("replaces_rest", [False, True])
def test_intensity_cue_equals_the_pixel_sum(scene, replaces_rest):
    """The true body's label map coloured per part on grey: the intensity score per
    hypothesis against the exact sum over the pixels it owns -- its own colour cost, less
    (``replaces_rest``) the cost of the rest's front part that it covers up there, i.e.
    the change of the whole body's colour likelihood when j is placed."""
    seg, poses, _, rig, sil, x, model = scene
    labels, _ = label_map(project_parts(rig, seg, model.radii), H, W)
    colours = torch.rand(15, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    table = torch.cat([torch.full((1, 3), 0.5, dtype=F64), colours])
    image = table[labels[0] + 1].permute(2, 0, 1)  # (3, H, W)
    obs = Observation(sil[None, None, None], image=image[None, None, None])
    cue = Intensity(colours, weight=1.0, sigma=1.0, replaces_rest=replaces_rest)
    f = _factor(scene, [cue], obs=obs)
    score = f.log_potential(x, torch.arange(15), poses)[0]  # (P, K)
    flat = image.reshape(3, -1)
    errs, costs = [], []
    for j in range(15):
        _, own, _ = _exact(scene, j)
        per_pixel = (flat.T[None] - colours[j]).square().sum(-1) / 2  # at most 1.5
        cost = (per_pixel * own).sum(-1)
        if replaces_rest:
            others = [i for i in range(15) if i != j]
            rest, _ = label_map(project_parts(rig, seg[others], model.radii[others]), H, W)
            front = rest[0].reshape(-1)  # index into others, -1: uncovered
            rest_colour = colours[torch.tensor(others)[front.clamp_min(0)]]
            rest_cost = (flat.T - rest_colour).square().sum(-1) / 2 * (front >= 0)
            cost = cost - (rest_cost[None] * own).sum(-1)
        area = own.sum(-1).to(F64)
        err = (-score[j] - cost).abs()
        # a misassigned pixel costs at most 1.5 (twice with the rest's term): the
        # silhouette test's pixel bound, x 1.5 or x 3
        bound = 3.0 if replaces_rest else 1.5
        assert (err <= bound * (0.15 * area + 4)).all(), (j, -score[j], cost)
        errs.append(err)
        costs.append((per_pixel * own).sum(-1))
    # the cost lives where colours change -- on boundaries, where the quadrature is least
    # exact: 9.6 % of the total measured (the silhouette's area terms: 2 %); with the
    # rest's term, relative to the own cost: 13.6 % measured
    assert torch.cat(errs).sum() / torch.cat(costs).sum() < (0.16 if replaces_rest else 0.12)


def test_joint_cue_is_a_cauchy_of_the_end_distances(scene):
    """Keypoints at the true projected part ends: the cue is exactly the Cauchy sum of the
    hypotheses' end distances, and a missing keypoint (confidence 0) or end (-1) counts 0."""
    seg, poses, shapes, rig, sil, x, model = scene
    truth = project_parts(rig, seg, model.radii).ends[0]  # (P, 2, 2)
    keypoints = torch.cat([truth.reshape(-1, 2), torch.ones(30, 1, dtype=F64)], -1)
    keypoints[3, 2] = 0.0  # part 1's distal end unseen
    part_kp = torch.arange(30).reshape(15, 2)
    part_kp[2, 1] = -1  # the head's top has no keypoint
    obs = Observation(sil[None, None, None], keypoints=keypoints[None, None, None])
    cue = Joints2D(part_kp, weight=1.0, sigma=4.0)
    score = _factor(scene, [cue], obs=obs).log_potential(x, torch.arange(15), poses)[0]
    hyp = project_parts(
        rig,
        shapes.segments(x[0], torch.arange(15), trailing=1),
        model.radii[:, None].expand(15, K, 2),
    )
    d2 = (hyp.ends[:, 0] - truth[:, None]).square().sum(-1)  # (P, K, 2)
    mask = torch.ones(15, 1, 2, dtype=F64)
    mask[1, :, 1] = 0
    mask[2, :, 1] = 0
    torch.testing.assert_close(score, -(mask * torch.log1p(d2 / 16.0)).sum(-1))


def test_segment_distance_against_dense_sampling():
    g = torch.Generator().manual_seed(2)
    p1, q1, p2, q2 = torch.randn(4, 200, 3, generator=g, dtype=F64).unbind(0)
    q2[:20] = p2[:20] + 1e-9  # degenerate segments (points)
    q1[20:40] = p1[20:40] + 0.5 * (q2[20:40] - p2[20:40])  # parallel ones
    p1[20:40] = p2[20:40] + 0.3
    q1[20:40] = p1[20:40] + (q2[20:40] - p2[20:40])
    got = segment_distance(p1, q1, p2, q2)
    s = torch.linspace(0, 1, 401, dtype=F64)
    a = p1[:, None] + s[None, :, None] * (q1 - p1)[:, None]
    b = p2[:, None] + s[None, :, None] * (q2 - p2)[:, None]
    brute = torch.cdist(a, b).amin((-1, -2))
    assert (got <= brute + 1e-9).all() and (brute - got < 5e-3).all()


def test_non_penetration_penalises_overlap_with_other_parts_only(scene):
    poses, model = scene[1], scene[6]
    allowed = torch.eye(15, dtype=torch.bool)
    thigh_l, thigh_r = model.part_names.index("thigh_l"), model.part_names.index("thigh_r")
    allowed[thigh_l, model.part_names.index("pelvis")] = True
    cue = NonPenetration(allowed, weight=1.0, depth=0.02)
    f = _factor(scene, [cue])
    into = poses[:, thigh_r].clone()  # the left thigh placed where the right one is
    apart = poses[:, thigh_l].clone()
    apart[:, 0] += 2.0  # two metres away from everything
    hyp = torch.stack([into, apart], 1)[:, None]  # (1, 1, 2, 7)
    score = f.log_potential(hyp, torch.tensor([thigh_l]), poses)[0, 0]
    radius = model.radii[thigh_l].mean() + model.radii[thigh_r].mean()
    assert score[1] == 0 and score[0] <= -((radius / 0.02) ** 2) * 0.99


def test_factor_contract_frames_batch_cameras_and_annealing():
    """T = 3 frames x 2 cameras, a batch of 2, a subset of nodes: shapes (B, N, K), cameras
    summed (two identical cameras give twice one), the schedule scales the score."""
    seg, model = walk_segments([30, 60, 90])
    poses = poses_from_segments(seg)  # (T, P, 7)
    shapes = PartShapes.from_segments(seg[0], model.radii)
    one = side_camera()
    two = type(one)(
        one.K.repeat(2, 1, 1),
        one.R.repeat(2, 1, 1),
        one.t.repeat(2, 1),
        one.dist.repeat(2, 1),
        one.size.repeat(2, 1),
        ["a", "b"],
        orthographic=True,
    )
    sil = torch.stack(
        [silhouette(project_parts(one, seg[t], model.radii), H, W)[0] for t in range(3)]
    ).to(F64)
    estimates = poses.reshape(1, 45, 7).expand(2, 45, 7)
    nodes = torch.tensor([1, 17, 44])  # parts 1, 2, 14 of frames 0, 1, 2
    g = torch.Generator().manual_seed(3)
    x = SE3().perturb(estimates[:, nodes, None].expand(2, 3, 5, 7), (0.02, 0.2), g)
    f1 = BodyObservation(shapes, one, Observation(sil[None, :, None]))
    f2 = BodyObservation(shapes, two, Observation(sil[None, :, None].expand(1, 3, 2, H, W)))
    a, b = f1.log_potential(x, nodes, estimates), f2.log_potential(x, nodes, estimates)
    assert a.shape == (2, 3, 5)
    torch.testing.assert_close(b, 2 * a)
    per_frame = BodyObservation(shapes, one, Observation(sil[None, 1:2, None]))
    alone = per_frame.log_potential(x[:, 1:2], torch.tensor([2]), estimates[:, 15:30])
    torch.testing.assert_close(alone, a[:, 1:2])
    annealed = BodyObservation(
        shapes, one, Observation(sil[None, :, None]), schedule=Geometric(0.2, 1.0, 3)
    )
    assert annealed.multiplier == 1.0
    first = annealed.annealed(AnnealingStep(iteration=0))
    torch.testing.assert_close(first.log_potential(x, nodes, estimates), 0.2 * a)
    assert annealed.annealed(AnnealingStep(iteration=2)).multiplier == 1.0
    with pytest.raises(ValueError, match="the observation has 3 frames of 15 parts"):
        f1.log_potential(x, nodes, estimates[:, :30])
    with pytest.raises(ValueError, match="the rig has 2 cameras but the observation 1"):
        BodyObservation(shapes, two, Observation(sil[None, :, None]))


def test_smooth_gathers_interpolate_bilinearly(scene):
    """On a map that is linear in (u, v) a bilinear read is exact at any sub-pixel point; a
    nearest read is off by up to half a pixel's slope."""
    poses, x = scene[1], scene[5]
    f = _factor(scene, [Silhouette(smooth=True)])
    inner = f.samples(x, torch.arange(15), poses).interior
    v, u = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    ramp = (0.3 * u - 0.7 * v + 2.0)[None, None, None]  # (1, 1, 1, H, W)
    u_pt, v_pt = inner.points[..., 0], inner.points[..., 1]
    exact = 0.3 * u_pt - 0.7 * v_pt + 2.0
    inside = inner.inside & (u_pt <= W - 1) & (v_pt <= H - 1) & (u_pt >= 0) & (v_pt >= 0)
    got = inner.gather(ramp, smooth=True)
    torch.testing.assert_close(got[inside], exact[inside])
    nearest = inner.gather(ramp)
    assert ((nearest - exact)[inside].abs() <= 0.5 * (0.3 + 0.7) + 1e-9).all()
