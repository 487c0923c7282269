"""Choosing among searches: the joint image residual against an independent renderer."""

from __future__ import annotations

import pytest
import torch

from motion.body.observation import Observation
from motion.body.select import best_overall, best_per_frame, render_residual
from motion.render import label_map, project_parts, render_intensity, silhouette
from pgm import SE3
from tests.motion.body.conftest import F64

H, W = 120, 160


@pytest.fixture(scope="module")
def searches(walk_body):
    """The true postures of 3 frames and 4 searches: the truth and three perturbations."""
    seg, poses, shapes, model, rig = walk_body
    colours = torch.rand(15, 3, generator=torch.Generator().manual_seed(3), dtype=F64)
    parts = project_parts(rig, seg, model.radii)
    labels, _ = label_map(parts, H, W)
    obs = Observation(
        silhouette(parts, H, W).to(F64)[None],
        image=render_intensity(labels, colours, 0.5)[None],
    )
    g = torch.Generator().manual_seed(0)
    moved = [SE3().perturb(poses[:, :, None], (0.02 * i, 0.1 * i), g)[:, :, 0] for i in (1, 2, 3)]
    return torch.stack([poses, *moved]), shapes, rig, obs, colours


def test_silhouette_residual_counts_the_pixels_in_disagreement(searches):
    """Against motion.render.silhouette (its own rasteriser over the whole image): the
    residual is the number of pixels where the rendering and the observation differ."""
    poses, shapes, rig, obs, _ = searches
    got = render_residual(shapes, rig, obs, poses)  # (4, 3)
    segments = shapes.segments(poses, torch.arange(15))
    rendered = silhouette(project_parts(rig, segments, shapes.radii), H, W).to(F64)
    want = (rendered != obs.silhouette[0]).flatten(2).sum(-1).to(F64)
    # body_layers and silhouette agree but for ties on capsule rims (a pixel or two)
    assert (got - want).abs().max() <= 2, (got, want)
    assert (got[0] == 0).all() and (got[1:] > 20).all()


def test_colour_term_is_the_intensity_cost_over_the_rendered_body(searches):
    poses, shapes, rig, obs, colours = searches
    plain = render_residual(shapes, rig, obs, poses)
    both = render_residual(shapes, rig, obs, poses, colours, colour_weight=0.5, sigma=0.5)
    segments = shapes.segments(poses, torch.arange(15))
    labels, _ = label_map(project_parts(rig, segments, shapes.radii), H, W)
    image = render_intensity(labels, colours)
    diff = (image - obs.image[0]).square().sum(-3) * (labels >= 0)
    want = 0.5 * (diff / 0.5).flatten(2).sum(-1)
    torch.testing.assert_close(both - plain, want, atol=3.0, rtol=0.02)  # rim ties, as above
    assert (both[0] < 1).all()  # the truth: only depth ties where two parts meet


def test_best_per_frame_takes_each_frames_smallest_residual(searches):
    poses = searches[0]
    residual = torch.tensor([[3.0, 1.0, 2.0], [1.0, 5.0, 2.5], [9.0, 9.0, 0.5], [4.0, 2.0, 7.0]])
    best, choice = best_per_frame(poses, residual)
    assert choice.tolist() == [1, 0, 2]
    for t, s in enumerate(choice.tolist()):
        assert torch.equal(best[t], poses[s, t])


def test_best_overall_keeps_one_search_for_every_frame_the_smallest_in_sum(searches):
    poses = searches[0]
    # per frame searches 1, 0, 2 are best; in sum search 3 (6.5 against 9, 8.5 and 13)
    residual = torch.tensor([[3.0, 1.0, 5.0], [1.0, 5.0, 2.5], [9.0, 3.5, 0.5], [2.5, 2.0, 2.0]])
    best, choice = best_overall(poses, residual)
    assert choice.tolist() == [3, 3, 3]
    assert torch.equal(best, poses[3])
    with pytest.raises(ValueError, match=r"residual must have shape \(4, 3\)"):
        best_overall(poses, torch.zeros(3, 4))


def test_bad_shapes_state_expected_and_actual(searches):
    poses, shapes, rig, obs, _ = searches
    with pytest.raises(ValueError, match=r"poses must have shape \(S, T, P, 7\); got \(3, 15, 7\)"):
        render_residual(shapes, rig, obs, poses[0])
    with pytest.raises(ValueError, match="poses have 2 frames; the observation has 3"):
        render_residual(shapes, rig, obs, poses[:, :2])
    with pytest.raises(ValueError, match=r"residual must have shape \(4, 3\)"):
        best_per_frame(poses, torch.zeros(3, 4))
