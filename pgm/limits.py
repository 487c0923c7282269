"""Joint-angle limits: an Euler-angle box on the relative rotation of two SE(3) ends.

An articulated joint's freedom is usually given as a range per Euler angle of its relative
rotation ``R_a^T R_b`` (as BVH files and joint-limit tables give it). :class:`EulerBox` turns
such a box into a soft log-penalty -- 0 inside, a half-Gaussian of the angular distance
outside -- and :class:`LimitedConnection` multiplies it onto a
:class:`~pgm.continuous.RigidConnection`, keeping the connection's conditional sampler
exact: a draw of the connection is accepted with probability ``exp(penalty) <= 1``, which
samples ``psi_conn * exp(penalty)`` exactly (rejection), and the normaliser that makes the
product a density of the target is the same for every source particle (below), computed
once per rotation spread by quadrature.

Euler angles are intrinsic, in the order given: ``"ZYX"`` is ``R = Rz(a) Ry(b) Rx(c)`` (the
BVH convention, channel order). Angles in radians; quaternions ``(w, x, y, z)`` as
:mod:`pgm.rotations`. Shapes: ``B`` batch, ``E`` edges, ``K`` / ``M`` particles.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch
from torch import Tensor

from pgm.continuous import RigidConnection
from pgm.factors import EdgeIndex, PairwiseFactor
from pgm.rotations import qexp, qmatrix, qmul

__all__ = ["EulerBox", "LimitedConnection"]

_AXIS = {"X": 0, "Y": 1, "Z": 2}
_TWO_PI = 2.0 * math.pi
#: rejection rounds of :meth:`LimitedConnection.sample_target` before the fallback
MAX_REJECTION_ROUNDS = 32
#: candidates drawn in one rejection round, at most (bounds its memory)
CANDIDATE_BUDGET = 1 << 20
#: quadrature of the normaliser: radial nodes x polar nodes x azimuths (see _quadrature)
QUADRATURE = (40, 20, 40)
#: normalisers computed, by value (see LimitedConnection.log_normaliser); bounded
_LOG_Z: dict[tuple, Tensor] = {}
_LOG_Z_ENTRIES = 512


def _order_index(order: str) -> tuple[list[int], float]:
    if not isinstance(order, str) or len(order) != 3 or set(order) != {"X", "Y", "Z"}:
        raise ValueError(f"an Euler order must be a permutation of 'XYZ'; got {order!r}")
    i, j, _ = (_AXIS[a] for a in order)
    # sign of the permutation (i, j, k): +1 for the cyclic XYZ, YZX, ZXY
    return [_AXIS[a] for a in order], 1.0 if (j - i) % 3 == 1 else -1.0


class EulerBox:
    """A soft box ``lower <= angles <= upper`` on the intrinsic Euler angles of ``R_a^T R_b``.

    Away from gimbal lock a rotation has exactly two Euler triples (mod 2 pi): ``(a, b, c)``
    with the middle angle ``b`` in ``[-pi/2, pi/2]`` and ``(a + pi, pi - b, c + pi)``. An
    angle's distance to its range is periodic (``d = max(0, |wrap(angle - centre)| - half
    width)``), and the log-penalty is that of the closer triple::

        log_penalty = -0.5 * min over the two triples of sum_channels (d / softness)^2

    -- 0 inside the box, a violation of one ``softness`` costs half a nat, of three 4.5. It
    is a function of the rotation alone (the triple is not chosen by the caller), so a box
    in a file's stored angles applies to rotations read from anywhere. At gimbal lock
    (middle angle +-pi/2, a set of measure zero) the outer angles are split arbitrarily.

    Args:
        lower, upper: ``(3,)`` shared or ``(E, 3)`` per edge, radians, in the channel order
            of ``order``. A free channel has ``-inf, inf`` (or a range of 2 pi or more).
        order: a permutation of ``"XYZ"``, or a list of one per edge.
        softness: radians > 0, the width of the penalty's Gaussian fall-off outside.
    """

    def __init__(self, lower, upper, order: str | list[str] = "ZYX", softness: float = 0.1):
        lo = torch.as_tensor(lower, dtype=torch.float64)
        hi = torch.as_tensor(upper, dtype=torch.float64)
        if lo.shape != hi.shape or lo.dim() not in (1, 2) or lo.shape[-1] != 3:
            raise ValueError(
                f"lower and upper must both have shape (3,) or (E, 3); got {tuple(lo.shape)} "
                f"and {tuple(hi.shape)}"
            )
        if torch.isnan(lo).any() or torch.isnan(hi).any():
            raise ValueError("lower and upper must not be NaN")
        free = torch.isinf(lo) | torch.isinf(hi)
        if not ((lo[free] == -math.inf) & (hi[free] == math.inf)).all():
            raise ValueError(
                "an angle is periodic: a channel is free only with lower = -inf and upper = inf "
                "(one-sided bounds mean nothing)"
            )
        if (hi[~free] < lo[~free]).any():
            raise ValueError("upper must be >= lower on every bounded channel")
        if not (isinstance(softness, int | float) and softness > 0):
            raise ValueError(f"softness must be a number > 0 (radians); got {softness!r}")
        orders = [order] if isinstance(order, str) else list(order)
        parsed = [_order_index(o) for o in orders]
        self.lower, self.upper, self.softness = lo, hi, float(softness)
        self.orders = orders
        free = free | (hi - lo >= _TWO_PI)
        # A free channel is a half width of pi around 0 (|wrap| <= pi). Both triples'
        # distances are |wrap(angle - s)| of the *first* triple's angles (a, b, c): the
        # second's (a + pi, pi - b, c + pi) against centres (c0, c1, c2) are a against
        # c0 - pi, b against pi - c1 (|wrap| is even) and c against c2 - pi. The targets s
        # are kept in [-pi, pi), so that for angles in [-pi, pi] the difference y lies in
        # [-2 pi, 2 pi] and |wrap(y)| = min(|y|, 2 pi - |y|): (E or 1, 2, 3), the first
        # triple's row then the second's; half widths (E or 1, 1, 3).
        centre = torch.where(free, 0.0, 0.5 * (lo + hi)).reshape(-1, 3)
        self.half = torch.where(free, math.pi, 0.5 * (hi - lo)).reshape(-1, 1, 3)
        second = (
            centre * centre.new_tensor([1.0, -1, 1]) + centre.new_tensor([-1.0, 1, -1]) * math.pi
        )
        target = torch.stack([centre, second], 1)
        self.target = torch.remainder(target + math.pi, _TWO_PI) - math.pi
        self.perm = torch.tensor([p for p, _ in parsed])  # (E or 1, 3)
        self.sign = torch.tensor([s for _, s in parsed], dtype=torch.float64)  # (E or 1,)
        counts = {self.half.shape[0], len(orders)} - {1}
        if len(counts) > 1:
            raise ValueError(
                f"per-edge bounds and orders disagree: {self.half.shape[0]} bound rows, "
                f"{len(orders)} orders"
            )
        self.num_edges: int | None = counts.pop() if counts else None

    # -- parameters per edge -------------------------------------------------------------
    @staticmethod
    def _select(t: Tensor, edges: EdgeIndex, dims: int, like: Tensor) -> Tensor:
        """A parameter ``(E or 1, *p)`` for ``(B, E, *dims axes, *p)`` broadcasting, on
        ``like``'s device (and dtype, if floating)."""
        t = t.to(like.device, like.dtype if t.is_floating_point() else t.dtype)
        if t.shape[0] > 1:
            t = t[edges]
        return t.reshape(1, t.shape[0], *([1] * dims), *t.shape[1:])

    def _channels(self, t: Tensor, edges: EdgeIndex, dims: int, like: Tensor) -> Tensor:
        """A per-channel parameter ``(E or 1, r, 3)`` laid out channel-major for
        ``(r, 3, B, E, *dims axes)`` broadcasting."""
        t = t.to(like.device, like.dtype)
        if t.shape[0] > 1:
            t = t[edges]
        return t.permute(1, 2, 0).reshape(t.shape[1], 3, 1, t.shape[0], *([1] * dims))

    # -- the penalty -----------------------------------------------------------------------
    def _squared_distances(self, el, edges: EdgeIndex, dims: int, like: Tensor) -> Tensor:
        """Squared distance to the box per channel of both Euler triples, from the relative
        rotation's elements ``m02, m12, m22, m01, m00`` in axis order (``m[r, c] =
        R[order[r], order[c]]``, each ``(B, E, *d)``): ``(2, 3, B, E, *d)`` radians^2,
        channel-major (every pass is over contiguous memory): six passes over the six
        distances after the three angles."""
        m02, m12, m22, m01, m00 = el
        sign = self._select(self.sign, edges, dims, like)
        theta = m02.new_empty(3, *m02.shape)  # (3, B, E, *d): the first triple (a, b, c)
        torch.atan2(m12 * -sign, m22, out=theta[0])
        torch.asin((m02 * sign).clamp_(-1.0, 1.0), out=theta[1])
        torch.atan2(m01 * -sign, m00, out=theta[2])
        y = (theta - self._channels(self.target, edges, dims, like)).abs_()  # (2, 3, B, E, *d)
        y = torch.minimum(y, _TWO_PI - y)  # |wrap|
        return y.sub_(self._channels(self.half, edges, dims, like)).clamp_(min=0.0).square_()

    def _log_penalty(self, d2: Tensor) -> Tensor:
        per_triple = d2[:, 0] + d2[:, 1] + d2[:, 2]  # (2, B, E, *d)
        return torch.minimum(per_triple[0], per_triple[1]).mul_(-0.5 / self.softness**2)

    def _elements(self, qa: Tensor, qb: Tensor, edges: EdgeIndex):
        """Elementwise relative rotations ``R_a^T R_b`` of ``(B, E, *n, 4)`` each: their five
        matrix elements in axis order, ``(B, E, n)`` each, and the broadcast shape. Written
        out component by component: ``q = conj(q_a) q_b``, the nine elements of ``R(q)``
        stacked, the five each edge's order needs gathered."""
        shape = torch.broadcast_shapes(qa.shape, qb.shape)
        lead = (shape[0], shape[1], -1)
        # component-major copies: every product below is then over contiguous memory
        aw, ax, ay, az = qa.expand(shape).reshape(*lead, 4).movedim(-1, 0).contiguous()
        bw, bx, by, bz = qb.expand(shape).reshape(*lead, 4).movedim(-1, 0).contiguous()
        w = aw * bw + ax * bx + ay * by + az * bz
        x = aw * bx - ax * bw - ay * bz + az * by
        y = aw * by + ax * bz - ay * bw - az * bx
        z = aw * bz - ax * by + ay * bx - az * bw
        s = 2.0 / (w * w + x * x + y * y + z * z).clamp_min(torch.finfo(w.dtype).tiny)
        xs, ys, zs = x * s, y * s, z * s
        xx, yy, zz, xy, xz, yz = x * xs, y * ys, z * zs, x * ys, x * zs, y * zs
        wx, wy, wz = w * xs, w * ys, w * zs
        rows = [1 - yy - zz, xy - wz, xz + wy, xy + wz, 1 - xx - zz, yz - wx, xz - wy, yz + wx]
        m = torch.stack([*rows, 1 - xx - yy])  # (9, B, E, n): m[3 r + c] = R[r, c]
        p = self.perm.to(m.device)
        p = p[edges] if p.shape[0] > 1 else p
        i, j, k = p.unbind(-1)  # (E or 1,)
        flat = torch.stack([3 * i + k, 3 * j + k, 4 * k, 3 * i + j, 4 * i])  # (5, E or 1)
        el = m.gather(0, flat[:, None, :, None].expand(5, *m.shape[1:]))
        return el.unbind(0), shape

    def excess(self, qa: Tensor, qb: Tensor, edges: EdgeIndex = slice(None)) -> Tensor:
        """How far (radians, per channel) each relative rotation ``R_a^T R_b`` lies outside
        the box, for the closer of its two Euler triples (0 inside). Elementwise: ``qa``,
        ``qb`` ``(B, E, *n, 4)`` -> ``(B, E, *n, 3)``."""
        el, shape = self._elements(qa, qb, edges)
        d2 = self._squared_distances(el, edges, 1, el[0])  # (2, 3, B, E, n)
        total = d2.sum(1)
        closer = torch.where(total[1] < total[0], d2[1], d2[0])  # (3, B, E, n)
        return closer.sqrt_().movedim(0, -1).reshape(*shape[:-1], 3)

    def log_penalty(self, qa: Tensor, qb: Tensor, edges: EdgeIndex = slice(None)) -> Tensor:
        """The log-penalty of each relative rotation, elementwise: ``(B, E, *n, 4)`` each ->
        ``(B, E, *n)`` (<= 0)."""
        el, shape = self._elements(qa, qb, edges)
        return self._log_penalty(self._squared_distances(el, edges, 1, el[0])).reshape(shape[:-1])

    def log_penalty_table(self, qa: Tensor, qb: Tensor, edges: EdgeIndex = slice(None)) -> Tensor:
        """The log-penalty of every pair: ``(B, E, K, 4)``, ``(B, E, M, 4)`` ->
        ``(B, E, K, M)``. The five matrix elements the angles need are five batched
        products of ``(K, 3)`` by ``(3, M)`` columns of the two sides' rotation matrices
        (columns in axis order); no ``(K, M, 3, 3)`` temporary."""
        ma, mb = qmatrix(qa), qmatrix(qb)  # (B, E, n, 3, 3)
        perm = self._select(self.perm, edges, 1, ma).unsqueeze(-2)  # (1, E, 1, 1, 3)
        a = ma.gather(-1, perm.expand(*ma.shape))
        b = mb.gather(-1, perm.expand(*mb.shape))

        def el(r, c):
            return a[..., :, r] @ b[..., :, c].transpose(-1, -2)

        d2 = self._squared_distances(
            [el(0, 2), el(1, 2), el(2, 2), el(0, 1), el(0, 0)], edges, 2, qa
        )
        return self._log_penalty(d2)

    def __repr__(self) -> str:
        e = "shared" if self.num_edges is None else f"{self.num_edges} edges"
        return f"EulerBox({e}, orders={sorted(set(self.orders))}, softness={self.softness})"


@functools.lru_cache(maxsize=64)
def _quadrature(std: float, kind: str) -> tuple[Tensor, Tensor]:
    """Nodes and log-weights ``(n, 4)``, ``(n,)`` (float64, weights summing to 1) for
    expectations under the isotropic rotation kernel ``kind`` of spread ``std`` around the
    identity (:func:`pgm.kernels.rotation_noise`): a product of Gauss-Legendre rules in the
    rotation's half angle ``h`` (``"bingham"``: density ``exp(-kappa sin^2 h) sin^2 h`` on
    ``[0, pi/2]``, cut where ``kappa sin^2 h = 60``) or angle ``a`` (``"gaussian"``:
    ``a^2 exp(-a^2 / 2 std^2)`` on ``[0, 11 std]``) and, for the axis, Gauss-Legendre in
    ``cos(theta)`` times equally spaced azimuths. Exact for constants; for the piecewise
    smooth penalties here (measured against a rule of 27x the nodes) relative errors ~1e-4
    for spreads up to 0.3 rad and below 0.5 % for the broadest (std 1-2 rad).
    Tested against Monte Carlo in ``tests/pgm/test_limits.py``."""
    n_r, n_p, n_a = QUADRATURE
    x, w = np.polynomial.legendre.leggauss(n_r)
    if kind == "bingham":
        kappa = 2.0 / std**2
        top = math.asin(min(1.0, math.sqrt(60.0 / kappa)))
        h = 0.5 * top * (x + 1)
        log_wr = np.log(0.5 * top * w) - kappa * np.sin(h) ** 2 + 2 * np.log(np.sin(h))
        angle = 2 * h
    else:
        top = 11.0 * std
        angle = 0.5 * top * (x + 1)
        log_wr = np.log(0.5 * top * w) - 0.5 * (angle / std) ** 2 + 2 * np.log(angle)
    log_wr = log_wr - np.logaddexp.reduce(log_wr)
    cx, cw = np.polynomial.legendre.leggauss(n_p)
    phi = (np.arange(n_a) + 0.5) * _TWO_PI / n_a
    sin_t = np.sqrt(1 - cx**2)
    axis = np.stack(
        [
            (sin_t[:, None] * np.cos(phi)[None]).ravel(),
            (sin_t[:, None] * np.sin(phi)[None]).ravel(),
            np.repeat(cx, n_a),
        ],
        -1,
    )  # (n_p * n_a, 3)
    log_wa = np.repeat(np.log(0.5 * cw / n_a), n_a)
    vec = angle[:, None, None] * axis[None]  # (n_r, n_axes, 3)
    log_w = log_wr[:, None] + log_wa[None]
    return qexp(torch.from_numpy(vec.reshape(-1, 3))), torch.from_numpy(log_w.ravel())


class LimitedConnection(RigidConnection):
    """A :class:`~pgm.continuous.RigidConnection` times joint-angle limits on the relative
    rotation ``R_a^T R_b`` of its ends (an :class:`EulerBox`), normalised in the target::

        psi(x_a, x_b) = psi_conn(x_a, x_b) * exp(log_penalty(R_a^T R_b)) / Z_e

    Given either end, the connection's conditional makes the relative rotation
    ``N r`` with ``N`` drawn from its isotropic rotation kernel (``R_b = N R_a r`` forward,
    ``R_a = N R_b r^-1`` backward; conjugating an isotropic kernel by the source's rotation
    leaves it unchanged), and its position part is a normalised Gaussian for every rotation.
    So ``Z_e = E_N[exp(log_penalty(N r_e))]`` is the same for every source particle and both
    directions: one number per edge and rotation spread, computed by quadrature
    (:func:`_quadrature`) and cached. With it the table is a normalised conditional density
    in either end, as the connection's own (``log_target_density`` is the table; a constant
    per edge changes no belief).

    Sampling (both directions) draws from the connection's conditional and accepts a draw
    with probability ``exp(log_penalty)``: exact rejection sampling of the product. Each
    round draws ``c`` candidates per pending particle, with ``(1 - Z)^c <= e^-f`` for ``Z``
    the smallest acceptance rate of the edges sampled -- a particle's acceptance rate is its
    edge's ``Z_e``, whatever the source -- and ``f = 4`` for up to 4096 pending particles
    (a round usually finishes them; ~4 / Z draws per sample), 1.5 beyond (more rounds,
    ~1.9 / Z draws), and keeps each particle's first accepted candidate; after :data:`MAX_REJECTION_ROUNDS` rounds a particle still pending --
    an acceptance rate below ~1e-3 of the candidates drawn, i.e. a kernel that barely reaches
    the box -- takes its least-penalised candidate (no longer exact, but inside the
    neighbourhood the limits allow as far as the kernel gets).

    Cost: the table adds the penalty of every pair (five ``(K, 3) x (3, M)`` products, three
    arc functions and six passes per pair): measured 15 ms against the connection's 2 ms
    for the body's 14 joints x 150 x 150 particles in float32 on one CPU thread. Sampling
    costs ~2-4 / Z_e connection draws per sample: cheap for boxes the rotation kernel mostly
    covers (the CMU body's joints at ``rot_std`` 1 rad: Z 0.1-1), dearer for hinges with
    zero-width channels under a broad kernel (Z ~0.003 at 1 rad; 0.5 rad gives ~7x more).

    Args:
        offset_a, offset_b, pos_std, rot_std, rel_rot, schedule, rotation,
            rotation_schedule: as :class:`~pgm.continuous.RigidConnection`; ``rot_std`` is
            required (without a rotation kernel the conditional is improper).
        limits: the :class:`EulerBox` (shared, or one row per edge). The limits do not
            anneal; the normaliser follows the rotation kernel's spread at each step.
    """

    def __init__(
        self,
        offset_a,
        offset_b,
        pos_std: float,
        rot_std: float,
        rel_rot=None,
        schedule=None,
        rotation: str = "bingham",
        rotation_schedule=None,
        *,
        limits: EulerBox,
    ):
        if rot_std is None:
            raise ValueError(
                "LimitedConnection needs rot_std > 0: its normaliser and sampler are over the "
                "connection's rotation kernel; got None"
            )
        super().__init__(
            offset_a, offset_b, pos_std, rot_std, rel_rot, schedule, rotation, rotation_schedule
        )
        if not isinstance(limits, EulerBox):
            raise TypeError(f"limits must be an EulerBox; got {type(limits).__name__}")
        if limits.num_edges is not None:
            if self.num_edges not in (None, limits.num_edges):
                raise ValueError(
                    f"limits have {limits.num_edges} edges; the connection's parameters have "
                    f"{self.num_edges}"
                )
            self.num_edges = limits.num_edges
        self.limits = limits
        box = limits
        self._limits_key = (
            self.rotation,
            box.softness,
            *(t.cpu().numpy().tobytes() for t in (box.target, box.half, box.perm, box.sign)),
            self.rel_rot.to(torch.float64).cpu().numpy().tobytes(),
            self.num_edges,
        )

    # -- the normaliser ----------------------------------------------------------------------
    def log_normaliser(self) -> Tensor:
        """``log Z_e`` at this value's rotation spread, ``(E,)`` (or ``(1,)`` when every
        parameter is shared), float64 on the CPU. Cached by value (limits, mean relative
        rotations, kernel and spread), so annealed copies and equal factors share it."""
        s_r = float(self._spreads()[1])
        key = (self._limits_key, s_r)
        if key not in _LOG_Z:
            if len(_LOG_Z) >= _LOG_Z_ENTRIES:
                _LOG_Z.pop(next(iter(_LOG_Z)))  # the oldest
            _LOG_Z[key] = self._compute_log_normaliser(s_r)
        return _LOG_Z[key]

    def _compute_log_normaliser(self, s_r: float) -> Tensor:
        nodes, log_w = _quadrature(s_r, self.rotation)
        e = self.num_edges or 1
        rel = self.rel_rot.to(torch.float64)
        rel = rel.expand(e, 4) if rel.dim() == 1 else rel
        out = torch.empty(e, dtype=torch.float64)
        identity = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)
        chunk = max(1, (1 << 18) // len(nodes))
        for start in range(0, e, chunk):  # setup, not the hot path: bounded memory
            ids = torch.arange(start, min(start + chunk, e))
            q = qmul(nodes[None], rel[ids, None])  # (n_e, n, 4): N r_e
            pen = self.limits.log_penalty(identity.expand_as(q)[None], q[None], ids)[0]
            out[ids] = torch.logsumexp(pen + log_w, -1)
        return out

    def _log_z_for(self, edges: EdgeIndex, like: Tensor) -> Tensor:
        """``log Z`` for ``(B, E, ...)`` broadcasting: ``(1, E or 1)``."""
        log_z = self.log_normaliser().to(device=like.device, dtype=like.dtype)
        return (log_z[edges] if log_z.shape[0] > 1 else log_z).reshape(1, -1)

    # -- tables ------------------------------------------------------------------------------
    def log_potential_into(self, edges, xa, xb, num_states, out):
        table = super().log_potential_into(edges, xa, xb, num_states, out)
        table.add_(self.limits.log_penalty_table(xa[..., 3:7], xb[..., 3:7], edges))
        return table.sub_(self._log_z_for(edges, table)[..., None, None])

    def log_potential_bound(self) -> float:
        # the penalty is <= 0: the connection's peak less the smallest log Z
        return super().log_potential_bound() - float(self.log_normaliser().min())

    def log_target_mixture(self, x_target, x_source, log_w_source, edges, forward):
        # the connection's one-product mixture does not hold the penalty: the generic one
        return PairwiseFactor.log_target_mixture(
            self, x_target, x_source, log_w_source, edges, forward
        )

    # -- sampling ----------------------------------------------------------------------------
    def _edge_ids(self, edges: EdgeIndex, count: int, device) -> Tensor:
        if self.num_edges is None:
            return torch.zeros(count, dtype=torch.long, device=device)
        return torch.arange(self.num_edges, device=device)[edges]

    def _log_accept(self, x_source: Tensor, x_target: Tensor, edges, forward: bool) -> Tensor:
        """``log_penalty`` of (source, target) pairs ``(n, c, D)`` on edges ``(n,)``."""
        qs, qt = x_source[..., 3:7], x_target[..., 3:7]
        qa, qb = (qs, qt) if forward else (qt, qs)
        return self.limits.log_penalty(qa[None], qb[None], edges)[0]

    def sample_target(self, x_source, edges, forward, generator):
        b, e, m, d = x_source.shape
        dev, dt = x_source.device, x_source.dtype
        flat_src = x_source.reshape(-1, d)
        flat_edge = self._edge_ids(edges, e, dev)[None, :, None].expand(b, e, m).reshape(-1)
        accept_rate = self.log_normaliser().exp().to(dev)  # (E or 1,): Z_e
        out = None
        todo = torch.arange(b * e * m, device=dev)  # slots still without a sample
        for round_ in range(MAX_REJECTION_ROUNDS):
            n = len(todo)
            if n == 0:
                break
            ed = flat_edge[todo]
            z = float(accept_rate[ed].min() if accept_rate.shape[0] > 1 else accept_rate[0])
            # (1 - z)^c <= e^-f: a slot misses a round with probability e^-f -- 2 % for
            # the few draws of a proposal (per-round overhead dominates: ~1-2 rounds), 22 %
            # for large batches (compute dominates: ~1.9 / z draws a sample, not ~4 / z)
            f = 4.0 if n <= 4096 else 1.5
            c = math.ceil(f / max(-math.log1p(-min(z, 1 - 1e-12)), 1e-12))
            c = int(min(c, max(1, CANDIDATE_BUDGET // n)))
            src = flat_src[todo][None, :, None, :].expand(1, n, c, d)
            draw = RigidConnection.sample_target(self, src, ed, forward, generator)[0]
            log_acc = self._log_accept(src[0], draw, ed, forward)  # (n, c)
            log_u = torch.rand((n, c), generator=generator, dtype=dt, device=dev).log_()
            ok = log_u < log_acc
            hit = ok.any(-1)
            pick = ok.to(torch.int8).argmax(-1)  # each slot's first accepted candidate
            if round_ == MAX_REJECTION_ROUNDS - 1:  # the fallback: the least penalised
                pick = torch.where(hit, pick, log_acc.argmax(-1))
                hit = torch.ones_like(hit)
            if out is None:
                out = draw.new_empty(b * e * m, draw.shape[-1])
            rows = hit.nonzero().squeeze(-1)
            out[todo[rows]] = draw[rows, pick[rows]]
            todo = todo[~hit]
        return out.reshape(b, e, m, -1)
