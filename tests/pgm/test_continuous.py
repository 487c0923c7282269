"""Pairwise factors of continuous nodes: their samplers draw from their own densities."""

import math

import pytest
import torch

from pgm.continuous import LinearGaussian, RigidConnection
from pgm.rotations import qangle, qconj, qexp, qmul, qrotate
from pgm.spaces import SE3

F64 = torch.float64


def _rigid(kind, rot_std=0.15):
    """A two-edge connection with float64 parameters (factors take the default dtype)."""
    offset_a = torch.tensor([[0.0, 0.3, 0.0], [0.1, 0.0, 0.05]], dtype=F64)
    offset_b = torch.tensor([[0.0, -0.2, 0.0], [0.0, 0.0, 0.0]], dtype=F64)
    rel = qexp(torch.tensor([[0.0, 0.0, 0.4], [0.2, 0.0, 0.0]], dtype=F64))
    torch.set_default_dtype(F64)
    try:
        return RigidConnection(
            offset_a, offset_b, pos_std=0.02, rot_std=rot_std, rel_rot=rel, rotation=kind
        )
    finally:
        torch.set_default_dtype(torch.float32)


def _poses(n, seed):
    g = torch.Generator().manual_seed(seed)
    return SE3().perturb(
        torch.tensor([0.1, 0.2, 2.0, 1.0, 0, 0, 0], dtype=F64).expand(1, 2, n, 7), (0.3, 1.0), g
    )


@pytest.mark.parametrize("kind", ["bingham", "gaussian"])
@pytest.mark.parametrize("forward", [True, False])
def test_rigid_connection_samples_from_its_target_density(kind, forward):
    """E_{y ~ psi(x0, .)}[psi(x1, y) / psi(x0, y)] = 1 (importance check, 100k draws, both
    directions and both rotation kernels); the draws put the joints together (position
    spread s_p per axis) and the relative rotation at rel_rot."""
    factor = _rigid(kind)
    g = torch.Generator().manual_seed(3)
    src = _poses(2, 1)  # (1, E=2, 2, 7): x0 and a nearby x1 per edge
    src[..., 1, :3] = src[..., 0, :3] + 0.01
    src[..., 1, 3:] = qmul(qexp(torch.tensor([0.03, -0.02, 0.0], dtype=F64)), src[..., 0, 3:])
    n = 100_000
    draws = factor.sample_target(src[..., :1, :].expand(1, 2, n, 7), slice(None), forward, g)
    dens = factor.log_target_density(draws, src, slice(None), forward)  # (1, E, n, 2)
    ratio = (dens[..., 1] - dens[..., 0]).exp().mean(-1)
    torch.testing.assert_close(ratio, torch.ones_like(ratio), atol=0.03, rtol=0)
    a, b = (src[..., :1, :], draws) if forward else (draws, src[..., :1, :])
    a, b = a.expand_as(draws), b.expand_as(draws)
    ja = a[..., :3] + qrotate(a[..., 3:], factor.offset_a[None, :, None].expand(1, 2, n, 3))
    jb = b[..., :3] + qrotate(b[..., 3:], factor.offset_b[None, :, None].expand(1, 2, n, 3))
    spread = (ja - jb).std(-2)
    torch.testing.assert_close(spread, torch.full_like(spread, 0.02), rtol=0.03, atol=0)
    rel = qmul(qconj(a[..., 3:]), b[..., 3:])
    angle = qangle(rel, factor.rel_rot[None, :, None].expand_as(rel))
    assert angle.median() < 0.15 * 2  # within the kernel's width


@pytest.mark.parametrize("kind", ["bingham", "gaussian"])
def test_rigid_connection_table_is_symmetric_in_its_arguments(kind):
    """log_potential(a, b)[i, j] is the forward density of b_j given a_i and the backward
    density of a_i given b_j; the fused position table equals the direct Gaussian."""
    factor = _rigid(kind)
    xa, xb = _poses(30, 5), _poses(20, 6)
    table = factor.log_potential(slice(None), xa, xb, 30)
    torch.testing.assert_close(
        factor.log_target_density(xb, xa, slice(None), True), table.transpose(-1, -2)
    )
    torch.testing.assert_close(factor.log_target_density(xa, xb, slice(None), False), table)
    rot_free = _rigid(kind, rot_std=None)
    ja = xa[..., :3] + qrotate(xa[..., 3:], factor.offset_a[None, :, None].expand(1, 2, 30, 3))
    jb = xb[..., :3] + qrotate(xb[..., 3:], factor.offset_b[None, :, None].expand(1, 2, 20, 3))
    normal = torch.distributions.Normal(torch.tensor(0.0, dtype=F64), torch.tensor(0.02, dtype=F64))
    direct = normal.log_prob(ja[..., :, None, :] - jb[..., None, :, :])
    torch.testing.assert_close(rot_free.log_potential(slice(None), xa, xb, 30), direct.sum(-1))


def test_rotation_kernel_choice_is_validated():
    with pytest.raises(ValueError, match="rotation must be one of"):
        RigidConnection(torch.zeros(3), torch.zeros(3), 0.1, 0.1, rotation="vmf")
    with pytest.raises(ValueError, match="rotation must be one of"):
        SE3(rotation="vmf")
    assert math.isfinite(float(LinearGaussian(1).anneal))


@pytest.mark.parametrize("kind", ["bingham", "gaussian"])
@pytest.mark.parametrize("forward", [True, False])
def test_rigid_connection_target_mixture_equals_the_generic_one(kind, forward):
    """RigidConnection's one-call mixture density equals the base class's logsumexp over
    log_target_density (the table) plus the source weights."""
    from pgm.continuous import ContinuousPairwise

    factor = _rigid(kind)
    xs = _poses(30, 7)
    # targets drawn from the sources' conditionals: within the kernel's reach (points far
    # from every source read the documented floor instead; see se3_kernel_mixture)
    xt = factor.sample_target(
        xs[..., :20, :], slice(None), forward, torch.Generator().manual_seed(2)
    )
    log_w = torch.log_softmax(torch.randn(1, 2, 30, dtype=F64), -1)
    fused = factor.log_target_mixture(xt, xs, log_w, slice(None), forward)
    generic = ContinuousPairwise.log_target_mixture(factor, xt, xs, log_w, slice(None), forward)
    torch.testing.assert_close(fused, generic)


@pytest.mark.parametrize("kind", ["bingham", "gaussian"])
def test_rigid_connection_bound_is_the_potential_peak(kind):
    """No table entry exceeds log_potential_bound, and a target at its conditional's mode
    (joints together, relative rotation exactly rel_rot) attains it."""
    factor = _rigid(kind)
    xa = _poses(6, 3)
    table = factor.log_potential(slice(None), xa, _poses(50, 4), 6)
    assert table.max() <= factor.log_potential_bound() + 1e-9
    noiseless = _rigid(kind)
    noiseless.pos_std = noiseless.rot_std = 1e-7  # draw (nearly) the mode
    mode = noiseless.sample_target(xa, slice(None), True, torch.Generator().manual_seed(0))
    at_mode = factor.log_potential(slice(None), xa, mode, 6).diagonal(dim1=-2, dim2=-1)
    torch.testing.assert_close(
        at_mode, torch.full_like(at_mode, factor.log_potential_bound()), atol=1e-6, rtol=0
    )


@pytest.mark.parametrize("forward", [True, False])
def test_rigid_connection_shortcuts_equal_the_general_formulas(forward):
    """Zero joint offsets and an identity relative rotation skip their products; the
    tables, mixtures and draws equal those of the general formulas (same random stream)."""
    fast = RigidConnection(torch.zeros(2, 3), torch.zeros(3), pos_std=0.03, rot_std=0.2)
    general = RigidConnection(torch.zeros(2, 3), torch.zeros(3), pos_std=0.03, rot_std=0.2)
    general._at_origin = lambda end: False
    general._rel_identity = lambda: False
    xa, xb = _poses(30, 5).float(), _poses(20, 6).float()
    log_w = torch.log_softmax(torch.randn(1, 2, 30, generator=torch.Generator().manual_seed(1)), -1)
    for f in (fast, general):
        f.table = f.log_potential(slice(None), xa, xb, 30)
        f.mixture = f.log_target_mixture(xb, xa, log_w, slice(None), forward)
        g = torch.Generator().manual_seed(0)
        f.draws = f.sample_target(xa, slice(None), forward, g)
    torch.testing.assert_close(fast.table, general.table)
    torch.testing.assert_close(fast.mixture, general.mixture)
    torch.testing.assert_close(fast.draws, general.draws)


@pytest.mark.parametrize("kind", ["bingham", "gaussian"])
def test_outlier_kernel_is_the_mixture_of_its_two_kernels(kind):
    """The heavy-tailed connection against two plain ones (rot_std 0.1 and 0.6, each tested
    above): its table is ``log((1 - e) psi_narrow + e psi_wide)`` to float64 rounding, its
    bound is that mixture's peak, and its draws' angles to the mean relative rotation have
    the quantiles of a 80/20 pool of the plain factors' draws (200k each; quantile error
    measured < 0.01 rad, asserted 0.02)."""
    torch.set_default_dtype(F64)
    try:
        common = dict(
            offset_a=torch.tensor([[0.0, 0.3, 0.0]]),
            offset_b=torch.tensor([[0.0, -0.2, 0.0]]),
            pos_std=0.02,
            rel_rot=qexp(torch.tensor([[0.0, 0.0, 0.4]])),
            rotation=kind,
        )
        mixed = RigidConnection(rot_std=0.1, outlier=0.2, outlier_rot_std=0.6, **common)
        narrow = RigidConnection(rot_std=0.1, **common)
        wide = RigidConnection(rot_std=0.6, **common)
    finally:
        torch.set_default_dtype(torch.float32)
    a, b = _poses(30, 1)[:, :1], _poses(40, 2)[:, :1]
    table = mixed.log_potential(slice(None), a, b, 30)
    expected = torch.logaddexp(
        narrow.log_potential(slice(None), a, b, 30) + math.log(0.8),
        wide.log_potential(slice(None), a, b, 30) + math.log(0.2),
    )
    torch.testing.assert_close(table, expected, rtol=1e-12, atol=1e-10)
    peak = math.log(
        0.8 * math.exp(narrow.log_potential_bound()) + 0.2 * math.exp(wide.log_potential_bound())
    )
    assert mixed.log_potential_bound() == pytest.approx(peak, rel=1e-12)
    n = 200_000
    src = a[..., :1, :].expand(1, 1, n, 7)

    def angles(factor, count, seed):
        draws = factor.sample_target(
            src[..., :count, :], slice(None), True, torch.Generator().manual_seed(seed)
        )
        rel = qmul(qconj(src[..., :count, 3:]), draws[..., 3:])
        return qangle(rel, factor.rel_rot[None, :, None].expand_as(rel)).flatten()

    pooled = torch.cat([angles(narrow, int(0.8 * n), 5), angles(wide, int(0.2 * n), 6)])
    levels = torch.tensor([0.1, 0.25, 0.5, 0.75, 0.8, 0.85, 0.9, 0.95, 0.99], dtype=F64)
    got = torch.quantile(angles(mixed, n, 7), levels)
    want = torch.quantile(pooled, levels)
    torch.testing.assert_close(got, want, rtol=0, atol=0.02)


@pytest.mark.parametrize(
    "kwargs, expected",
    [
        (
            dict(rot_std=0.1, outlier=1.0, outlier_rot_std=0.5),
            r"outlier must be a weight in \[0, 1\)",
        ),
        (
            dict(rot_std=0.1, outlier=-0.1, outlier_rot_std=0.5),
            r"outlier must be a weight in \[0, 1\)",
        ),
        (
            dict(rot_std=0.1, outlier=0.1),
            "outlier_rot_std > rot_std; got rot_std=0.1, outlier_rot_std=None",
        ),
        (dict(rot_std=0.5, outlier=0.1, outlier_rot_std=0.5), "outlier_rot_std > rot_std"),
        (dict(outlier=0.1, outlier_rot_std=0.5), "an outlier kernel needs rot_std"),
    ],
)
def test_bad_outlier_kernels_are_refused(kwargs, expected):
    with pytest.raises(ValueError, match=expected):
        RigidConnection(torch.zeros(3), torch.zeros(3), 0.1, **kwargs)
