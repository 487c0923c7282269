"""Euler-box limits and the limited connection, against independent computations.

The penalty is checked against SciPy's Euler angles with a brute-force periodic distance over
both Euler triples of every rotation (each verified to rebuild the rotation); the normaliser
against Monte Carlo draws of the connection's own kernel; the sampler against its density
in the conformance suite (tests/pgm/test_factor_conformance.py, ``limited-*`` cases).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from pgm import EulerBox, LimitedConnection
from pgm.kernels import rotation_noise
from pgm.rotations import qexp, qmul

F64 = torch.float64
ORDERS = ["".join(p) for p in itertools.permutations("XYZ")]


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _matrices(q: torch.Tensor) -> np.ndarray:
    """SciPy's rotation matrices of (w, x, y, z) quaternions (SciPy takes x, y, z, w)."""
    return Rotation.from_quat(q.reshape(-1, 4).numpy()[:, [1, 2, 3, 0]]).as_matrix()


def _brute_excess(r: np.ndarray, order: str, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per-channel distance to the box of the closer of the rotation's two Euler triples,
    each tried at every 2 pi shift in [-4 pi, 4 pi]."""
    a, b, c = Rotation.from_matrix(r).as_euler(order)  # upper case: intrinsic, as BVH
    best = None
    for triple in ((a, b, c), (a + math.pi, math.pi - b, c + math.pi)):
        np.testing.assert_allclose(Rotation.from_euler(order, triple).as_matrix(), r, atol=1e-9)
        d = []
        for angle, low, high in zip(triple, lo, hi, strict=True):
            if not np.isfinite(low):
                d.append(0.0)
                continue
            shifted = angle + 2 * math.pi * np.arange(-2, 3)
            d.append(float(np.maximum(0, np.maximum(low - shifted, shifted - high)).min()))
        if best is None or sum(x * x for x in d) < sum(x * x for x in best):
            best = d
    return np.array(best)


@pytest.fixture(scope="module")
def box():
    """Six edges, one per order: narrow, wide, crossing +-pi, a free channel, a zero-width
    channel, a range beyond 2 pi (free)."""
    inf = math.inf
    lo = torch.tensor(
        [
            [-0.5, -0.3, -1.0],
            [0.2, -0.1, -0.4],
            [2.5, -1.0, 0.5],  # the first channel's range crosses pi: [2.5, 3.8]
            [-inf, -0.2, -0.3],
            [0.0, 0.0, -1.5],
            [-4.0, -0.6, -0.2],
        ],
        dtype=F64,
    )
    hi = torch.tensor(
        [
            [0.4, 0.6, 1.0],
            [1.5, 0.8, 0.4],
            [3.8, 1.2, 1.0],
            [inf, 0.9, 0.3],
            [0.0, 0.0, 1.5],
            [3.0, 0.7, 0.9],
        ],
        dtype=F64,
    )
    return EulerBox(lo, hi, ORDERS, 0.1)


def test_excess_is_the_distance_of_the_closer_euler_triple(box):
    qa = qexp(torch.randn(1, 6, 150, 3, generator=_gen(0), dtype=F64))
    qb = qexp(torch.randn(1, 6, 150, 3, generator=_gen(1), dtype=F64))
    got = box.excess(qa, qb)[0].numpy()  # (6, 150, 3)
    ra, rb = _matrices(qa).reshape(6, 150, 3, 3), _matrices(qb).reshape(6, 150, 3, 3)
    lo, hi = box.lower.numpy(), box.upper.numpy()
    hi = np.where(hi - lo >= 2 * math.pi, np.inf, hi)  # a range of 2 pi or more is free
    lo = np.where(np.isinf(hi), -np.inf, lo)
    for e in range(6):
        want = np.stack(
            [_brute_excess(ra[e, i].T @ rb[e, i], ORDERS[e], lo[e], hi[e]) for i in range(150)]
        )
        np.testing.assert_allclose(got[e], want, atol=1e-9, err_msg=ORDERS[e])
    assert 0.2 < (got > 0).mean() < 0.9  # both inside and outside are exercised
    penalty = box.log_penalty(qa, qb)[0].numpy()
    np.testing.assert_allclose(penalty, -0.5 * (got**2).sum(-1) / 0.1**2, atol=1e-9)


def test_rotations_built_from_angles_inside_the_box_have_no_penalty(box):
    """Euler angles drawn inside each box (free channels anywhere), composed by SciPy: the
    penalty is 0, whichever triple the angles were."""
    g = np.random.default_rng(2)
    lo = np.where(np.isfinite(box.lower.numpy()), box.lower.numpy(), -math.pi)
    hi = np.where(np.isfinite(box.upper.numpy()), box.upper.numpy(), math.pi)
    angles = lo[:, None] + (hi - lo)[:, None] * g.random((6, 200, 3))
    q = np.stack([Rotation.from_euler(o, a).as_quat() for o, a in zip(ORDERS, angles, strict=True)])
    qb = torch.from_numpy(q[..., [3, 0, 1, 2]])[None]  # (1, 6, 200, 4)
    qa = torch.tensor([1.0, 0, 0, 0], dtype=F64).expand_as(qb)
    assert box.log_penalty(qa, qb).abs().max() < 1e-9
    # and a rotation about the first axis beyond the range costs (d / softness)^2 / 2
    e = 1  # "XZY": X in [0.2, 1.5], Z and Y ranges contain 0
    q1 = torch.tensor(Rotation.from_euler("XZY", [1.8, 0, 0]).as_quat()[[3, 0, 1, 2]])
    got = box.log_penalty(qa[:, e : e + 1, :1], q1.expand(1, 1, 1, 4), torch.tensor([e]))
    torch.testing.assert_close(got, torch.full_like(got, -0.5 * (0.3 / 0.1) ** 2))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_pair_table_equals_the_elementwise_penalty(box, dtype):
    qa = qexp(torch.randn(2, 6, 7, 3, generator=_gen(3), dtype=F64)).to(dtype)
    qb = qexp(torch.randn(2, 6, 9, 3, generator=_gen(4), dtype=F64)).to(dtype)
    table = box.log_penalty_table(qa, qb)
    assert table.shape == (2, 6, 7, 9) and table.dtype == dtype
    pairs = box.log_penalty(qa[:, :, :, None], qb[:, :, None, :])
    tol = 1e-9 if dtype == F64 else 2e-3
    torch.testing.assert_close(table, pairs, atol=tol, rtol=tol)
    subset = torch.tensor([4, 1])
    sub = box.log_penalty_table(qa[:, subset], qb[:, subset], subset)
    torch.testing.assert_close(sub, table[:, subset], atol=tol, rtol=tol)
    if dtype == torch.float32:  # float32 agrees with float64 to its precision
        ref = box.log_penalty_table(qa.double(), qb.double())
        torch.testing.assert_close(table.double(), ref, atol=5e-3, rtol=1e-3)


def _limited(rotation="bingham", rot_std=0.6):
    lo = torch.tensor([[-0.3, -0.2, -0.5], [0.0, 0.0, -0.8], [-math.inf, -0.1, 0.1]], dtype=F64)
    hi = torch.tensor([[0.2, 0.35, 0.4], [0.0, 0.0, 0.8], [math.inf, 0.3, 0.6]], dtype=F64)
    rel = qexp(torch.tensor([[0.1, 0.0, -0.1], [0.0, 0.2, 0.0], [0.0, 0.0, 0.0]], dtype=F64))
    return LimitedConnection(
        torch.zeros(3, dtype=F64),
        torch.zeros(3, dtype=F64),
        0.05,
        rot_std,
        rel,
        rotation=rotation,
        limits=EulerBox(lo, hi, ["ZYX", "ZXY", "YZX"], 0.1),
    )


@pytest.mark.parametrize(
    ("rotation", "rot_std"), [("bingham", 0.6), ("bingham", 1.0), ("gaussian", 0.3)]
)
def test_normaliser_is_the_kernels_mean_of_exp_penalty(rotation, rot_std):
    """Z_e = E_N[exp(penalty(N r_e))] for N from the connection's kernel: the quadrature
    against 400,000 draws, within 4 standard errors (relative errors ~1e-3)."""
    factor = _limited(rotation, rot_std)
    z = factor.log_normaliser().exp()
    n = 400_000
    noise = rotation_noise((3, n), rot_std, rotation, _gen(5), F64)
    rel = qmul(noise, factor.rel_rot[:, None])
    identity = torch.tensor([1.0, 0, 0, 0], dtype=F64).expand_as(rel)
    w = factor.limits.log_penalty(identity[None], rel[None])[0].exp()
    se = w.std(-1) / math.sqrt(n)
    assert ((z - w.mean(-1)).abs() <= 4 * se + 1e-4).all(), (z, w.mean(-1), se)
    assert (z > 0.001).all() and (z < 0.9).all()


@pytest.mark.parametrize("forward", [True, False])
def test_draws_respect_the_limits_as_the_density_says(forward):
    """Draws in both directions: the relative rotations' penalties are distributed as
    under the truncated kernel (importance-weighted draws of the plain connection), and a
    hinge edge (two zero-width channels) keeps them within a few softness widths."""
    factor = _limited()
    plain = super(LimitedConnection, factor)
    src = qexp(torch.randn(1, 3, 1, 3, generator=_gen(6), dtype=F64))
    x_src = torch.cat([torch.zeros(1, 3, 1, 3, dtype=F64), src], -1).expand(1, 3, 5_000, 7)
    draws = factor.sample_target(x_src, slice(None), forward, _gen(7))
    # the reference: many plain draws, weighted by exp(penalty) (the hinge keeps ~2 %)
    free = plain.sample_target(
        x_src[:, :, :1].expand(1, 3, 100_000, 7), slice(None), forward, _gen(8)
    )

    def ends(x):
        src = x_src[:, :, :1, 3:].expand(*x.shape[:-1], 4)
        return (src, x[..., 3:]) if forward else (x[..., 3:], src)

    def penalty(x):
        return factor.limits.log_penalty(*ends(x))

    p_draw, p_free = penalty(draws), penalty(free)
    w = p_free.exp()
    for e in range(3):
        for cut in (-0.5, -2.0):
            want = float((w[0, e] * (p_free[0, e] > cut)).sum() / w[0, e].sum())
            got = float((p_draw[0, e] > cut).double().mean())
            assert abs(got - want) < 0.04, (e, cut, got, want)  # ~3 standard errors
    hinge = factor.limits.excess(*ends(draws))[0, 1, :, :2]  # the zero-width channels
    assert hinge.max() < 0.5 and hinge.mean() < 0.1, (hinge.max(), hinge.mean())


def test_limited_connection_checks_its_arguments():
    box = EulerBox([-0.1, -0.1, -0.1], [0.1, 0.1, 0.1])
    with pytest.raises(ValueError, match="needs rot_std > 0"):
        LimitedConnection(torch.zeros(3), torch.zeros(3), 0.1, None, limits=box)
    with pytest.raises(TypeError, match="limits must be an EulerBox"):
        LimitedConnection(torch.zeros(3), torch.zeros(3), 0.1, 0.5, limits=(0, 1))
    two = EulerBox(torch.zeros(2, 3), torch.ones(2, 3))
    with pytest.raises(ValueError, match="limits have 2 edges; the connection's parameters have 3"):
        LimitedConnection(torch.zeros(3, 3), torch.zeros(3), 0.1, 0.5, limits=two)
    with pytest.raises(ValueError, match="permutation of 'XYZ'; got 'XXY'"):
        EulerBox([0, 0, 0], [1, 1, 1], "XXY")
    with pytest.raises(ValueError, match="one-sided bounds"):
        EulerBox([-math.inf, 0, 0], [1, 1, 1])
    with pytest.raises(ValueError, match="upper must be >= lower"):
        EulerBox([0, 0, 0], [1, -1, 1])
    with pytest.raises(ValueError, match="3 bound rows, 2 orders"):
        EulerBox(torch.zeros(3, 3), torch.ones(3, 3), ["XYZ", "ZYX"])
    with pytest.raises(ValueError, match="softness must be a number > 0"):
        EulerBox([0, 0, 0], [1, 1, 1], softness=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_limited_connection_follows_the_particles_to_cuda():
    """Tables on a CUDA device equal the CPU's; draws there stay on it and respect the
    hinge edge as on the CPU (the parameters and the normaliser follow the particles)."""
    cuda = torch.device("cuda")
    factor = _limited()
    qa = qexp(torch.randn(1, 3, 20, 3, generator=_gen(9), dtype=F64))
    qb = qexp(torch.randn(1, 3, 30, 3, generator=_gen(10), dtype=F64))
    xa = torch.cat([torch.randn(1, 3, 20, 3, generator=_gen(11), dtype=F64) * 0.05, qa], -1)
    xb = torch.cat([torch.randn(1, 3, 30, 3, generator=_gen(12), dtype=F64) * 0.05, qb], -1)
    edges = torch.tensor([2, 0])
    want = factor.log_potential(edges, xa[:, edges], xb[:, edges], 30)
    got = factor.log_potential(edges, xa[:, edges].to(cuda), xb[:, edges].to(cuda), 30)
    assert got.device.type == "cuda"
    torch.testing.assert_close(got.cpu(), want, atol=1e-9, rtol=1e-9)
    g = torch.Generator(device=cuda).manual_seed(0)
    src = xa[:, :, :1].expand(1, 3, 2_000, 7).to(cuda)
    for forward in (True, False):
        draws = factor.sample_target(src, slice(None), forward, g)
        assert draws.device.type == "cuda" and draws.shape == (1, 3, 2_000, 7)
        ends = (src[..., 3:], draws[..., 3:]) if forward else (draws[..., 3:], src[..., 3:])
        assert factor.limits.excess(*ends)[0, 1, :, :2].max() < 0.5
