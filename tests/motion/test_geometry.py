"""motion.geometry against independent answers: the matrix exponential of the cross-product
matrix (built from ``torch.linalg.cross``) for Rodrigues' formula, elementary rotations
written out by hand for the Euler conversions, and invariants (orthonormality, det = 1,
round trips, the rotation angle of ``exp(w)`` being ``|w|``); gradients by float64 gradcheck.

Tolerances: float64 results are compared to ~1e-12 (a few hundred ulps: the reference is a
different algorithm), float32 ones to ~1e-5 (tens of ulps of entries of size 1).
"""

import math

import pytest
import torch

from motion import geometry as geo

F64 = torch.float64
ORDERS = ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"]
TOL = {torch.float32: 1e-5, torch.float64: 1e-12}
DTYPES = [torch.float32, torch.float64]


def _rotation_vectors(n: int, seed: int, max_angle: float = math.pi) -> torch.Tensor:
    """``(n, 3)`` float64 rotation vectors: random axes; angles generic in [0, max_angle),
    tiny (1e-1 .. 1e-12 and 0) and near pi (pi - 1e-1 .. pi - 1e-9)."""
    g = torch.Generator().manual_seed(seed)
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=F64), dim=-1)
    k = n // 4
    angle = torch.cat(
        [
            torch.rand(n - 2 * k - 2, generator=g, dtype=F64) * max_angle,
            10.0 ** -torch.linspace(1, 12, k, dtype=F64),
            math.pi - 10.0 ** -torch.linspace(1, 9, k, dtype=F64),
            torch.zeros(2, dtype=F64),
        ]
    )
    return axis * angle[:, None]


def _cross_matrix(w: torch.Tensor) -> torch.Tensor:
    """``[w]_x`` by its definition: column ``i`` is ``w x e_i`` (independent of the module)."""
    eye = torch.eye(3, dtype=w.dtype).expand(*w.shape[:-1], 3, 3)
    cols = torch.linalg.cross(w[..., None, :].expand(*w.shape[:-1], 3, 3), eye, dim=-1)
    return cols.transpose(-1, -2)  # row i of cols is w x e_i


def _elementary(axis: str, angle: torch.Tensor) -> torch.Tensor:
    """``R_axis(angle)`` written out (right-handed, column vectors)."""
    c, s = torch.cos(angle), torch.sin(angle)
    o, one = torch.zeros_like(angle), torch.ones_like(angle)
    rows = {
        "X": [[one, o, o], [o, c, -s], [o, s, c]],
        "Y": [[c, o, s], [o, one, o], [-s, o, c]],
        "Z": [[c, -s, o], [s, c, o], [o, o, one]],
    }[axis]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def _assert_rotations(r: torch.Tensor, tol: float) -> None:
    eye = torch.eye(3, dtype=r.dtype).expand_as(r)
    torch.testing.assert_close(r.transpose(-1, -2) @ r, eye, atol=tol, rtol=0)
    torch.testing.assert_close(
        torch.linalg.det(r), torch.ones(r.shape[:-2], dtype=r.dtype), atol=tol, rtol=0
    )


# --------------------------------------------------------------------------- rotation vectors


def test_skew_matrix_is_the_cross_product():
    g = torch.Generator().manual_seed(0)
    v, u = torch.randn(2, 4, 5, 3, generator=g, dtype=F64)
    k = geo.skew_matrix(v)
    assert k.shape == (4, 5, 3, 3)
    torch.testing.assert_close(k, _cross_matrix(v), atol=0, rtol=0)
    torch.testing.assert_close((k @ u[..., None])[..., 0], torch.linalg.cross(v, u, dim=-1))
    torch.testing.assert_close(k, -k.transpose(-1, -2), atol=0, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_rotation_vector_to_matrix_is_the_matrix_exponential(dtype):
    """Against ``matrix_exp([w]_x)`` (float64), angles generic, tiny, near pi and past pi."""
    w = torch.cat([_rotation_vectors(400, 1), _rotation_vectors(40, 2, max_angle=4 * math.pi)])
    expected = torch.linalg.matrix_exp(_cross_matrix(w))
    got = geo.rotation_vector_to_matrix(w.to(dtype))
    assert got.dtype == dtype and got.shape == (440, 3, 3)
    torch.testing.assert_close(got.to(F64), expected, atol=TOL[dtype], rtol=0)
    _assert_rotations(got, TOL[dtype])
    batched = geo.rotation_vector_to_matrix(w[:60].reshape(3, 4, 5, 3).to(dtype))
    torch.testing.assert_close(batched.reshape(60, 3, 3), got[:60], atol=0, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_batch_last_variant_agrees_with_batch_first(dtype):
    w = torch.cat([_rotation_vectors(400, 3), _rotation_vectors(40, 4, max_angle=4 * math.pi)])
    w = w.to(dtype)
    last = geo.rotation_vector_to_matrix_batch_last(w.T.contiguous())
    assert last.shape == (3, 3, 440)
    first = geo.rotation_vector_to_matrix(w)
    torch.testing.assert_close(last.permute(2, 0, 1), first, atol=TOL[dtype], rtol=0)
    expected = torch.linalg.matrix_exp(_cross_matrix(w.to(F64)))
    torch.testing.assert_close(last.permute(2, 0, 1).to(F64), expected, atol=TOL[dtype], rtol=0)
    # a non-contiguous view (as the LM loop passes step[:3]) gives the same
    step = torch.cat([w.T, torch.zeros(3, 440, dtype=dtype)])
    torch.testing.assert_close(
        geo.rotation_vector_to_matrix_batch_last(step[:3]), last, atol=0, rtol=0
    )


def test_matrix_to_rotation_vector_round_trips():
    """vector -> matrix -> vector for angles in [0, pi) including tiny and near pi; past pi
    the vector comes back as the equivalent one with angle in [0, pi]."""
    w = _rotation_vectors(400, 5)
    r = torch.linalg.matrix_exp(_cross_matrix(w))
    back = torch.stack([geo.matrix_to_rotation_vector(m) for m in r])
    # near pi the axis comes from (R + R^T) / 2, accurate to ~sqrt(eps) / (pi - angle) ...
    torch.testing.assert_close(back, w, atol=1e-7, rtol=0)
    # ... and away from pi to rounding
    generic = w.norm(dim=-1) < 3.0
    torch.testing.assert_close(back[generic], w[generic], atol=1e-14, rtol=0)
    assert torch.equal(
        geo.matrix_to_rotation_vector(torch.eye(3, dtype=F64)), torch.zeros(3, dtype=F64)
    )

    far = _rotation_vectors(40, 6, max_angle=4 * math.pi)
    r = torch.linalg.matrix_exp(_cross_matrix(far))
    back = torch.stack([geo.matrix_to_rotation_vector(m) for m in r])
    assert float(back.norm(dim=-1).max()) <= math.pi + 1e-12
    torch.testing.assert_close(geo.rotation_vector_to_matrix(back), r, atol=1e-12, rtol=0)


@pytest.mark.parametrize("axis", range(3))
def test_matrix_to_rotation_vector_at_pi(axis):
    """Half turns about a coordinate axis (no antisymmetric part at all) and about a tilted
    axis: the vector has angle pi and reproduces the matrix (its sign is arbitrary)."""
    d = -torch.ones(3, dtype=F64)
    d[axis] = 1.0
    w = geo.matrix_to_rotation_vector(torch.diag(d))
    expected = torch.zeros(3, dtype=F64)
    expected[axis] = math.pi
    torch.testing.assert_close(w.abs(), expected, atol=1e-15, rtol=0)
    tilted = torch.nn.functional.normalize(torch.tensor([1.0, 2.0, -0.5], dtype=F64), dim=0)
    r = torch.linalg.matrix_exp(_cross_matrix(math.pi * tilted))
    w = geo.matrix_to_rotation_vector(r)
    torch.testing.assert_close(w.norm(), torch.tensor(math.pi, dtype=F64), atol=1e-12, rtol=0)
    torch.testing.assert_close(geo.rotation_vector_to_matrix(w), r, atol=1e-12, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_rotation_about_y(dtype):
    a = torch.linspace(-7, 7, 24, dtype=F64).reshape(2, 3, 4)
    w = torch.stack([torch.zeros_like(a), a, torch.zeros_like(a)], -1)
    got = geo.rotation_about_y(a.to(dtype))
    assert got.shape == (2, 3, 4, 3, 3) and got.dtype == dtype
    expected = torch.linalg.matrix_exp(_cross_matrix(w))
    torch.testing.assert_close(got.to(F64), expected, atol=TOL[dtype], rtol=0)


# --------------------------------------------------------------------------- rotation angles


def test_rotation_angle_is_the_vector_norm_even_for_tiny_angles():
    w = _rotation_vectors(400, 7)
    r = geo.rotation_vector_to_matrix(w)
    angle = geo.rotation_angle(r)
    torch.testing.assert_close(angle, w.norm(dim=-1), atol=1e-14, rtol=1e-12)
    tiny = w.norm(dim=-1) < 1e-6
    # relative accuracy where acos((trace - 1) / 2) would give 0 or ~1e-8
    torch.testing.assert_close(angle[tiny], w[tiny].norm(dim=-1), atol=1e-300, rtol=1e-9)


@pytest.mark.parametrize("dtype", DTYPES)
def test_relative_angle_is_the_geodesic_distance(dtype):
    g = torch.Generator().manual_seed(8)
    a = geo.rotation_vector_to_matrix(torch.randn(50, 3, generator=g, dtype=F64))
    w = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=F64), dim=-1)
    w = w * torch.linspace(0.01, math.pi - 0.01, 50, dtype=F64)[:, None]
    b = a @ geo.rotation_vector_to_matrix(w)
    got = geo.relative_angle(a.to(dtype), b.to(dtype))
    # acos near 0 and pi: resolution sqrt(eps)
    tol = 1e-3 if dtype == torch.float32 else 1e-7
    torch.testing.assert_close(got.to(F64), w.norm(dim=-1), atol=tol, rtol=0)
    # symmetric, zero on the diagonal, broadcasts like the product it avoids forming
    torch.testing.assert_close(geo.relative_angle(b, a), geo.relative_angle(a, b), atol=0, rtol=0)
    table = geo.relative_angle(a[:10, None], b[None, :7])
    assert table.shape == (10, 7)
    torch.testing.assert_close(
        table, geo.rotation_angle(a[:10, None].transpose(-1, -2) @ b[None, :7]), atol=1e-7, rtol=0
    )


# --------------------------------------------------------------------------- Euler angles


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("order", ORDERS)
def test_euler_to_matrix_is_the_product_of_elementary_rotations(order, dtype):
    g = torch.Generator().manual_seed(9)
    angles = (torch.rand(200, 3, generator=g, dtype=F64) * 2 - 1) * 4
    expected = (
        _elementary(order[0], angles[:, 0])
        @ _elementary(order[1], angles[:, 1])
        @ _elementary(order[2], angles[:, 2])
    )
    got = geo.euler_to_matrix(angles.to(dtype), order)
    torch.testing.assert_close(got.to(F64), expected, atol=TOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("order", ORDERS)
def test_matrix_to_euler_round_trips(order, dtype):
    """Angles in the principal range come back; any rotation's angles rebuild it."""
    g = torch.Generator().manual_seed(10)
    angles = (torch.rand(300, 3, generator=g, dtype=F64) * 2 - 1) * torch.tensor(
        [math.pi * 0.999, math.pi / 2 * 0.99, math.pi * 0.999], dtype=F64
    )
    m = geo.euler_to_matrix(angles, order)
    back = geo.matrix_to_euler(m.to(dtype), order)
    # float32: the middle angle near +-pi/2 is conditioned like 1 / cos(b)
    torch.testing.assert_close(back.to(F64), angles, atol=TOL[dtype] * 100, rtol=0)
    r = geo.rotation_vector_to_matrix(_rotation_vectors(200, 11))
    e = geo.matrix_to_euler(r.to(dtype), order)
    torch.testing.assert_close(geo.euler_to_matrix(e, order).to(F64), r, atol=TOL[dtype], rtol=0)
    assert float(e[:, 1].abs().max()) <= math.pi / 2
    assert float(e[:, [0, 2]].abs().max()) <= math.pi


@pytest.mark.parametrize("order", ORDERS)
def test_matrix_to_euler_at_gimbal_lock(order):
    """Middle angle +-90 degrees exactly and within 1e-12 .. 1e-6 rad: the angles rebuild the
    matrix to rounding; at exact lock the first angle is 0 (the last carries ``a +- c``)."""
    g = torch.Generator().manual_seed(12)
    n = 200
    angles = (torch.rand(n, 3, generator=g, dtype=F64) * 2 - 1) * math.pi * 0.999
    near = torch.tensor([0.0, 1e-12, 1e-9, 1e-7, 1e-6], dtype=F64).repeat(n // 5)
    sign = torch.where(torch.arange(n) % 2 == 0, 1.0, -1.0).to(F64)
    angles[:, 1] = sign * (math.pi / 2 - near)
    m = geo.euler_to_matrix(angles, order)
    e = geo.matrix_to_euler(m, order)
    torch.testing.assert_close(geo.euler_to_matrix(e, order), m, atol=1e-12, rtol=0)
    exact = near == 0
    locked = torch.hypot(m[exact][:, 0, 0], m[exact][:, 0, 1])
    assert e[exact][:, 0][locked < 1e-12].eq(0).all()


def test_matrix_to_euler_writes_no_negative_zeros():
    e = geo.matrix_to_euler(torch.eye(3, dtype=F64).expand(4, 3, 3), "ZYX")
    assert not torch.signbit(e).any()


@pytest.mark.parametrize("bad", ["XXY", "XY", "xyz", "XYZW"])
def test_bad_rotation_order(bad):
    with pytest.raises(geo.RotationOrderError, match=f"permutation of 'XYZ'; got {bad!r}"):
        geo.euler_to_matrix(torch.zeros(3), bad)
    with pytest.raises(ValueError, match="permutation of 'XYZ'"):
        geo.matrix_to_euler(torch.eye(3), bad)


# --------------------------------------------------------------------------- gradients


def test_gradients_float64():
    g = torch.Generator().manual_seed(13)
    w = torch.randn(4, 3, generator=g, dtype=F64)
    w = torch.cat([w, 1e-5 * w[:1], torch.zeros(1, 3, dtype=F64)]).requires_grad_()
    assert torch.autograd.gradcheck(geo.rotation_vector_to_matrix, (w,))
    assert torch.autograd.gradcheck(geo.rotation_vector_to_matrix_batch_last, (w.T,))
    assert torch.autograd.gradcheck(geo.skew_matrix, (w,))
    angles = (torch.rand(5, 3, generator=g, dtype=F64) - 0.5).requires_grad_()
    for order in ORDERS:
        assert torch.autograd.gradcheck(lambda a, o=order: geo.euler_to_matrix(a, o), (angles,))
        assert torch.autograd.gradcheck(
            lambda a, o=order: geo.matrix_to_euler(geo.euler_to_matrix(a, o), o), (angles,)
        )
    # away from 0 and pi, where the angle is smooth
    r = geo.rotation_vector_to_matrix(torch.randn(5, 3, generator=g, dtype=F64).clamp(-1, 1))
    r = r.detach().requires_grad_()
    assert torch.autograd.gradcheck(geo.rotation_angle, (r,))
    r2 = geo.rotation_vector_to_matrix(torch.randn(5, 3, generator=g, dtype=F64).clamp(-1, 1))
    assert torch.autograd.gradcheck(geo.relative_angle, (r, r2.detach().requires_grad_()))
    yaw = torch.randn(6, generator=g, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(geo.rotation_about_y, (yaw,))
