"""Rendering: exact orthographic areas, depth order, soft -> hard, gradients, hypotheses."""

import math

import pytest
import torch

from motion.cameras import CameraRig
from motion.render import (
    ProjectedParts,
    capsule_area,
    capsule_sdf,
    label_map,
    outline_points,
    project_parts,
    render_intensity,
    render_part_hypotheses,
    silhouette,
)

F64 = torch.float64


def _ortho(scale=100.0, size=200):
    k = torch.tensor([[[scale, 0, size / 2], [0, scale, size / 2], [0, 0, 1]]], dtype=F64)
    return CameraRig(
        k,
        torch.eye(3, dtype=F64)[None],
        torch.tensor([[0, 0, 5.0]], dtype=F64),
        torch.zeros(1, 5, dtype=F64),
        torch.tensor([[size, size]], dtype=F64),
        ["o"],
        orthographic=True,
    )


@pytest.mark.parametrize(
    ("r1", "r2", "length"), [(20.0, 20.0, 80.0), (25.0, 12.0, 90.0), (8.0, 18.0, 60.0)]
)
def test_orthographic_capsule_area_is_analytic(r1, r2, length):
    """A 3-D tapered capsule seen orthographically: pixel count vs the exact 2-D area,
    within 0.5 % (rasterisation error of a ~6,000-12,000 px shape)."""
    rig = _ortho(scale=1.0, size=300)  # 1 px per metre unit
    seg = torch.tensor([[[-length / 2, 10.0, 0.0], [length / 2, -5.0, 0.3]]], dtype=F64)
    seg[0, 1, :2] = seg[0, 0, :2] + length * torch.nn.functional.normalize(
        seg[0, 1, :2] - seg[0, 0, :2], dim=0
    )
    parts = project_parts(rig, seg, torch.tensor([[r1, r2]], dtype=F64))
    area = silhouette(parts, 300, 300)[0].sum().item()
    assert area == pytest.approx(capsule_area(r1, r2, length), rel=0.005)


def test_sdf_is_exact_distance_for_round_capsules():
    ends = torch.tensor([[0.0, 0.0], [10.0, 0.0]], dtype=F64)
    radii = torch.tensor([2.0, 2.0], dtype=F64)
    pts = torch.tensor([[5.0, 5.0], [-3.0, 0.0], [13.0, 4.0], [5.0, 0.0]], dtype=F64)
    sdf, t = capsule_sdf(pts, ends, radii)
    torch.testing.assert_close(sdf, torch.tensor([3.0, 1.0, 3.0, -2.0], dtype=F64))
    torch.testing.assert_close(t, torch.tensor([0.5, 0.0, 1.0, 0.5], dtype=F64))


def test_depth_order_when_one_part_passes_behind_another():
    rig = _ortho(scale=100.0)
    # part 0 horizontal at depth z = +0.5 (farther), part 1 vertical at z = -0.5 (nearer)
    seg = torch.tensor(
        [[[-0.6, 0.0, 0.5], [0.6, 0.0, 0.5]], [[0.0, -0.6, -0.5], [0.0, 0.6, -0.5]]], dtype=F64
    )
    radii = torch.tensor([[0.1, 0.1], [0.1, 0.1]], dtype=F64)
    labels, depth = (
        label_map(project_parts(rig, seg, radii)[0], 200, 200)
        if False
        else label_map(_first(project_parts(rig, seg, radii)), 200, 200)
    )
    assert labels[100, 100] == 1  # the crossing shows the nearer part
    assert labels[100, 40] == 0 and labels[40, 100] == 1 and labels[5, 5] == -1
    assert math.isinf(depth[5, 5])
    # swap depths: now part 0 is in front at the crossing
    seg2 = seg.clone()
    seg2[0, :, 2], seg2[1, :, 2] = -0.5, 0.5
    labels2, _ = label_map(_first(project_parts(rig, seg2, radii)), 200, 200)
    assert labels2[100, 100] == 0


def _first(parts):
    return ProjectedParts(parts.ends[0], parts.radii[0], parts.depth[0])


def test_soft_silhouette_tends_to_hard_and_has_gradients():
    rig = _ortho(scale=100.0, size=64)
    seg = torch.tensor([[[-0.2, 0.0, 0.0], [0.2, 0.1, 0.0]]], dtype=F64, requires_grad=True)
    radii = torch.tensor([[0.08, 0.05]], dtype=F64)
    parts = project_parts(rig, seg, radii)
    hard = silhouette(parts, 64, 64)
    prev = None
    for sharp in [4.0, 1.0, 0.25, 0.01]:
        soft = silhouette(parts, 64, 64, sharpness=sharp)
        diff = (soft - hard.to(F64)).abs().mean().item()
        if prev is not None:
            assert diff < prev
        prev = diff
    assert prev < 0.005
    soft = silhouette(project_parts(rig, seg, radii), 64, 64, sharpness=1.0)
    soft.sum().backward()
    assert seg.grad.abs().sum() > 0


def test_soft_silhouette_gradcheck():
    rig = _ortho(scale=20.0, size=12)
    radii = torch.tensor([[0.1, 0.07]], dtype=F64)

    def fn(seg):
        return silhouette(project_parts(rig, seg, radii), 12, 12, sharpness=0.7)

    seg = torch.tensor([[[-0.13, 0.02, 0.0], [0.12, 0.09, 0.1]]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(fn, (seg,))


def test_part_hypotheses_match_full_renders():
    """Cropped hypotheses composited against the rest == rendering the whole body per hypothesis."""
    rig = _ortho(scale=100.0, size=100)
    g = torch.Generator().manual_seed(0)
    rest = torch.tensor([[[-0.3, 0.0, 0.2], [0.3, 0.0, 0.2]]], dtype=F64)
    rest_parts = _first(project_parts(rig, rest, torch.tensor([[0.08, 0.08]], dtype=F64)))
    _, base_depth = label_map(rest_parts, 100, 100)
    k = 6
    hyp = torch.tensor([[0.0, -0.25, 0.0], [0.0, 0.25, 0.0]], dtype=F64).expand(k, 2, 3).clone()
    hyp[..., :2] += 0.1 * torch.randn(k, 1, 2, generator=g, dtype=F64)
    hyp[..., 2] = torch.tensor([-0.5, 0.5, -0.5, 0.5, -0.5, 0.5], dtype=F64)[
        :, None
    ]  # in front / behind
    hyp_parts = project_parts(rig, hyp.unsqueeze(1), torch.tensor([[0.06, 0.05]], dtype=F64))
    hyp_one = ProjectedParts(
        hyp_parts.ends[:, 0, 0], hyp_parts.radii[:, 0, 0], hyp_parts.depth[:, 0, 0]
    )
    covered, visible, origin = render_part_hypotheses(hyp_one, base_depth, crop=80)
    assert not (visible & ~covered).any()
    assert visible[1].sum() < covered[1].sum()  # hypothesis 1 is behind the rest: partly hidden
    for i in range(k):
        both = torch.cat([rest, hyp[i : i + 1]], 0)
        radii = torch.tensor([[0.08, 0.08], [0.06, 0.05]], dtype=F64)
        labels, _ = label_map(_first(project_parts(rig, both, radii)), 100, 100)
        full_visible = labels == 1
        u0, v0 = origin[i].tolist()
        window = torch.zeros(100, 100, dtype=torch.bool)
        window[max(v0, 0) : v0 + 80, max(u0, 0) : u0 + 80] = True
        assert not (full_visible & ~window).any()  # the crop holds the whole part
        got = torch.zeros(100, 100, dtype=torch.bool)
        vv, uu = torch.nonzero(visible[i], as_tuple=True)
        got[vv + v0, uu + u0] = True
        assert torch.equal(got, full_visible), i


def test_outline_points_lie_on_the_boundary_and_occlusion_hides_some():
    rig = _ortho(scale=100.0)
    seg = torch.tensor(
        [[[-0.6, 0.0, 0.5], [0.6, 0.0, 0.5]], [[0.0, -0.6, -0.5], [0.0, 0.6, -0.5]]], dtype=F64
    )
    radii = torch.tensor([[0.1, 0.1], [0.1, 0.1]], dtype=F64)
    parts = _first(project_parts(rig, seg, radii))
    pts, _ = outline_points(parts, per_part=64)
    for p in range(2):
        sdf, _ = capsule_sdf(pts[p], parts.ends[p], parts.radii[p])
        assert sdf.abs().max() < 1e-9
    labels, _ = label_map(parts, 200, 200)
    _, visible = outline_points(parts, per_part=64, labels=labels)
    assert (
        visible[1].all() and not visible[0].all()
    )  # the front part hides some of the back's outline


def test_intensity_colours_labels():
    labels = torch.tensor([[-1, 0], [1, 1]])
    img = render_intensity(labels, torch.tensor([[1.0, 0, 0], [0, 0, 1.0]]), background=0.5)
    assert img.shape == (3, 2, 2)
    assert img[:, 0, 0].tolist() == [0.5, 0.5, 0.5] and img[:, 0, 1].tolist() == [1.0, 0, 0]
