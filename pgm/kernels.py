"""Rotation and SE(3) kernels: densities, exact samplers, tables and mixtures.

The perturbation kernels of :class:`pgm.spaces.SE3` and the connection potential of
:class:`pgm.continuous.RigidConnection` are a Gaussian in position times an isotropic
rotation kernel of one of two kinds (:data:`ROTATION_KERNELS`):

* ``"bingham"`` (default): ``exp(-kappa sin^2(a / 2))``, ``kappa = 2 / std^2``, exactly
  normalised (Bessel functions) and exactly sampled (:func:`rotation_noise`); its log density
  is quadratic in quaternion dot products, so a whole ``(..., K, M)`` kernel table is one
  batched matrix product over 15 features (:func:`se3_kernel_table`), and a kernel mixture's
  density one product, exp and sum with the analytic peak as shift (:func:`se3_kernel_mixture`).
* ``"gaussian"``: the Gaussian of rotation vectors, ``exp(e)`` with ``e ~ N(0, std^2 I_3)``.

Angles are radians, positions metres; quaternions ``(w, x, y, z)`` as in :mod:`pgm.rotations`.
Shapes: kernels between ``K`` points and ``M`` centres are ``(..., K, M)``.
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from pgm.rotations import qexp
from pgm.tuning import EXP_FLOOR, budget_for

__all__ = [
    "ROTATION_KERNELS",
    "bingham_log_kernel_from_dot",
    "bingham_log_normaliser",
    "gaussian_position_table",
    "rotation_log_kernel_from_dot",
    "rotation_noise",
    "se3_kernel_mixture",
    "se3_kernel_table",
    "so3_log_kernel",
    "so3_log_kernel_from_dot",
]

_LOG_2PI = math.log(2 * math.pi)
#: rotation kernel families (see :func:`rotation_noise`)
ROTATION_KERNELS = ("bingham", "gaussian")


def so3_log_kernel(angle: Tensor, std: Tensor | float) -> Tensor:
    """Log density on SO(3) of ``exp(e) R_c`` with ``e ~ N(0, std^2 I_3)``, at relative angle
    ``angle`` (radians) from the centre ``R_c``.

    Taken w.r.t. the measure of exponential coordinates, ``dR = 2 (1 - cos a) / a^2 de``, so
    the Gaussian is divided by that Jacobian; wrap-around past pi is ignored (fine for
    ``std`` well below pi). Shapes: broadcast of ``angle`` and ``std``.
    """
    return _so3_log_kernel_half(0.5 * angle, std)


def _so3_log_kernel_half(half: Tensor, std: Tensor | float) -> Tensor:
    """:func:`so3_log_kernel` from the half angle ``h = a / 2`` (what ``acos`` of quaternion
    dot products gives), in one fused polynomial: the Gaussian is ``-2 h^2 / std^2`` and the
    Jacobian ``log(h^2 / sin^2 h) = -2 log(sin h / h)``, whose Taylor series
    ``h^2/3 + h^4/90 + 2h^6/2835 + h^8/18900 + 2h^10/467775 + 1382h^12/3831077250`` is
    truncated with an error below 3e-5 for h <= pi/2 (tested against the closed form)."""
    std = torch.as_tensor(std, dtype=half.dtype, device=half.device)
    h2 = half * half
    # Horner's scheme in place: these tensors are (B, E, K, K) tables, so every avoided
    # temporary is a pass over memory saved.
    poly = h2 * (1382.0 / 3831077250)
    poly.add_(2.0 / 467775)
    for c in (1.0 / 18900, 2.0 / 2835, 1.0 / 90):
        poly.mul_(h2).add_(c)
    poly.mul_(h2).add_(1.0 / 3 - 2.0 / std**2)
    return poly.mul_(h2).sub_(3 * torch.log(std) + 1.5 * _LOG_2PI)


def so3_log_kernel_from_dot(dot: Tensor, std: Tensor | float) -> Tensor:
    """:func:`so3_log_kernel` from quaternion dot products ``<q, q_c>`` (e.g. a batched
    matmul of two particle sets). Overwrites nothing; shapes: broadcast of inputs."""
    return _so3_log_kernel_half(torch.acos_(dot.abs().clamp_(max=1.0)), std)


def _float64(x) -> Tensor:
    """A spread as a float64 tensor: a tensor stays on its device, a number is a host
    constant."""
    if isinstance(x, Tensor):
        return x.to(torch.float64)
    return torch.tensor(x, dtype=torch.float64, device="cpu")


def bingham_log_normaliser(std) -> Tensor:
    """``log c`` of :func:`rotation_noise`'s ``"bingham"`` kernel (float64 for any input):
    ``c = int_{S^3} exp(-kappa (1 - d^2)) dS = 2 pi^2 (i0e(kappa/2) - i1e(kappa/2))`` with
    ``kappa = 2 / std^2`` (in polar form ``1 - d^2 = sin^2 h``, ``dS = 4 pi sin^2 h dh``;
    the exponentially scaled Bessel functions keep large ``kappa`` finite), plus ``log 4``:
    the density is taken w.r.t. the measure of :func:`so3_log_kernel`, ``dR = 8 dS``, and the
    sphere covers each rotation twice."""
    half = 1.0 / _float64(std).square()  # kappa / 2
    c = 2 * math.pi**2 * (torch.special.i0e(half) - torch.special.i1e(half))
    return torch.log(c) + math.log(4.0)


def bingham_log_kernel_from_dot(dot: Tensor, std) -> Tensor:
    """Log density of :func:`rotation_noise`'s ``"bingham"`` kernel around a centre ``q_c``
    from the dot products ``d = <q, q_c>``: ``kappa (d^2 - 1) - log c`` with
    ``kappa = 2 / std^2`` -- near the centre the Gaussian of rotation vectors of per-axis
    ``std`` (``1 - d^2 = sin^2(a / 2) ~ a^2 / 4``), exactly normalised on the whole
    sphere (:func:`bingham_log_normaliser`). Two passes over ``dot``, which it overwrites."""
    kappa = 2.0 / _float64(std).square()
    const = (kappa + bingham_log_normaliser(std)).to(dot.dtype)
    return dot.square_().mul_(kappa.to(dot.dtype)).sub_(const)


def rotation_log_kernel_from_dot(dot: Tensor, std, kind: str = "bingham") -> Tensor:
    """The rotation kernel ``kind`` (``"bingham"`` or ``"gaussian"``) from quaternion dot
    products; may overwrite ``dot``. See :func:`rotation_noise`."""
    if kind == "bingham":
        return bingham_log_kernel_from_dot(dot, std)
    return so3_log_kernel_from_dot(dot, std)


@functools.lru_cache(maxsize=256)
def _bingham_envelope(kappa: float) -> tuple[float, float, float, float, float]:
    """``(t0, head_scale, t_star, p_head, acceptance)`` of :func:`_bingham_around_identity`'s
    envelope for concentration ``kappa``: the split point ``t0`` minimising the envelope's
    mass (a grid search, log-spaced as the best ``t0`` shrinks like ``log(kappa) / kappa``,
    float64; at ``t0 = 0`` there is no head), the head's ``B`` (0 without one), the point
    ``t*`` where ``t^(1/2) exp(-kappa t)`` peaks on [t0, 1], the head's share of the mass and
    the acceptance rate ``mass(f) / mass(g)``, ``mass(f) = (pi/2) (i0e(kappa/2) - i1e(kappa/2))``."""
    t0 = torch.cat(
        [torch.zeros(1, device="cpu"), torch.logspace(-9, math.log10(0.995), 4000, device="cpu")]
    ).double()
    scale = torch.where(t0 > 0, (1.0 - t0).rsqrt(), 0.0)
    head = scale * (0.5 * math.sqrt(math.pi) * kappa**-1.5)
    t_star = torch.clamp(torch.full_like(t0, 0.5 / kappa), max=1.0).maximum(t0)
    tail = 2.0 * t_star.sqrt() * torch.exp(-kappa * t_star) * (1.0 - t0).sqrt()
    i = int(torch.argmin(head + tail))
    half = torch.tensor(0.5 * kappa, dtype=torch.float64, device="cpu")
    mass_f = 0.5 * math.pi * float(torch.special.i0e(half) - torch.special.i1e(half))
    total = float(head[i] + tail[i])
    return float(t0[i]), float(scale[i]), float(t_star[i]), float(head[i]) / total, mass_f / total


def _bingham_around_identity(n: int, std, generator, dtype, device) -> Tensor:
    """``n`` draws of the isotropic Bingham density ``exp(-kappa (1 - w^2))`` on unit
    quaternions ``(w, x, y, z)``, ``kappa = 2 / std^2``, exactly, by rejection.

    With ``q = (sqrt(1 - t), sqrt(t) u)``, ``u`` uniform on S^2 (the density is isotropic),
    ``t = sin^2(a / 2)`` has density ``f(t) ~ t^(1/2) (1 - t)^(-1/2) exp(-kappa t)`` on
    [0, 1). For any ``t0`` in [0, 1) the envelope
    ``g(t) = B t^(1/2) exp(-kappa t) + 1[t >= t0] M (1 - t)^(-1/2)`` with
    ``B = (1 - t0)^(-1/2)`` and ``M = max_{[t0, 1]} t^(1/2) exp(-kappa t)`` dominates ``f``
    (the first term on [0, t0], the second on [t0, 1)), and both terms are sampled in closed
    form: a Gamma(3/2, kappa), i.e. ``|z|^2 / (2 kappa)`` for ``z ~ N(0, I_3)`` -- whose
    direction ``z / |z|`` is the independent ``u`` -- and ``1 - t = (1 - t0) v^2`` with ``v``
    uniform. A draw is kept with probability
    ``f / g = 1 / (B (1 - t)^(1/2) + 1[t >= t0] M exp(kappa t) t^(-1/2))``. ``t0`` minimises
    the envelope's mass (:func:`_bingham_envelope`; ``t0 = 0`` drops the head, best for
    wide kernels): acceptance ~0.99 at std = 0.05, ~0.8 at std = 0.3, above 0.54 at every
    concentration; 3 normals and 2 uniforms a draw (an angular central Gaussian envelope
    needs 4 and 1, at ~45 % acceptance for concentrated kernels)."""
    kappa = 2.0 / float(std) ** 2
    t0, scale, t_star, p_head, acceptance = _bingham_envelope(kappa)
    out = torch.empty(n, 4, dtype=dtype, device=device)
    done = 0
    while done < n:
        m = n - done
        draw = int(m / acceptance * 1.02) + 32  # one round, mostly
        z = torch.randn(3, draw, generator=generator, dtype=dtype, device=device)
        u = torch.rand(2, draw, generator=generator, dtype=dtype, device=device)
        r2 = z.square().sum(0)
        head = u[0] < p_head
        v = (u[0] - p_head) / (1.0 - p_head) if p_head < 1.0 else u[0]
        t = torch.where(head, r2 * (0.5 / kappa), 1.0 - (1.0 - t0) * v.square())
        bound = scale * (1.0 - t).clamp_min(0.0).sqrt()
        # M exp(kappa t) = sqrt(t*) exp(kappa (t - t*)); capped at e^80 against overflow
        # (such a draw is kept with probability below e^-80 either way).
        tail = math.sqrt(t_star) * torch.exp((kappa * (t - t_star)).clamp_max(80.0)) * t.rsqrt()
        bound = bound + torch.where(t >= t0, tail, 0.0)
        keep = ((u[1] * bound < 1.0) & (t < 1.0)).nonzero().squeeze(-1)[:m]
        t, z, r2 = t[keep], z[:, keep], r2[keep]
        block = out[done : done + len(keep)]
        block[:, 0] = (1.0 - t).sqrt()
        block[:, 1:] = (z * (t / r2).sqrt()).T
        done += len(keep)
    return out


def rotation_noise(
    shape: tuple[int, ...],
    std,
    kind: str = "bingham",
    generator: torch.Generator | None = None,
    dtype: torch.dtype | None = None,
    device=None,
) -> Tensor:
    """Random rotations around the identity, ``(*shape, 4)`` unit quaternions, to be
    left-multiplied onto a centre (both kinds are isotropic: the result's density is a
    function of the angle to that centre).

    ``"bingham"``: density ``exp(-kappa sin^2(a / 2))``, ``kappa = 2 / std^2``
    (:func:`bingham_log_kernel_from_dot`): near the centre the Gaussian of rotation vectors
    with ``std`` per axis, exactly normalised and sampled, and its log density is quadratic
    in quaternion dot products -- so a whole kernel table is one batched matrix product.
    ``"gaussian"``: ``exp(e)`` with ``e ~ N(0, std^2 I_3)`` (:func:`so3_log_kernel`, whose
    evaluation needs ``acos`` and a series per entry).
    ``std``: radians, a scalar.
    """
    if kind not in ROTATION_KERNELS:
        raise ValueError(f"rotation kernel must be one of {ROTATION_KERNELS}; got {kind!r}")
    dtype = dtype or torch.get_default_dtype()
    if kind == "gaussian":
        e = torch.randn((*shape, 3), generator=generator, dtype=dtype, device=device)
        return qexp(e * torch.as_tensor(std, dtype=dtype, device=device))
    n = math.prod(shape)
    return _bingham_around_identity(n, std, generator, dtype, device).reshape(*shape, 4)


def _quadratic_features_into(q: Tensor, scale: float, out: Tensor) -> None:
    """``out (..., 10, K) = scale * f(q)`` with ``<f(a), f(b)> = <a, b>^2``: the squares
    ``q_i^2`` then ``sqrt(2) q_i q_j`` for ``i < j`` (the cross terms appear twice in
    ``<a, b>^2``). ``q (..., 4, K)`` component-major: every product is a contiguous row."""
    q = q.contiguous()
    if scale != 1.0:
        q = q * math.sqrt(scale)
    torch.mul(q, q, out=out[..., :4, :])
    r2q = q[..., :3, :] * math.sqrt(2.0)
    torch.mul(r2q[..., 0:1, :], q[..., 1:, :], out=out[..., 4:7, :])
    torch.mul(r2q[..., 1:2, :], q[..., 2:, :], out=out[..., 7:9, :])
    torch.mul(r2q[..., 2:3, :], q[..., 3:, :], out=out[..., 9:10, :])


def _se3_features(
    pos_a: Tensor,
    quat_a: Tensor | None,
    pos_b: Tensor,
    quat_b: Tensor | None,
    pos_std,
    rot_std,
    log_weights_b: Tensor | None = None,
) -> tuple[Tensor, Tensor, tuple[int, ...]]:
    """Features ``L (N, F, K)``, ``R (N, F, M)`` (leading dims flattened to ``N``) with
    ``L^T R = log N(p_a - p_b; 0, s_p^2 I_3) + log k(q_a, q_b) + log_w_b`` for the Bingham
    rotation kernel ``k`` (``rot_std=None``: position only).

    ``-|a - b|^2 / 2 s^2 = a.b / s^2 - |a|^2 / 2 s^2 - |b|^2 / 2 s^2`` and
    ``kappa <q_a, q_b>^2`` is linear in the 10 products ``q_i q_j`` (``i <= j``), so the
    whole table is one batched matrix product with F = 15 features: a single write of
    ``(..., K, M)``. The features are built component-major (each a contiguous row of K),
    where concatenating narrow last-axis pieces would cost more than the product. Positions
    are centred on a common point first, so float32 keeps small differences of large ones."""
    lead = torch.broadcast_shapes(pos_a.shape[:-2], pos_b.shape[:-2])
    if quat_a is not None:
        lead = torch.broadcast_shapes(lead, quat_a.shape[:-2], quat_b.shape[:-2])
    std = float(pos_std)
    inv = 1.0 / std**2
    const = 3.0 * math.log(std) + 1.5 * _LOG_2PI
    nf = 5 if rot_std is None else 15
    origin = pos_b.mean(-2, keepdim=True)

    def side(
        pos: Tensor, quat: Tensor | None, scale_pos: float, scale_rot
    ) -> tuple[Tensor, Tensor]:
        """``(..., F, n)`` features -- scaled centred position, quadratic rotation features,
        two rows left for the caller -- and the squared centred positions ``(..., n)``."""
        n = pos.shape[-2]
        out = pos.new_empty(*lead, nf, n)
        p = out[..., :3, :]
        torch.sub(pos.transpose(-1, -2), origin.transpose(-1, -2), out=p)
        if nf == 15:
            q = quat.transpose(-1, -2).expand(*lead, 4, n)
            _quadratic_features_into(q, scale_rot, out[..., 3:13, :])
        sq = p.square().sum(-2)
        p.mul_(scale_pos)
        return out, sq

    kappa = None
    if rot_std is not None:
        kappa = 2.0 / float(rot_std) ** 2
        const += kappa + float(bingham_log_normaliser(rot_std))
    left, sq_a = side(pos_a, quat_a, inv, kappa)
    right, sq_b = side(pos_b, quat_b, 1.0, 1.0)
    torch.add(sq_a.mul_(-0.5 * inv), -const, out=left[..., -2, :])
    left[..., -1, :] = 1.0
    right[..., -2, :] = 1.0
    sq_b.mul_(-0.5 * inv)
    if log_weights_b is not None:
        sq_b.add_(log_weights_b)
    right[..., -1, :] = sq_b
    return left.reshape(-1, nf, left.shape[-1]), right.reshape(-1, nf, right.shape[-1]), lead


def se3_kernel_table(
    pos_a: Tensor,
    quat_a: Tensor | None,
    pos_b: Tensor,
    quat_b: Tensor | None,
    pos_std,
    rot_std,
    kind: str = "bingham",
    out: Tensor | None = None,
) -> Tensor:
    """``log N(p_a - p_b; 0, pos_std^2 I_3) + log k(q_a, q_b)`` for every pair, with ``k``
    the rotation kernel ``kind`` (``rot_std=None``: position only). Shapes: ``(..., K, 3)``,
    ``(..., K, 4)``, ``(..., M, 3)``, ``(..., M, 4)`` -> ``(..., K, M)``. With the Bingham
    kernel (or none) one batched matrix product (see :func:`_se3_features`), written into
    ``out`` (a buffer of as many elements, reused by the caller) when given."""
    if rot_std is not None and kind != "bingham":
        out = se3_kernel_table(pos_a, None, pos_b, None, pos_std, None)
        dot = quat_a @ quat_b.transpose(-1, -2)
        return out.add_(rotation_log_kernel_from_dot(dot, rot_std, kind))
    left, right, lead = _se3_features(pos_a, quat_a, pos_b, quat_b, pos_std, rot_std)
    if len(lead) == 2:
        # Laid out edge-major, (E, B, K, M) in memory for a (B, E, K, M) table, so that a
        # run of edges is one contiguous block (what tree BP's exp-matmul messages read).
        n0, n1 = lead
        left = left.reshape(n0, n1, *left.shape[-2:]).transpose(0, 1).reshape(left.shape)
        right = right.reshape(n0, n1, *right.shape[-2:]).transpose(0, 1).reshape(right.shape)
        table = _bmm_into(left.transpose(-1, -2), right, out)
        return table.reshape(n1, n0, *table.shape[-2:]).transpose(0, 1)
    table = _bmm_into(left.transpose(-1, -2), right, out)
    return table.reshape(*lead, *table.shape[-2:])


def _bmm_into(a: Tensor, b: Tensor, out: Tensor | None) -> Tensor:
    shape = (a.shape[0], a.shape[1], b.shape[2])
    if out is not None and out.numel() == math.prod(shape) and out.dtype == a.dtype:
        return torch.bmm(a, b, out=out.view(shape))
    return torch.bmm(a, b)


def gaussian_position_table(a: Tensor, b: Tensor, std) -> Tensor:
    """``log N(a_k - b_m; 0, std^2 I_3)`` for every pair: ``(..., K, 3)``, ``(..., M, 3)``
    -> ``(..., K, M)`` (one batched matrix product, see :func:`_se3_features`)."""
    return se3_kernel_table(a, None, b, None, std, None)


def se3_kernel_mixture(
    pos_a: Tensor,
    quat_a: Tensor | None,
    pos_b: Tensor,
    quat_b: Tensor | None,
    log_weights_b: Tensor,
    pos_std,
    rot_std,
    kind: str = "bingham",
) -> Tensor:
    """``log sum_m w_m k(a_k, b_m)`` for the kernel of :func:`se3_kernel_table`: the density
    of each ``a`` under the kernel mixture centred on the ``b`` with weights ``log_weights_b``
    ``(..., M)``; returns ``(..., K)``.

    With the Bingham kernel (or none) no table entry exceeds the kernel's analytic peak
    (0 in the features' units) plus the largest weight, which is therefore the log-sum-exp's
    shift: one matrix product, ``exp`` in place and a sum, without a pass for the maximum.
    Terms more than 87 nats below that peak count as ``e^-87`` (the CPU's exp leaves its
    vectorised path below, ~40x slower): a mixture density is then exact up to ``M e^-87``
    times the peak, and a point far from every centre reads about ``peak - 82`` instead of
    less. As a proposal's component that is far below the density of the component that
    drew the point (that one is above ``peak - 25`` except with probability ~1e-8)."""
    if rot_std is not None and kind != "bingham":
        table = se3_kernel_table(pos_a, quat_a, pos_b, quat_b, pos_std, rot_std, kind)
        return torch.logsumexp(table + log_weights_b.unsqueeze(-2), -1)
    w_peak = log_weights_b.amax(-1, keepdim=True)
    w_peak = torch.where(torch.isfinite(w_peak), w_peak, torch.zeros_like(w_peak))
    left, right, lead = _se3_features(
        pos_a, quat_a, pos_b, quat_b, pos_std, rot_std, log_weights_b - w_peak
    )
    # In blocks of ~4 MB on a CPU: the product, clamp, exp and sum then pass over cached
    # memory (2.4x faster than whole (N, K, M) passes at K = M = 150 on 2 cores); elsewhere
    # the blocks only bound memory (256 MB).
    n, k, m = left.shape[0], left.shape[-1], right.shape[-1]
    block_bytes = budget_for(left.device).mixture_block_bytes
    rows = max(1, block_bytes // (k * m * left.element_size()))
    s = left.new_empty(n, k)
    buffer = left.new_empty(min(rows, n), k, m)
    for start in range(0, n, rows):
        block = slice(start, min(start + rows, n))
        table = torch.bmm(
            left[block].transpose(-1, -2), right[block], out=buffer[: block.stop - start]
        )
        torch.sum(table.clamp_(min=EXP_FLOOR).exp_(), -1, out=s[block])
    out = torch.log(s)
    w_peak = w_peak.expand(*lead, 1).reshape(-1, 1)
    return (out + w_peak).reshape(*lead, out.shape[-1])
