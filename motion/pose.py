"""Global pose from 2-D joints (the proposal's Section 5.1.1), batched over many problems.

Given 3-D joints ``X`` in the body frame and their pixels ``x`` in a calibrated pinhole
camera, find ``R, t`` with ``x ~ K (R X + t)``: a linear DLT estimate of ``[R | t]`` (in
normalised image coordinates, ``P[2, 3]`` fixed positive so depths are positive, then the
nearest proper rotation by a 3x3 SVD), refined by Levenberg-Marquardt on the 6 pose
parameters (left-multiplied rotation increment, translation) with analytic Jacobians,
optionally from several starts. Everything is one batched tensor program over ``B``.

Conventions: OpenCV camera frame; pixels; rotation vectors in radians; metres.
Shapes: ``B`` problems, ``n`` joints.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from torch import Tensor

from motion.geometry import rotation_vector_to_matrix_batch_last, skew_matrix

#: Default convergence tolerance of the LM refinement: a problem stops when a further step
#: would lower its cost by less than this fraction. At 1.8-3.6 % joint noise this leaves the
#: rotation within 0.01 degrees of the exact optimum (median ~1e-5;
#: ``tests/motion/test_pose.py``), far below the noise's own effect (0.5-1 degree); without
#: noise the cost still reaches ~0.
TOL = 1e-7

__all__ = [
    "PoseResult",
    "affine_pose",
    "dlt_pose",
    "newton_pose",
    "refine_pose",
    "solve_pose",
    "solve_pose_views",
]


@dataclass
class PoseResult:
    """R ``(B, 3, 3)``, t ``(B, 3)``, cost ``(B,)`` = mean squared pixel residual, iterations run."""

    R: Tensor
    t: Tensor
    cost: Tensor
    iterations: int


def _cholesky(entry, m: int) -> list[list[Tensor]]:
    """Unrolled Cholesky factorisation of small symmetric positive-definite matrices,
    vectorised over the batch: ``entry(i, j)`` gives the lower-triangle entries (``i >= j``)
    as tensors of one batch shape; returns the factor's lower triangle the same way."""
    low = [[None] * m for _ in range(m)]
    for i in range(m):
        for j in range(i + 1):
            acc = entry(i, j)
            for k in range(j):
                acc = acc - low[i][k] * low[j][k]
            low[i][j] = acc.clamp_min(1e-300).sqrt() if i == j else acc / low[j][j]
    return low


def _forward(low: list[list[Tensor]], rhs: list[Tensor]) -> list[Tensor]:
    """``L^-1 rhs`` for a factor from :func:`_cholesky`."""
    y = []
    for i in range(len(rhs)):
        acc = rhs[i]
        for k in range(i):
            acc = acc - low[i][k] * y[k]
        y.append(acc / low[i][i])
    return y


def _backward(low: list[list[Tensor]], y: list[Tensor]) -> list[Tensor]:
    """``L^-T y`` for a factor from :func:`_cholesky`."""
    m = len(y)
    x = [None] * m
    for i in reversed(range(m)):
        acc = y[i]
        for k in range(i + 1, m):
            acc = acc - low[k][i] * x[k]
        x[i] = acc / low[i][i]
    return x


def _solve_spd(a: Tensor, b: Tensor) -> Tensor:
    """Solve batch-first SPD systems ``a (B, m, m)``, ``b (B, m)`` -> ``(B, m)``."""
    low = _cholesky(lambda i, j: a[:, i, j], a.shape[-1])
    return torch.stack(_backward(low, _forward(low, list(b.unbind(-1)))), -1)


def _check(points3d: Tensor, points2d: Tensor, K: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    if points3d.dim() == 2:
        points3d = points3d.unsqueeze(0)
    if points2d.dim() == 2:
        points2d = points2d.unsqueeze(0)
    if (
        points3d.shape[-1] != 3
        or points2d.shape[-1] != 2
        or points3d.shape[-2] != points2d.shape[-2]
    ):
        raise ValueError(
            f"need points3d (B, n, 3) and points2d (B, n, 2) with the same n; got "
            f"{tuple(points3d.shape)} and {tuple(points2d.shape)}"
        )
    if points3d.shape[-2] < 6:
        raise ValueError(f"pose from 2-D joints needs at least 6 joints; got {points3d.shape[-2]}")
    if not (torch.isfinite(points3d).all() and torch.isfinite(points2d).all()):
        raise ValueError("points contain NaN or inf")
    b = max(points3d.shape[0], points2d.shape[0])
    K = K.to(points2d.dtype)
    if K.shape[-2:] != (3, 3) or bool(
        (K[..., 2, :2] != 0).any() | (K[..., 1, 0] != 0).any() | (K[..., 2, 2] != 1).any()
    ):
        raise ValueError(
            "K must be a pinhole intrinsic matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]]"
        )
    if K.shape == (3, 3):
        K = K.expand(b, 3, 3)
    return points3d.expand(b, -1, -1), points2d.expand(b, -1, -1), K


def dlt_pose(points3d: Tensor, points2d: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Linear pose: DLT of ``[R | t]`` in normalised coordinates, positive depth, nearest rotation.

    Shapes: points3d ``(B, n, 3)``, points2d ``(B, n, 2)``, K ``(3, 3)`` or ``(B, 3, 3)`` ->
    R ``(B, 3, 3)``, t ``(B, 3)``.
    """
    x3, x2, K = _check(points3d, points2d, K)
    return _dlt(x3, _Pinhole.build(x3, x2, K))


def _dlt(x3: Tensor, problem: _Pinhole) -> tuple[Tensor, Tensor]:
    norm = torch.stack(problem.normalised(), -1).transpose(0, 1)  # (B, n, 2)
    # centre and scale the 3-D points for conditioning; undone below
    mean = x3.mean(1, keepdim=True)
    scale = (x3 - mean).norm(dim=-1).mean(1, keepdim=True).unsqueeze(-1).clamp_min(1e-9)
    xs = (x3 - mean) / scale
    h = torch.cat([xs, torch.ones_like(xs[..., :1])], -1)  # (B, n, 4)
    zeros = torch.zeros_like(h)
    rows_u = torch.cat([h, zeros, -norm[..., :1] * h], -1)
    rows_v = torch.cat([zeros, h, -norm[..., 1:] * h], -1)
    a = torch.cat([rows_u, rows_v], 1)  # (B, 2n, 12)
    _, _, vh = torch.linalg.svd(a, full_matrices=False)
    p = vh[:, -1].reshape(-1, 3, 4)
    # depth of the (normalised) centroid is P[2, 3]: make it positive
    p = p * torch.sign(p[:, 2, 3]).clamp(min=0).mul(2).sub(1)[:, None, None]
    u, s, wh = torch.linalg.svd(p[:, :, :3])
    det = torch.linalg.det(u @ wh)
    d = torch.ones_like(s)
    d[:, 2] = det
    r = u @ torch.diag_embed(d) @ wh
    return r, problem.translation_for(r.permute(1, 2, 0)).T


def affine_pose(
    points3d: Tensor, points2d: Tensor, K: Tensor, orthographic: bool = False
) -> tuple[Tensor, Tensor]:
    """Weak-perspective pose: a least-squares affine camera on centred points, its rows
    orthonormalised (the polar factor, closed form), t then re-solved exactly for
    perspective. Stable where the DLT is not (a body far from the camera is nearly flat in
    depth). For an ``orthographic`` camera the affine scale is dropped (it is known:
    pixels per metre) and ``t_z = 0``. Shapes as :func:`dlt_pose`."""
    r, t = _Pinhole.build(*_check(points3d, points2d, K), orthographic).initial_pose()
    return r.permute(2, 0, 1), t.T


def _project(pc: Tensor, fx: Tensor, fy: Tensor, cx: Tensor, cy: Tensor, skew: Tensor):
    """Pinhole pixels of camera-frame points; intrinsics broadcast against ``pc[..., 0]``.
    Returns u, v and the depth (clamped positive)."""
    z = pc[..., 2].clamp_min(1e-9)
    u = fx * pc[..., 0] / z + skew * pc[..., 1] / z + cx
    v = fy * pc[..., 1] / z + cy
    return u, v, z


def _intrinsics(K: Tensor, shape: tuple[int, ...]) -> list[Tensor]:
    """fx, fy, cx, cy, skew of ``K`` (..., 3, 3), reshaped to broadcast as ``shape``."""
    return [K[..., i, j].reshape(shape) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2), (0, 1))]


def _matmul3(a: Tensor, b: Tensor) -> Tensor:
    """Products of 3x3 matrices stored batch last: ``(3, 3, B) @ (3, 3, B)``."""
    return (a[:, :, None] * b[None]).sum(1)


class _Pinhole:
    """A batch of pose problems stored *batch last*: points ``X (3, n, B)``, pixels
    ``u, v (n, B)``, intrinsics ``(B,)`` each.

    With n ~ 20 points per problem, batch-first tensors make every broadcast against a
    per-problem value an outer loop of 20-element inner loops; batch last, every operation
    is one long vectorised loop over the batch (faster end to end).

    ``orthographic``: project without the division by depth (``K[0, 0]``, ``K[1, 1]`` are
    pixels per metre, as in :class:`motion.cameras.CameraRig`); the depth ``t_z`` is then
    unobservable and stays where it starts.
    """

    def __init__(self, X, u, v, fx, fy, cx, cy, skew, orthographic: bool = False):
        self.X, self.u, self.v = X, u, v
        self.fx, self.fy, self.cx, self.cy, self.skew = fx, fy, cx, cy, skew
        self.skewed = bool((skew != 0).any())
        self.orthographic = orthographic

    @classmethod
    def build(cls, x3: Tensor, x2: Tensor, K: Tensor, orthographic: bool = False) -> _Pinhole:
        """From batch-first ``x3 (B, n, 3)``, ``x2 (B, n, 2)``, ``K (B, 3, 3)``."""
        intrinsics = (K[:, i, j].contiguous() for i, j in ((0, 0), (1, 1), (0, 2), (1, 2), (0, 1)))
        return cls(
            x3.permute(2, 1, 0).contiguous(),
            x2[..., 0].T.contiguous(),
            x2[..., 1].T.contiguous(),
            *intrinsics,
            orthographic=orthographic,
        )

    def select(self, index: Tensor) -> _Pinhole:
        """The problems at ``index`` (long indices over the batch)."""
        fields = (self.fx, self.fy, self.cx, self.cy, self.skew)
        return _Pinhole(
            self.X.index_select(-1, index),
            self.u.index_select(-1, index),
            self.v.index_select(-1, index),
            *(f[index] for f in fields),
            orthographic=self.orthographic,
        )

    def initial_pose(self) -> tuple[Tensor, Tensor]:
        """Weak-perspective start (see :func:`affine_pose`): ``r (3, 3, B)``, ``t (3, B)``.

        A least-squares affine camera on centred points (3x3 normal equations), its two rows
        made orthonormal by the polar factor ``(A A^T)^(-1/2) A`` (closed form for the 2x2
        SPD ``A A^T``), then the exact least-squares translation for that rotation (or, for
        an orthographic camera, the image of the centroid, with ``t_z = 0``)."""
        xn, yn = self.normalised()
        mean = self.X.mean(1)  # (3, B)
        xc = self.X - mean[:, None]
        xs, ys = xn - xn.mean(0), yn - yn.mean(0)
        gram = [[(xc[i] * xc[j]).sum(0) if j <= i else None for j in range(3)] for i in range(3)]
        low = _cholesky(lambda i, j: gram[i][j], 3)
        a = [
            _backward(low, _forward(low, [(xc[i] * s).sum(0) for i in range(3)])) for s in (xs, ys)
        ]
        m00, m01, m11 = (
            sum(p * q for p, q in zip(a[i], a[j], strict=True)) for i, j in ((0, 0), (0, 1), (1, 1))
        )
        sd = (m00 * m11 - m01 * m01).clamp_min(1e-30).sqrt()
        norm = (m00 + m11 + 2 * sd).sqrt()
        q00, q01, q11 = (m00 + sd) / norm, m01 / norm, (m11 + sd) / norm  # (A A^T)^(1/2)
        det = q00 * q11 - q01 * q01
        r1 = [(q11 * a[0][k] - q01 * a[1][k]) / det for k in range(3)]
        r2 = [(q00 * a[1][k] - q01 * a[0][k]) / det for k in range(3)]
        r3 = [
            r1[1] * r2[2] - r1[2] * r2[1],
            r1[2] * r2[0] - r1[0] * r2[2],
            r1[0] * r2[1] - r1[1] * r2[0],
        ]
        r = torch.stack([torch.stack(row) for row in (r1, r2, r3)])
        if self.orthographic:
            rm = (r * mean[None]).sum(1)  # R times the centroid, (3, B)
            t_xy = torch.stack([xn.mean(0), yn.mean(0)]) - rm[:2]
            return r, torch.cat([t_xy, torch.zeros_like(t_xy[:1])])
        return r, self.translation_for(r)

    def normalised(self) -> tuple[Tensor, Tensor]:
        """Normalised image coordinates ``K^-1 x``: ``xn, yn`` ``(n, B)`` (closed form for the
        upper-triangular ``K`` that :func:`_check` guarantees)."""
        yn = (self.v - self.cy) / self.fy
        return (self.u - self.cx - self.skew * yn) / self.fx, yn

    def translation_for(self, r: Tensor) -> Tensor:
        """Least-squares ``t (3, B)`` for fixed rotations ``r (3, 3, B)``: each point gives
        ``t_x - x_n t_z = x_n (r3 . X) - r1 . X`` and the same for y -- linear in t, so an
        ill-conditioned scale (the DLT's) never decides the depth. The 3x3 normal equations
        are summed in closed form and solved by an unrolled Cholesky."""
        xn, yn = self.normalised()
        x0, x1, x2 = self.X
        rx = [x0 * r[i, 0] + x1 * r[i, 1] + x2 * r[i, 2] for i in range(3)]
        bu, bv = xn * rx[2] - rx[0], yn * rx[2] - rx[1]
        sx, sy = xn.sum(0), yn.sum(0)
        count = torch.full_like(sx, xn.shape[0])
        ata = [
            [count, None, None],
            [torch.zeros_like(sx), count, None],
            [-sx, -sy, (xn.square() + yn.square()).sum(0)],
        ]
        low = _cholesky(lambda i, j: ata[i][j], 3)
        atb = [bu.sum(0), bv.sum(0), -(xn * bu + yn * bv).sum(0)]
        return torch.stack(_backward(low, _forward(low, atb)))

    def evaluate(self, r: Tensor, t: Tensor) -> tuple[Tensor, ...]:
        """At poses ``r (3, 3, B)``, ``t (3, B)``: rotated points ``R X (3, n, B)``, inverse
        depth ``zi``, normalised coordinates ``xn, yn`` and pixel residuals ``ru, rv`` (each
        ``(n, B)``). Depths are clamped positive; callers reject poses behind the camera."""
        x0, x1, x2 = self.X
        rx = torch.stack([x0 * r[i, 0] + x1 * r[i, 1] + x2 * r[i, 2] for i in range(3)])
        if self.orthographic:
            zi = torch.ones_like(rx[2])
            xn, yn = rx[0] + t[0], rx[1] + t[1]
        else:
            zi = (rx[2] + t[2]).clamp_min_(1e-9).reciprocal_()
            xn = (rx[0] + t[0]) * zi
            yn = (rx[1] + t[1]) * zi
        ru = self.fx * xn + (self.cx - self.u)
        if self.skewed:
            ru += self.skew * yn
        rv = self.fy * yn + (self.cy - self.v)
        return rx, zi, xn, yn, ru, rv

    @staticmethod
    def cost(state: tuple[Tensor, ...]) -> Tensor:
        """Sum of squared pixel residuals ``(B,)``."""
        return (state[-2].square() + state[-1].square()).sum(0)

    def in_front(self, state: tuple[Tensor, ...], t: Tensor) -> Tensor:
        """``(B,)``: every point has positive depth (always, for an orthographic camera)."""
        if self.orthographic:
            return torch.ones_like(t[2], dtype=torch.bool)
        return (state[0][2] + t[2] > 0).all(0)

    def jacobian_rows(self, rx, zi, xn, yn, ru, rv) -> tuple[dict, dict]:
        """The two row patterns of the Jacobian for ``(delta_omega, delta_t)`` (a
        left-multiplied rotation increment and a translation), as dicts entry -> ``(n, B)``
        (the other entries are zero).

        With ``d pc / d omega = -[R X]_x`` and ``d pc / d t = I``, the pixel rows are
        ``d u = fx U + skew V`` and ``d v = fy V`` where ``U = zi [RX x e_u, e_u]``,
        ``V = zi [RX x e_v, e_v]``, ``e_u = (1, 0, -xn)``, ``e_v = (0, 1, -yn)``: sums over
        points are taken without the per-problem intrinsics, which scale them after.
        Orthographic: ``zi = 1``, ``e_u = (1, 0, 0)``, ``e_v = (0, 1, 0)``.
        """
        a, b, c = rx
        if self.orthographic:
            return {1: c, 2: -b, 3: zi}, {0: -c, 2: a, 4: zi}
        bz, az = b * zi, a * zi
        U = {0: -(bz * xn), 1: (c + a * xn) * zi, 2: -bz, 3: zi, 5: -(xn * zi)}
        V = {0: -(b * yn + c) * zi, 1: az * yn, 2: az, 4: zi, 5: -(yn * zi)}
        return U, V

    def gradient(self, U: dict, V: dict, ru: Tensor, rv: Tensor) -> list[Tensor]:
        """``J^T r``: 6 ``(B,)``."""
        zero = torch.zeros_like(self.fx)
        g = []
        for p in range(6):
            s = self.fx * (U[p] * ru).sum(0) if p in U else zero
            if p in V:
                s = s + self.fy * (V[p] * rv).sum(0)
                if self.skewed:
                    s = s + self.skew * (V[p] * ru).sum(0)
            g.append(s)
        return g

    def gauss_newton(self, U: dict, V: dict) -> list[list[Tensor]]:
        """``J^T J``: a 6x6 nested list of ``(B,)`` with the lower triangle filled."""
        fx2, fy2 = self.fx.square(), self.fy.square()
        if self.skewed:
            fy2 = fy2 + self.skew.square()
        jtj = [[None] * 6 for _ in range(6)]
        for p in range(6):
            for q in range(p + 1):
                s = fx2 * (U[p] * U[q]).sum(0) if p in U and q in U else 0
                if p in V and q in V:
                    s = s + fy2 * (V[p] * V[q]).sum(0)
                if self.skewed:
                    cross = sum(
                        (a[p] * b[q]).sum(0) for a, b in ((U, V), (V, U)) if p in a and q in b
                    )
                    s = s + self.fx * self.skew * cross
                jtj[p][q] = s
        return jtj


def refine_pose(
    points3d: Tensor,
    points2d: Tensor,
    K: Tensor,
    R: Tensor,
    t: Tensor,
    iterations: int = 30,
    tol: float = TOL,
    orthographic: bool = False,
) -> PoseResult:
    """Levenberg-Marquardt on the 6 pose parameters, batched; each problem keeps its own
    damping and only accepts steps that lower its cost (a backtracking line search on the
    damping), and stops when a further step would gain less than ``tol`` of its cost.
    Shapes and ``orthographic`` as :func:`solve_pose`."""
    x3, x2, K = _check(points3d, points2d, K)
    problem = _Pinhole.build(x3, x2, K, orthographic)
    return _refine(problem, R.permute(1, 2, 0).contiguous(), t.T.contiguous(), iterations, tol)


@dataclass
class _Active:
    """The problems still iterating (batch last): their indices in the output, poses,
    costs, Marquardt damping, evaluated state and the last damped Gauss-Newton factor."""

    index: Tensor
    r: Tensor
    t: Tensor
    cost: Tensor
    lam: Tensor
    state: tuple
    problem: _Pinhole
    low: list | None = None

    def subset(self, keep: Tensor, with_state: bool = True) -> _Active:
        """The problems at indices ``keep``. Gathering along the batch (last) axis is slow,
        so the evaluated state is recomputed from the pose instead (the same numbers)."""
        low = None
        if self.low is not None:
            low = [[x[keep] if x is not None else None for x in row] for row in self.low]
        r, t = self.r.index_select(-1, keep), self.t.index_select(-1, keep)
        problem = self.problem.select(keep)
        return _Active(
            self.index[keep],
            r,
            t,
            self.cost[keep],
            self.lam[keep],
            problem.evaluate(r, t) if with_state else (),
            problem,
            low,
        )

    def try_step(self, step: Tensor) -> tuple[Tensor, Tensor, Tensor, tuple, Tensor]:
        """Pose, cost and state after ``step (6, B)``; whether each is an improvement in
        front of the camera."""
        r_new = _matmul3(rotation_vector_to_matrix_batch_last(step[:3]), self.r)
        t_new = self.t + step[3:]
        state = self.problem.evaluate(r_new, t_new)
        cost = self.problem.cost(state)
        better = (cost < self.cost) & torch.isfinite(cost) & self.problem.in_front(state, t_new)
        return r_new, t_new, cost, state, better


def _refine(problem: _Pinhole, r: Tensor, t: Tensor, iterations: int, tol: float) -> PoseResult:
    """LM from batch-last poses ``r (3, 3, B)``, ``t (3, B)``; returns batch first."""
    n, b = problem.u.shape
    tol = max(tol, 10 * torch.finfo(problem.u.dtype).eps)  # float32 cannot resolve finer
    state = problem.evaluate(r, t)
    cost = problem.cost(state)
    r_out, t_out, cost_out = r.clone(), t.clone(), cost.clone()
    # Only problems that have not converged are iterated (most converge in two or three
    # steps and the stragglers should not cost the whole batch); finished problems are
    # written out once.
    act = _Active(
        torch.arange(b, device=r.device), r, t, cost, torch.full_like(cost, 1e-3), state, problem
    )

    def finish(at: Tensor, r: Tensor, t: Tensor, cost: Tensor) -> None:
        r_out[..., act.index[at]], t_out[:, act.index[at]], cost_out[act.index[at]] = r, t, cost

    it = 0
    for it in range(1, iterations + 1):
        U, V = act.problem.jacobian_rows(*act.state)
        g = act.problem.gradient(U, V, *act.state[-2:])
        # Converged when the previous damped Gauss-Newton factor (nearly the same matrix
        # near the optimum) predicts that a further step would lower the cost by less than
        # tol: g^T A^-1 g needs the gradient only, the cheap part of an iteration. Those
        # still take that last step with the previous factor (one evaluation on them
        # alone), so the result is as close to the optimum as if a full iteration had run.
        done = torch.full_like(act.cost, it == iterations, dtype=torch.bool)
        if act.low is not None:
            y = _forward(act.low, g)
            done |= (sum(yi.square() for yi in y) <= tol * act.cost + 1e-30) & (act.lam < 1e-2)
        if done.any():
            at = done.nonzero().squeeze(1)
            fin = act.subset(at, with_state=False)
            if fin.low is not None:
                step = torch.stack(_backward(fin.low, [-yi[at] for yi in y]))
                r_new, t_new, cost_new, _, better = fin.try_step(step)
                fin.r = torch.where(better, r_new, fin.r)
                fin.t = torch.where(better, t_new, fin.t)
                fin.cost = torch.where(better, cost_new, fin.cost)
            finish(at, fin.r, fin.t, fin.cost)
            if len(at) == len(done):
                break
            going = (~done).nonzero().squeeze(1)
            act = act.subset(going)
            U, V = act.problem.jacobian_rows(*act.state)  # cheaper than gathering them
            g = [gi[going] for gi in g]
        jtj = act.problem.gauss_newton(U, V)
        for p in range(6):  # Marquardt's scaled damping, plus a floor for singular problems
            jtj[p][p] = jtj[p][p] * (1 + act.lam) + 1e-12 * act.lam
        if act.problem.orthographic:  # t_z does not move the projection: hold it
            jtj[5][5] = torch.ones_like(act.lam)
        act.low = _cholesky(lambda i, j, a=jtj: a[i][j], 6)
        step = torch.stack(_backward(act.low, _forward(act.low, [-gi for gi in g])))
        r_new, t_new, cost_new, state_new, better = act.try_step(step)
        improvement = torch.where(better, act.cost - cost_new, torch.zeros_like(cost_new))
        act.r = torch.where(better, r_new, act.r)
        act.t = torch.where(better, t_new, act.t)
        act.state = tuple(
            torch.where(better, new, old) for new, old in zip(state_new, act.state, strict=True)
        )
        act.cost = torch.where(better, cost_new, act.cost)
        act.lam = torch.where(better, act.lam * 0.3, act.lam * 10).clamp(1e-9, 1e9)
        # also converged: an accepted step that barely helped, or damping so high steps vanish
        done = (better & (improvement <= tol * act.cost.clamp_min(1e-30) + 1e-30)) | (
            act.lam >= 1e8
        )
        if done.any():
            at = done.nonzero().squeeze(1)
            finish(at, act.r.index_select(-1, at), act.t.index_select(-1, at), act.cost[at])
            if len(at) == len(done):
                break
            act = act.subset((~done).nonzero().squeeze(1))
    return PoseResult(r_out.permute(2, 0, 1), t_out.T, cost_out / n, it)


def solve_pose(
    points3d: Tensor,
    points2d: Tensor,
    K: Tensor,
    iterations: int = 30,
    starts: int = 1,
    generator: torch.Generator | None = None,
    orthographic: bool = False,
) -> PoseResult:
    """Pose from 2-D joints: LM from a weak-perspective start, and from the DLT where that
    fits worse than 4x the batch's median cost (the lower cost kept); with ``starts > 1``
    also LM from the first start rotated by ``starts - 1`` rotations (90-180 degrees about
    random axes drawn from ``generator``), keeping each problem's lowest cost.

    Args:
        points3d: ``(B, n, 3)`` metres (or ``(n, 3)``), n >= 6.
        points2d: ``(B, n, 2)`` pixels, undistorted.
        K: ``(3, 3)`` or ``(B, 3, 3)``.
        orthographic: the camera projects without the division by depth (``K[0, 0]``,
            ``K[1, 1]`` in pixels per metre, as :class:`motion.cameras.CameraRig`); then
            ``t_z`` is unobservable and returned as 0, and there is no DLT start.

    Returns:
        :class:`PoseResult`.
    """
    x3, x2, K = _check(points3d, points2d, K)
    problem = _Pinhole.build(x3, x2, K, orthographic)
    r0, t0 = problem.initial_pose()
    best = _refine(problem, r0, t0, iterations, TOL)
    r0, t0 = r0.permute(2, 0, 1), t0.T  # batch first, for the other starts
    # The DLT start is run only where the first solution fits worse than the batch typically
    # does (a wrong basin shows as a large residual): the common case pays for one start.
    doubt = best.cost > 4 * best.cost.median() + 1e-12
    if doubt.any() and not orthographic:
        idx = doubt.nonzero().flatten()
        doubtful = problem.select(idx)
        r_d, t_d = _dlt(x3[idx], doubtful)
        cand = _refine(doubtful, r_d.permute(1, 2, 0), t_d.T, iterations, TOL)
        take = cand.cost < best.cost[idx]
        r_all, t_all, c_all = best.R.clone(), best.t.clone(), best.cost.clone()
        r_all[idx] = torch.where(take[:, None, None], cand.R, r_all[idx])
        t_all[idx] = torch.where(take[:, None], cand.t, t_all[idx])
        c_all[idx] = torch.where(take, cand.cost, c_all[idx])
        best = PoseResult(r_all, t_all, c_all, max(best.iterations, cand.iterations))
    if starts > 1:
        g = generator or torch.Generator(device=x2.device).manual_seed(0)
        axes = torch.nn.functional.normalize(
            torch.randn(starts - 1, 3, generator=g, dtype=x2.dtype, device=x2.device), dim=-1
        )
        angles = torch.linspace(
            torch.pi / 2, torch.pi, starts - 1, dtype=x2.dtype, device=x2.device
        )
        for rot in axis_angle_to_rotation_matrix(axes * angles[:, None]):
            # rotate about the body's centroid so the start stays in front of the camera
            centre = x3.mean(1)
            r_s = r0 @ rot
            t_s = (
                t0
                + (r0 @ centre.unsqueeze(-1)).squeeze(-1)
                - (r_s @ centre.unsqueeze(-1)).squeeze(-1)
            )
            cand = _refine(problem, r_s.permute(1, 2, 0), t_s.T, iterations, TOL)
            take = cand.cost < best.cost
            best = PoseResult(
                torch.where(take[:, None, None], cand.R, best.R),
                torch.where(take[:, None], cand.t, best.t),
                torch.where(take, cand.cost, best.cost),
                max(best.iterations, cand.iterations),
            )
    return best


def newton_pose(
    points3d: Tensor,
    points2d: Tensor,
    K: Tensor,
    R: Tensor,
    t: Tensor,
    iterations: int = 20,
    tol: float = 1e-8,
) -> PoseResult:
    """The proposal's refinement (Eq. 20), for comparison with :func:`refine_pose`: Newton
    steps on the 6 pose parameters with the full Hessian ``J^T J + sum_i r_i H_i`` (autograd,
    vectorised over problems), made positive definite by a modified Cholesky (a diagonal
    shift just large enough, from the smallest eigenvalue), and a line search over step
    lengths 1, 1/2, ..., 1/32 that keeps the lowest cost. Shapes as :func:`solve_pose`."""
    from torch.func import hessian, vmap

    x3, x2, K = _check(points3d, points2d, K)
    r, t = R.clone(), t.clone()

    def cost_at(theta, r0, t0, xx3, xx2, kk):
        r1 = axis_angle_to_rotation_matrix(theta[:3].unsqueeze(0))[0] @ r0
        u, v, _ = _project(xx3 @ r1.T + t0 + theta[3:], *_intrinsics(kk, ()))
        return 0.5 * ((u - xx2[:, 0]).square() + (v - xx2[:, 1]).square()).sum()

    hess_fn = vmap(hessian(cost_at))
    problem = _Pinhole.build(x3, x2, K)

    def evaluate(r, t):  # the batch-last problem at batch-first poses
        t_last = t.T.contiguous()
        state = problem.evaluate(r.permute(1, 2, 0).contiguous(), t_last)
        return state, problem.cost(state), problem.in_front(state, t_last)

    state, cost, _ = evaluate(r, t)
    scales = [1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125]
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 -- the count is reported
        g = torch.stack(problem.gradient(*problem.jacobian_rows(*state), *state[-2:]), -1)
        h = hess_fn(x2.new_zeros(x2.shape[0], 6), r, t, x3, x2, K)
        h = 0.5 * (h + h.transpose(1, 2))
        low = torch.linalg.eigvalsh(h)[:, 0]
        shift = (1e-9 * h.diagonal(dim1=-2, dim2=-1).abs().amax(-1) - low).clamp_min(0)
        step = _solve_spd(
            h + shift[:, None, None] * torch.eye(6, dtype=x2.dtype, device=x2.device), -g
        )
        best_cost, best_r, best_t = cost.clone(), r.clone(), t.clone()
        for a in scales:
            r_new = axis_angle_to_rotation_matrix(a * step[:, :3]) @ r
            t_new = t + a * step[:, 3:]
            _, c_new, in_front = evaluate(r_new, t_new)
            ok = (c_new < best_cost) & in_front
            best_cost = torch.where(ok, c_new, best_cost)
            best_r = torch.where(ok[:, None, None], r_new, best_r)
            best_t = torch.where(ok[:, None], t_new, best_t)
        improved = cost - best_cost
        r, t, cost = best_r, best_t, best_cost
        state, _, _ = evaluate(r, t)
        if (improved <= tol * cost.clamp_min(1e-30) + 1e-30).all():
            break
    return PoseResult(r, t, cost / x2.shape[1], it)


def solve_pose_views(
    points3d: Tensor,
    points2d: Tensor,
    K: Tensor,
    R_cam: Tensor,
    t_cam: Tensor,
    weights: Tensor | None = None,
    iterations: int = 30,
    init_camera: int = 0,
) -> PoseResult:
    """Body pose seen by several calibrated cameras at once.

    Finds the world pose ``(R, t)`` of the body with ``x_c ~ K_c (R_c (R X + t) + t_c)`` for
    every camera c: started from the single-view solution of ``init_camera`` (moved into
    the world frame), then Levenberg-Marquardt on all cameras' residuals together.

    Args:
        points3d: ``(B, n, 3)`` body-frame joints (metres).
        points2d: ``(B, C, n, 2)`` pixels in each camera.
        K, R_cam, t_cam: ``(C, 3, 3)``, ``(C, 3, 3)``, ``(C, 3)``: the rig (world to camera).
        weights: optional ``(B, C, n)`` >= 0 (0 = not seen, e.g. a missed detection).

    Returns:
        :class:`PoseResult` with world ``R``, ``t`` and the weighted mean squared residual.
    """
    if points2d.dim() != 4 or points2d.shape[-1] != 2 or points2d.shape[1] != K.shape[0]:
        raise ValueError(
            f"points2d must be (B, C, n, 2) with C = {K.shape[0]} cameras; got {tuple(points2d.shape)}"
        )
    b, c, n, _ = points2d.shape
    dtype = points2d.dtype
    x3 = points3d.expand(b, n, 3)
    K, R_cam, t_cam = K.to(dtype), R_cam.to(dtype), t_cam.to(dtype)
    w = points2d.new_ones(b, c, n) if weights is None else weights.to(dtype)
    sw = w.sqrt().unsqueeze(-1)  # (B, C, n, 1)
    single = solve_pose(x3, points2d[:, init_camera], K[init_camera])
    rc0, tc0 = R_cam[init_camera], t_cam[init_camera]
    r = rc0.T @ single.R
    t = (single.t - tc0) @ rc0  # R_c0^T (t_single - t_c0), row-vector form

    def residuals(x3, points2d, sw, r, t):
        rx = x3 @ r.transpose(1, 2)  # (B, n, 3): R X
        q = rx + t[:, None]
        pc = torch.einsum("cij,bnj->bcni", R_cam, q) + t_cam[None, :, None]  # (B, C, n, 3)
        u, v, z = _project(pc, *_intrinsics(K, (1, -1, 1)))
        res = torch.stack([u - points2d[..., 0], v - points2d[..., 1]], -1) * sw
        return res, rx, pc, z

    res, rx, pc, z = residuals(x3, points2d, sw, r, t)
    cost = res.square().sum((1, 2, 3))
    r_out, t_out, cost_out = r.clone(), t.clone(), cost.clone()
    # Only problems that have not converged are iterated: most converge in two or three
    # steps, and a few stragglers would otherwise keep the whole batch for every iteration.
    index = torch.arange(b, device=points2d.device)
    seen = w > 0
    lam = torch.full_like(cost, 1e-3)
    eye = torch.eye(6, dtype=dtype, device=points2d.device)
    fx, fy, skew = K[:, 0, 0][None, :, None], K[:, 1, 1][None, :, None], K[:, 0, 1][None, :, None]
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 -- the count is reported
        zi = 1.0 / z
        zero = torch.zeros_like(zi)
        du = torch.stack([fx * zi, skew * zi, -(fx * pc[..., 0] + skew * pc[..., 1]) * zi * zi], -1)
        dv = torch.stack([zero, fy * zi, -fy * pc[..., 1] * zi * zi], -1)
        dproj = torch.stack([du, dv], -2) @ R_cam[None, :, None]  # (B, C, n, 2, 3): d uv / d q
        j_rot = -(dproj @ skew_matrix(rx)[:, None])  # [R X]_x (B, n, 3, 3)
        j = (torch.cat([j_rot, dproj], -1) * sw.unsqueeze(-1)).reshape(len(index), -1, 6)
        jtj = j.transpose(1, 2) @ j
        g = (j.transpose(1, 2) @ res.reshape(len(index), -1, 1)).squeeze(-1)
        diag = torch.diagonal(jtj, dim1=-2, dim2=-1)
        step = _solve_spd(jtj + lam[:, None, None] * (eye * diag.unsqueeze(-1) + 1e-12 * eye), -g)
        r_new = axis_angle_to_rotation_matrix(step[:, :3]) @ r
        t_new = t + step[:, 3:]
        res_new, rx_new, pc_new, z_new = residuals(x3, points2d, sw, r_new, t_new)
        cost_new = res_new.square().sum((1, 2, 3))
        better = (
            (cost_new < cost)
            & torch.isfinite(cost_new)
            & ((pc_new[..., 2] > 0) | ~seen).all(-1).all(-1)
        )
        improvement = torch.where(better, cost - cost_new, torch.zeros_like(cost))
        k3, k4 = better[:, None, None], better[:, None, None, None]
        r, t = torch.where(k3, r_new, r), torch.where(better[:, None], t_new, t)
        res, rx = torch.where(k4, res_new, res), torch.where(k3, rx_new, rx)
        pc, z = torch.where(k4, pc_new, pc), torch.where(k3, z_new, z)
        cost = torch.where(better, cost_new, cost)
        lam = torch.where(better, lam * 0.3, lam * 10).clamp(1e-9, 1e9)
        done = (better & (improvement <= 1e-10 * cost + 1e-30)) | (lam >= 1e8)
        r_out[index], t_out[index], cost_out[index] = r, t, cost
        if done.all():
            break
        if done.any():
            going = (~done).nonzero().squeeze(1)
            index, x3, points2d, sw, seen = (a[going] for a in (index, x3, points2d, sw, seen))
            r, t, res, rx, pc, z, cost, lam = (a[going] for a in (r, t, res, rx, pc, z, cost, lam))
    return PoseResult(r_out, t_out, cost_out / w.sum((1, 2)).clamp_min(1), it)
