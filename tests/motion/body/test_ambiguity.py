"""The depth-flip oracle: flips undone exactly, the image never changed."""

from __future__ import annotations

import pytest
import torch

from motion.body.ambiguity import resolve_depth_flips
from tests.motion.body.conftest import F64, walk_segments


@pytest.fixture(scope="module")
def walk():
    from motion.body.spec import part_tree

    seg, model = walk_segments([10, 40, 70])
    return seg, part_tree(model)


def _flip(seg, parents, part, axis):
    """Reflect ``part`` and everything beyond it about the plane through its proximal end
    normal to ``axis`` (the kinematic flip), by brute force on every point below it."""
    out = seg.clone()
    below = [part]
    for _ in range(len(parents)):
        below += [c for c in range(len(parents)) if int(parents[c]) in below and c not in below]
    origin = seg[:, part, 0]  # (T, 3)
    # the flipped part's rigid body: its distal end; its descendants move with the points
    # they hang from, so reflect their offsets from the flipped part's proximal end
    for c in below:
        for end in (0, 1):
            if c == part and end == 0:
                continue
            v = seg[:, c, end] - origin
            out[:, c, end] = origin + v - 2 * (v @ axis)[:, None] * axis
    return out


def test_flips_and_a_depth_shift_are_undone(walk):
    """The truth with a leg, an arm and the head flipped -- each with everything beyond
    it -- and shifted 0.4 m in depth is the truth again."""
    seg, parents = walk
    axis = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    flipped = seg
    for part in (9, 3, 2):  # thigh_l, upper_arm_l, head
        flipped = _flip(flipped, parents, part, axis)
    flipped = flipped + 0.4 * axis
    assert (flipped - seg).norm(dim=-1).mean() > 0.1
    torch.testing.assert_close(resolve_depth_flips(parents, flipped, seg, axis), seg)


def test_image_coordinates_never_change(walk):
    """Any estimate: only the depth coordinate moves, and the error never grows."""
    seg, parents = walk
    g = torch.Generator().manual_seed(0)
    est = seg + 0.05 * torch.randn(seg.shape, generator=g, dtype=F64)
    axis = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=F64), dim=0)
    got = resolve_depth_flips(parents, est, seg, axis)
    across = lambda x: x - (x @ axis)[..., None] * axis  # noqa: E731
    torch.testing.assert_close(across(got), across(est))
    assert (got - seg).norm(dim=-1).mean() <= (est - seg).norm(dim=-1).mean()


def test_bad_shapes_state_expected_and_actual(walk):
    seg, parents = walk
    axis = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    with pytest.raises(ValueError, match=r"shape \(T, P, 2, 3\); got \(3, 15, 2, 3\) and"):
        resolve_depth_flips(parents, seg, seg[:2], axis)
    with pytest.raises(ValueError, match=r"parents must have shape \(15,\); got \(14,\)"):
        resolve_depth_flips(parents[:14], seg, seg, axis)
