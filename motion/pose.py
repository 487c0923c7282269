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


def _solve3(a: Tensor, b: Tensor) -> Tensor:
    """Batched 3x3 solve by the adjugate (closed form; LAPACK's per-matrix calls dominate
    at these sizes). Shapes: a (B, 3, 3), b (B, 3) -> (B, 3)."""
    c0 = torch.linalg.cross(a[:, 1], a[:, 2])
    c1 = torch.linalg.cross(a[:, 2], a[:, 0])
    c2 = torch.linalg.cross(a[:, 0], a[:, 1])
    det = (a[:, 0] * c0).sum(-1, keepdim=True)
    adj_t = torch.stack([c0, c1, c2], -1)  # columns are the cofactor rows: inv = adj_t / det
    return (adj_t @ b.unsqueeze(-1)).squeeze(-1) / det


def _solve_spd(a: Tensor, b: Tensor) -> Tensor:
    """Batched solve of small symmetric positive-definite systems by an unrolled Cholesky
    factorisation (vectorised over the batch). Shapes: a (B, m, m), b (B, m) -> (B, m)."""
    m = a.shape[-1]
    low = [[None] * m for _ in range(m)]
    for i in range(m):
        for j in range(i + 1):
            acc = a[:, i, j]
            for k in range(j):
                acc = acc - low[i][k] * low[j][k]
            low[i][j] = acc.clamp_min(1e-300).sqrt() if i == j else acc / low[j][j]
    y = [None] * m
    for i in range(m):
        acc = b[:, i]
        for k in range(i):
            acc = acc - low[i][k] * y[k]
        y[i] = acc / low[i][i]
    x = [None] * m
    for i in reversed(range(m)):
        acc = y[i]
        for k in range(i + 1, m):
            acc = acc - low[k][i] * x[k]
        x[i] = acc / low[i][i]
    return torch.stack(x, -1)


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
    if K.shape == (3, 3):
        K = K.expand(b, 3, 3)
    return points3d.expand(b, -1, -1), points2d.expand(b, -1, -1), K


def dlt_pose(points3d: Tensor, points2d: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Linear pose: DLT of ``[R | t]`` in normalised coordinates, positive depth, nearest rotation.

    Shapes: points3d ``(B, n, 3)``, points2d ``(B, n, 2)``, K ``(3, 3)`` or ``(B, 3, 3)`` ->
    R ``(B, 3, 3)``, t ``(B, 3)``.
    """
    x3, x2, K = _check(points3d, points2d, K)
    ones = torch.ones_like(x2[..., :1])
    norm = (
        torch.linalg.solve(K.unsqueeze(1), torch.cat([x2, ones], -1).unsqueeze(-1)).squeeze(-1)
    )[..., :2]
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
    return r, _translation_given_rotation(r, x3, norm)


def affine_pose(points3d: Tensor, points2d: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Weak-perspective pose: a least-squares affine camera on centred points, its rows
    orthonormalised (2x3 SVD), the depth from its scale; t then re-solved exactly for
    perspective. Stable where the DLT is not (a body far from the camera is nearly flat in
    depth). Shapes as :func:`dlt_pose`."""
    x3, x2, K = _check(points3d, points2d, K)
    ones = torch.ones_like(x2[..., :1])
    norm = (
        torch.linalg.solve(K.unsqueeze(1), torch.cat([x2, ones], -1).unsqueeze(-1)).squeeze(-1)
    )[..., :2]
    xc = x3 - x3.mean(1, keepdim=True)
    nc = norm - norm.mean(1, keepdim=True)
    # least squares nc ~ xc A^T by the normal equations (3x3, closed form)
    gram = xc.transpose(1, 2) @ xc
    rhs = xc.transpose(1, 2) @ nc  # (B, 3, 2)
    a = torch.stack([_solve3(gram, rhs[..., 0]), _solve3(gram, rhs[..., 1])], 1)  # (B, 2, 3)
    # nearest orthonormal rows: the polar factor (A A^T)^(-1/2) A, in closed form for the
    # 2x2 SPD matrix M = A A^T (batched 2x3 SVDs are ~20x slower on the CPU)
    m = a @ a.transpose(1, 2)
    det = (m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]).clamp_min(1e-30)
    sd = det.sqrt()
    eye2 = torch.eye(2, dtype=a.dtype, device=a.device)
    root = (m + sd[:, None, None] * eye2) / (m[:, 0, 0] + m[:, 1, 1] + 2 * sd).sqrt()[:, None, None]
    adj = torch.stack(
        [
            torch.stack([root[:, 1, 1], -root[:, 0, 1]], -1),
            torch.stack([-root[:, 1, 0], root[:, 0, 0]], -1),
        ],
        -2,
    )
    inv_root = adj / (root[:, 0, 0] * root[:, 1, 1] - root[:, 0, 1] * root[:, 1, 0])[:, None, None]
    r12 = inv_root @ a
    r3 = torch.linalg.cross(r12[:, 0], r12[:, 1])
    r = torch.cat([r12, r3.unsqueeze(1)], 1)
    return r, _translation_given_rotation(r, x3, norm)


def _translation_given_rotation(r: Tensor, x3: Tensor, norm: Tensor) -> Tensor:
    """Least-squares t for a fixed R from normalised image points: each point gives
    ``t_x - x_n t_z = x_n (r3 . X) - r1 . X`` and the same for y -- linear in t, so the
    DLT's ill-conditioned scale never decides the depth."""
    rx = x3 @ r.transpose(1, 2)  # (B, n, 3)
    xn, yn = norm[..., 0], norm[..., 1]
    one, zero = torch.ones_like(xn), torch.zeros_like(xn)
    a = torch.cat(
        [torch.stack([one, zero, -xn], -1), torch.stack([zero, one, -yn], -1)], 1
    )  # (B, 2n, 3)
    b = torch.cat([xn * rx[..., 2] - rx[..., 0], yn * rx[..., 2] - rx[..., 1]], 1)  # (B, 2n)
    return _solve3(a.transpose(1, 2) @ a, (a.transpose(1, 2) @ b.unsqueeze(-1)).squeeze(-1))


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


def _residuals(r: Tensor, t: Tensor, x3: Tensor, x2: Tensor, K: Tensor):
    rx = x3 @ r.transpose(1, 2)  # (B, n, 3) rotated points
    pc = rx + t[:, None]
    u, v, z = _project(pc, *_intrinsics(K, (-1, 1)))
    res = torch.stack([u - x2[..., 0], v - x2[..., 1]], -1)  # (B, n, 2)
    return res, rx, pc, z


def _jacobian(rx: Tensor, pc: Tensor, z: Tensor, K: Tensor) -> Tensor:
    """d residual / d (delta_omega, delta_t): (B, n, 2, 6).

    Written out entry by entry from ``d uv / d pc`` and ``d pc / d omega = -[R X]_x``,
    ``d pc / d t = I``, and stacked once (components first): forming the chain rule with
    batched 3x3 products and stacks is ~2x slower here (DESIGN.md section 7).
    """
    fx, fy, skew = K[:, 0, 0, None], K[:, 1, 1, None], K[:, 0, 1, None]
    zi = 1.0 / z
    a0, a1 = fx * zi, skew * zi
    a2 = -(fx * pc[..., 0] + skew * pc[..., 1]) * zi * zi
    b1 = fy * zi
    b2 = -fy * pc[..., 1] * zi * zi
    a, b, c = rx[..., 0], rx[..., 1], rx[..., 2]
    zero = torch.zeros_like(a0)
    entries = [
        a2 * b - a1 * c, a0 * c - a2 * a, a1 * a - a0 * b, a0, a1, a2,  # u row
        b2 * b - b1 * c, -b2 * a, b1 * a, zero, b1, b2,  # v row
    ]  # fmt: skip
    return torch.stack(entries, -1).reshape(*a0.shape, 2, 6)


def refine_pose(
    points3d: Tensor,
    points2d: Tensor,
    K: Tensor,
    R: Tensor,
    t: Tensor,
    iterations: int = 30,
    tol: float = 1e-8,
) -> PoseResult:
    """Levenberg-Marquardt on the 6 pose parameters, batched; each problem keeps its own
    damping and only accepts steps that lower its cost (a backtracking line search on the
    damping). Shapes as :func:`solve_pose`."""
    x3, x2, K = _check(points3d, points2d, K)
    r, t = R.clone(), t.clone()
    res, rx, pc, z = _residuals(r, t, x3, x2, K)
    cost = res.square().sum((-1, -2))
    lam = torch.full_like(cost, 1e-3)
    eye = torch.eye(6, dtype=x2.dtype, device=x2.device)
    tol = max(tol, 10 * torch.finfo(x2.dtype).eps)  # float32 cannot resolve finer changes
    # Only problems that have not converged are iterated (an active set): most converge in a
    # few steps, and the stragglers should not cost the whole batch.
    active = torch.arange(x2.shape[0], device=x2.device)
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 -- the count is reported
        a3, a2, ak = x3[active], x2[active], K[active]
        ar, at, acost, alam = r[active], t[active], cost[active], lam[active]
        ares, arx, apc, az = res[active], rx[active], pc[active], z[active]
        j = _jacobian(arx, apc, az, ak).reshape(len(active), -1, 6)
        jtj = j.transpose(1, 2) @ j
        g = (j.transpose(1, 2) @ ares.reshape(len(active), -1, 1)).squeeze(-1)
        diag = torch.diagonal(jtj, dim1=-2, dim2=-1)
        damped = jtj + alam[:, None, None] * (eye * diag.unsqueeze(-1) + 1e-12 * eye)
        step = _solve_spd(damped, -g)
        r_new = axis_angle_to_rotation_matrix(step[:, :3]) @ ar
        t_new = at + step[:, 3:]
        res_new, rx_new, pc_new, z_new = _residuals(r_new, t_new, a3, a2, ak)
        cost_new = res_new.square().sum((-1, -2))
        better = (cost_new < acost) & torch.isfinite(cost_new) & (pc_new[..., 2] > 0).all(-1)
        improvement = torch.where(better, acost - cost_new, torch.zeros_like(acost))
        keep = better[:, None, None]
        r[active] = torch.where(keep, r_new, ar)
        t[active] = torch.where(better[:, None], t_new, at)
        res[active] = torch.where(keep, res_new, ares)
        rx[active] = torch.where(keep, rx_new, arx)
        pc[active] = torch.where(keep, pc_new, apc)
        z[active] = torch.where(better[:, None], z_new, az)
        new_cost = torch.where(better, cost_new, acost)
        cost[active] = new_cost
        new_lam = torch.where(better, alam * 0.3, alam * 10).clamp(1e-9, 1e9)
        lam[active] = new_lam
        # converged: an accepted step that barely helped, or damping so high steps vanish
        done = (better & (improvement <= tol * new_cost.clamp_min(1e-30) + 1e-30)) | (
            new_lam >= 1e8
        )
        active = active[~done]
        if len(active) == 0:
            break
    return PoseResult(r, t, cost / x2.shape[1], it)


def solve_pose(
    points3d: Tensor,
    points2d: Tensor,
    K: Tensor,
    iterations: int = 30,
    starts: int = 1,
    generator: torch.Generator | None = None,
) -> PoseResult:
    """Pose from 2-D joints: LM from a weak-perspective start, and from the DLT where that
    fits worse than 4x the batch's median cost (the lower cost kept); with ``starts > 1``
    also LM from the first start
    rotated by ``starts - 1`` fixed rotations (90-180 degrees about spread axes, plus the
    depth-flipped mirror pose), keeping each problem's lowest cost.

    Args:
        points3d: ``(B, n, 3)`` metres (or ``(n, 3)``), n >= 6.
        points2d: ``(B, n, 2)`` pixels, undistorted.
        K: ``(3, 3)`` or ``(B, 3, 3)``.

    Returns:
        :class:`PoseResult`.
    """
    x3, x2, K = _check(points3d, points2d, K)
    r0, t0 = affine_pose(x3, x2, K)
    best = refine_pose(x3, x2, K, r0, t0, iterations)
    # The DLT start is run only where the first solution fits worse than the batch typically
    # does (a wrong basin shows as a large residual): the common case pays for one start.
    doubt = best.cost > 4 * best.cost.median() + 1e-12
    if doubt.any():
        idx = doubt.nonzero().flatten()
        r_d, t_d = dlt_pose(x3[idx], x2[idx], K[idx])
        cand = refine_pose(x3[idx], x2[idx], K[idx], r_d, t_d, iterations)
        take = cand.cost < best.cost[idx]
        r_all, t_all, c_all = best.R.clone(), best.t.clone(), best.cost.clone()
        r_all[idx] = torch.where(take[:, None, None], cand.R, r_all[idx])
        t_all[idx] = torch.where(take[:, None], cand.t, t_all[idx])
        c_all[idx] = torch.where(take, cand.cost, c_all[idx])
        best = PoseResult(r_all, t_all, c_all, max(best.iterations, cand.iterations))
    if starts > 1:
        g = generator or torch.Generator().manual_seed(0)
        axes = torch.nn.functional.normalize(
            torch.randn(starts - 1, 3, generator=g, dtype=x2.dtype), dim=-1
        )
        angles = torch.linspace(torch.pi / 2, torch.pi, starts - 1, dtype=x2.dtype)
        for rot in axis_angle_to_rotation_matrix(axes * angles[:, None]):
            # rotate about the body's centroid so the start stays in front of the camera
            centre = x3.mean(1)
            r_s = r0 @ rot
            t_s = (
                t0
                + (r0 @ centre.unsqueeze(-1)).squeeze(-1)
                - (r_s @ centre.unsqueeze(-1)).squeeze(-1)
            )
            cand = refine_pose(x3, x2, K, r_s, t_s, iterations)
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
        res, _, _, _ = _residuals(r1[None], (t0 + theta[3:])[None], xx3[None], xx2[None], kk[None])
        return 0.5 * res.square().sum()

    hess_fn = vmap(hessian(cost_at))
    res, rx, pc, z = _residuals(r, t, x3, x2, K)
    cost = res.square().sum((-1, -2))
    scales = torch.tensor([1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125], dtype=x2.dtype)
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 -- the count is reported
        j = _jacobian(rx, pc, z, K).reshape(x2.shape[0], -1, 6)
        g = (j.transpose(1, 2) @ res.reshape(x2.shape[0], -1, 1)).squeeze(-1)
        h = hess_fn(torch.zeros(x2.shape[0], 6, dtype=x2.dtype), r, t, x3, x2, K)
        h = 0.5 * (h + h.transpose(1, 2))
        low = torch.linalg.eigvalsh(h)[:, 0]
        shift = (1e-9 * h.diagonal(dim1=-2, dim2=-1).abs().amax(-1) - low).clamp_min(0)
        step = _solve_spd(h + shift[:, None, None] * torch.eye(6, dtype=x2.dtype), -g)
        best_cost, best_r, best_t = cost.clone(), r.clone(), t.clone()
        for a in scales:
            r_new = axis_angle_to_rotation_matrix(a * step[:, :3]) @ r
            t_new = t + a * step[:, 3:]
            res_new, _, pc_new, _ = _residuals(r_new, t_new, x3, x2, K)
            c_new = res_new.square().sum((-1, -2))
            ok = (c_new < best_cost) & (pc_new[..., 2] > 0).all(-1)
            best_cost = torch.where(ok, c_new, best_cost)
            best_r = torch.where(ok[:, None, None], r_new, best_r)
            best_t = torch.where(ok[:, None], t_new, best_t)
        improved = cost - best_cost
        r, t, cost = best_r, best_t, best_cost
        res, rx, pc, z = _residuals(r, t, x3, x2, K)
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
    w = torch.ones(b, c, n, dtype=dtype) if weights is None else weights.to(dtype)
    sw = w.sqrt().unsqueeze(-1)  # (B, C, n, 1)
    single = solve_pose(x3, points2d[:, init_camera], K[init_camera])
    rc0, tc0 = R_cam[init_camera], t_cam[init_camera]
    r = rc0.T @ single.R
    t = (single.t - tc0) @ rc0  # R_c0^T (t_single - t_c0), row-vector form

    def residuals(r, t):
        rx = x3 @ r.transpose(1, 2)  # (B, n, 3): R X
        q = rx + t[:, None]
        pc = torch.einsum("cij,bnj->bcni", R_cam, q) + t_cam[None, :, None]  # (B, C, n, 3)
        u, v, z = _project(pc, *_intrinsics(K, (1, -1, 1)))
        res = torch.stack([u - points2d[..., 0], v - points2d[..., 1]], -1) * sw
        return res, rx, pc, z

    res, rx, pc, z = residuals(r, t)
    cost = res.square().sum((1, 2, 3))
    lam = torch.full_like(cost, 1e-3)
    eye = torch.eye(6, dtype=dtype)
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 -- the count is reported
        fx, fy, skew = (
            K[:, 0, 0][None, :, None],
            K[:, 1, 1][None, :, None],
            K[:, 0, 1][None, :, None],
        )
        zi = 1.0 / z
        zero = torch.zeros_like(zi)
        du = torch.stack([fx * zi, skew * zi, -(fx * pc[..., 0] + skew * pc[..., 1]) * zi * zi], -1)
        dv = torch.stack([zero, fy * zi, -fy * pc[..., 1] * zi * zi], -1)
        dproj = torch.stack([du, dv], -2) @ R_cam[None, :, None]  # (B, C, n, 2, 3): d uv / d q
        a, bb, cc = rx[..., 0], rx[..., 1], rx[..., 2]
        zr = torch.zeros_like(a)
        skew_rx = torch.stack(
            [
                torch.stack([zr, -cc, bb], -1),
                torch.stack([cc, zr, -a], -1),
                torch.stack([-bb, a, zr], -1),
            ],
            -2,
        )  # [R X]_x, (B, n, 3, 3)
        j_rot = -(dproj @ skew_rx[:, None])
        j = (torch.cat([j_rot, dproj], -1) * sw.unsqueeze(-1)).reshape(b, -1, 6)
        jtj = j.transpose(1, 2) @ j
        g = (j.transpose(1, 2) @ res.reshape(b, -1, 1)).squeeze(-1)
        diag = torch.diagonal(jtj, dim1=-2, dim2=-1)
        step = _solve_spd(jtj + lam[:, None, None] * (eye * diag.unsqueeze(-1) + 1e-12 * eye), -g)
        r_new = axis_angle_to_rotation_matrix(step[:, :3]) @ r
        t_new = t + step[:, 3:]
        res_new, rx_new, pc_new, z_new = residuals(r_new, t_new)
        cost_new = res_new.square().sum((1, 2, 3))
        seen = w > 0
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
        if done.all():
            break
    return PoseResult(r, t, cost / w.sum((1, 2)).clamp_min(1), it)
