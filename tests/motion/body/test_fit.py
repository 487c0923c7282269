"""The posture fit's rotation steps: rigid_fit (Kabsch) and fit_part_rotations (each part's
frame from what images show of it, the twist from the reference)."""

from __future__ import annotations

import math

import pytest
import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix

from motion.body.fit import fit_part_rotations, rigid_fit
from pgm.rotations import qangle, qconj, qexp, qmul

F64 = torch.float64


@pytest.fixture(scope="module")
def posed(walk):
    """The walk's spec and its part poses at three frames."""
    skeleton, model, fk, spec = walk
    frames = [10, 70, 130]
    sub = type(fk)(fk.positions[frames], fk.rotations[frames])
    return spec, spec.poses(model, skeleton, sub)


def _random_rotations(n: int, g: torch.Generator) -> torch.Tensor:
    q = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=F64), dim=-1)
    return quaternion_to_rotation_matrix(q)


def test_rigid_fit_recovers_a_known_transform_and_is_least_squares():
    """Noise-free points come back exactly; with noise, the fit's residual is no larger
    than that of the true transform or of any nearby rotation (it is the minimum)."""
    g = torch.Generator().manual_seed(0)
    r = _random_rotations(4, g)
    t = torch.randn(4, 3, generator=g, dtype=F64)
    src = torch.randn(4, 20, 3, generator=g, dtype=F64)
    dst = (r[:, None] @ src[..., None]).squeeze(-1) + t[:, None]
    r_hat, t_hat = rigid_fit(src, dst)
    torch.testing.assert_close(r_hat, r, atol=1e-10, rtol=0)
    torch.testing.assert_close(t_hat, t, atol=1e-10, rtol=0)
    noisy = dst + 0.05 * torch.randn(dst.shape, generator=g, dtype=F64)
    r_hat, t_hat = rigid_fit(src, noisy)
    assert torch.allclose(torch.det(r_hat), torch.ones(4, dtype=F64))

    def residual(rot, tr):
        return (
            ((rot[:, None] @ src[..., None]).squeeze(-1) + tr[:, None] - noisy).square().sum((1, 2))
        )

    best = residual(r_hat, t_hat)
    assert (best <= residual(r, t) + 1e-12).all()
    for _ in range(20):  # small turns about random axes never do better
        w = 0.02 * torch.randn(4, 3, generator=g, dtype=F64)
        turn = quaternion_to_rotation_matrix(qexp(w))
        # the best translation for the turned rotation: through the centroids
        rot = turn @ r_hat
        tr = noisy.mean(1) - (rot @ src.mean(1)[..., None]).squeeze(-1)
        assert (best <= residual(rot, tr) + 1e-12).all()
    with pytest.raises(ValueError, match="same shape"):
        rigid_fit(src, noisy[:, :5])


def test_weighted_rigid_fit_is_the_fit_of_repeated_points():
    """Integer weights are the unweighted fit of each point repeated that many times (an
    independent answer: the plain Kabsch on the expanded set); a zero weight removes a
    point, however far off it lies; bad weights are refused."""
    g = torch.Generator().manual_seed(1)
    src = torch.randn(3, 12, 3, generator=g, dtype=F64)
    dst = torch.randn(3, 12, 3, generator=g, dtype=F64)
    counts = torch.randint(0, 4, (3, 12), generator=g)
    counts[:, 0] = 1  # every set keeps a point
    r_w, t_w = rigid_fit(src, dst, counts.to(F64))
    for i in range(3):
        rep = counts[i]
        r_i, t_i = rigid_fit(
            src[i].repeat_interleave(rep, 0)[None], dst[i].repeat_interleave(rep, 0)[None]
        )
        torch.testing.assert_close(r_w[i], r_i[0], atol=1e-10, rtol=0)
        torch.testing.assert_close(t_w[i], t_i[0], atol=1e-10, rtol=0)
    far = dst.clone()
    far[:, 5] += 100.0
    w = torch.ones(3, 12, dtype=F64)
    w[:, 5] = 0.0
    r_a, t_a = rigid_fit(src, far, w)
    r_b, t_b = rigid_fit(src[:, torch.arange(12) != 5], dst[:, torch.arange(12) != 5])
    torch.testing.assert_close(r_a, r_b, atol=1e-10, rtol=0)
    torch.testing.assert_close(t_a, t_b, atol=1e-10, rtol=0)
    shared = torch.rand(12, generator=g, dtype=F64) + 0.1  # one weight vector for the batch
    r_s, _ = rigid_fit(src, dst, shared)
    r_e, _ = rigid_fit(src, dst, shared.expand(3, 12))
    torch.testing.assert_close(r_s, r_e, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="one per point"):
        rigid_fit(src, dst, torch.ones(3, 11, dtype=F64))
    with pytest.raises(ValueError, match="one per point"):
        rigid_fit(src, dst, -torch.ones(3, 12, dtype=F64))
    with pytest.raises(ValueError, match="positive total"):
        rigid_fit(src, dst, torch.zeros(3, 12, dtype=F64))


def test_part_rotations_round_trip_and_twist_comes_from_the_reference(posed):
    """On a posture of the model every capsule comes back where it was: to 0.1 mm for single
    bones (the reference pull's weight against theirs), within what the spec's chains bend (pelvis, torso: BodySpec.rigidity, ~1 cm of
    their children's joints) for the others. Turning every part about its own capsule axis
    -- what no silhouette shows -- changes nothing: the children's joints, or for a limb
    whose only child sits on its axis the reference, decide the twist."""
    spec, poses = posed
    fitted = fit_part_rotations(spec, poses, poses)
    torch.testing.assert_close(fitted[..., :3], poses[..., :3])
    moved = (spec.landmarks(fitted) - spec.landmarks(poses)).norm(dim=-1).amax((0, 2))
    single = spec.rigidity < 1e-9
    assert float(moved[single].max()) < 1e-4, moved  # the pull's 1e-4 m^2 vs a limb's ~0.1
    assert float(moved.max()) < 0.015, moved
    axis = torch.nn.functional.normalize(spec.shapes.axis, dim=-1)  # (P, 3) in part frames
    g = torch.Generator().manual_seed(1)
    angle = (torch.rand(3, spec.num_parts, generator=g, dtype=F64) - 0.5) * math.radians(80)
    twist = qexp(angle[..., None] * axis)  # about each part's own axis
    twisted = torch.cat([poses[..., :3], qmul(poses[..., 3:], twist)], -1)
    err = torch.rad2deg(qangle(fit_part_rotations(spec, twisted, poses)[..., 3:], fitted[..., 3:]))
    assert float(err.max()) < 0.5, err


def _swung_forearm(spec, poses):
    """The left forearm's index and the poses with it swung by 25 degrees sideways (its
    children left where they were)."""
    p = spec.part_names.index("forearm_l")
    axis = torch.nn.functional.normalize(spec.shapes.axis[p], dim=0)
    side = torch.linalg.cross(axis, torch.tensor([0.0, 0, 1], dtype=F64))
    swing = qexp(math.radians(25) * torch.nn.functional.normalize(side, dim=0))
    moved = poses.clone()
    moved[:, p, 3:] = qmul(poses[:, p, 3:], swing.expand(poses.shape[0], 4))
    return p, moved


def test_part_rotations_follow_a_real_swing_and_a_given_root(posed):
    """A forearm swung by 25 degrees (its hand carried along) is followed: its far landmark
    lands where the swung one is, to 1 mm; and a given root rotation is used as it is."""
    spec, poses = posed
    p, moved = _swung_forearm(spec, poses)
    for child in (spec.parents == p).nonzero().flatten().tolist():  # the hand moves along
        moved[:, child, :3] = spec.landmarks(moved)[:, p, 1]
    fitted = fit_part_rotations(spec, moved, poses)
    far = (spec.landmarks(fitted)[:, p, 1] - spec.landmarks(moved)[:, p, 1]).norm(dim=-1)
    assert float(far.max()) < 1e-3, far
    root = int((spec.parents < 0).nonzero()[0])
    turn = torch.tensor([0.0, 0.3, 0.0], dtype=F64)
    given = quaternion_to_rotation_matrix(qexp(turn)).expand(3, 3, 3)
    fitted = fit_part_rotations(spec, poses, poses, root_rotation=given)
    got = quaternion_to_rotation_matrix(fitted[:, root, 3:].contiguous())
    torch.testing.assert_close(got, given, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="must have shape"):
        fit_part_rotations(spec, poses[..., :3], poses)


def test_part_rotations_take_a_pull_per_part(posed):
    """Per-part pulls: equal ones give the scalar's result exactly; a pull far stronger than
    the limb's vectors (~0.1 m^2) on the swung forearm alone brings it back to the
    reference's joint angle (within 0.05 degrees; it was 25 off) while the other parts keep
    the scalar's fit."""
    spec, poses = posed
    p, moved = _swung_forearm(spec, poses)
    scalar = fit_part_rotations(spec, moved, poses, 1e-4)
    same = fit_part_rotations(spec, moved, poses, torch.full((3, spec.num_parts), 1e-4, dtype=F64))
    torch.testing.assert_close(same, scalar, rtol=0, atol=1e-12)
    pull = torch.full((3, spec.num_parts), 1e-4, dtype=F64)
    pull[:, p] = 1e3
    strong = fit_part_rotations(spec, moved, poses, pull)
    parent = int(spec.parents[p])
    rel_fit = qmul(qconj(strong[:, parent, 3:]), strong[:, p, 3:])
    rel_ref = qmul(qconj(poses[:, parent, 3:]), poses[:, p, 3:])
    back = torch.rad2deg(qangle(rel_fit, rel_ref))
    assert float(back.max()) < 0.05, back
    others = [q for q in range(spec.num_parts) if q != p and int(spec.parents[q]) != p]
    torch.testing.assert_close(strong[:, others], scalar[:, others], rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match=r"prior_weight must be a float or \(\.\.\., 15\)"):
        fit_part_rotations(spec, moved, poses, torch.ones(3, 4))
