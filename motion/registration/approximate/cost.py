"""The image cost of a pair (video frame ``t'``, reference frame ``t``) at a rigid ``T`` and
its Levenberg-Marquardt refinement: :class:`_Batch` (cost and normal equations of a chunk of
problems, with analytic Jacobians, batch last), :func:`_levenberg_marquardt`, and
:func:`pair_costs` (the cost of given transforms, no fitting).

The cost's terms are those :mod:`motion.registration.approximate` lists, each a mean over its
points of distances in pixels divided by the body's pixel height ``h``, summed over cameras.
Pose parameters: a rotation increment left-multiplied about the root (radians), the root's
translation (metres), and for the body scale a log-scale. Conventions: pixels with centres at
integer ``(u, v)``, ``u`` right, ``v`` down; camera frames as OpenCV (x right, y down, z
forward); rotation matrices act on column vectors. Shapes: ``n`` problems (pair, start),
``C`` cameras, ``P`` parts, ``L`` capsule ends, ``S`` samples per part, ``M`` silhouette
pixels, ``K`` keypoints, ``D`` pose parameters (6, or 7 with the scale).
"""

from __future__ import annotations

import torch
from torch import Tensor

from motion.geometry import rotation_vector_to_matrix
from motion.registration.approximate.scene import _build_scene, _check_pairs, _generator, _Scene
from motion.registration.approximate.settings import Stage1Settings, _settings
from motion.registration.approximate.starts import _as_pair_init
from motion.registration.types import Reference, VideoFeatures


def _blend_index() -> Tensor:
    """``(16,)``: for the 4 x 4 channel pairs ``(a_u, a_v, b_u, b_v)^2`` of a part's
    normal-equation block, which of its 9 sums ``[g_u g_u, g_u g_v, g_v g_v] x [w_a w_a,
    w_a w_b, w_b w_b]`` (index ``3 gg + ww``) it is; a residual's point moves with the part's
    end pixels as ``w_a a + w_b b`` and ``g`` is the residual's gradient in pixels."""
    ch = torch.arange(4)
    e, k = ch // 2, ch % 2
    return ((k[:, None] + k[None, :]) * 3 + (e[:, None] + e[None, :])).reshape(-1)


_BLEND = _blend_index()
#: A soft step (1 beyond ~1/_STEP px, 0 below): float arithmetic instead of slow bool masks
#: for the Jacobian's gates at truncations and image borders.
_STEP = 1e3


def _step(x: Tensor) -> Tensor:
    return (x * _STEP).clamp_(0.0, 1.0)


class _Batch:
    """``n`` problems (pair, start) of one chunk: video frames ``rows (n,)`` and reference
    frames ``cols (n,)``; :meth:`evaluate` gives the cost and the LM normal equations.

    Internally every tensor is *batch last* (``(..., n)``): with a few dozen points per
    problem, batch-first tensors make reductions over parts and samples short inner loops;
    batch last, every operation is one long vectorised loop (several times faster here).

    The normal equations are accumulated per part: every silhouette or edge residual of part
    ``p`` depends on the pose only through the pixels of the part's two ends (a point at
    ``s`` along the axis moves as ``(1 - s) a + s b``; the capsules' image radii are held
    fixed within a step), so ``J^T J = sum_p Jl_p^T Q_p Jl_p`` with ``Jl_p`` ``(4, D)`` the
    ends' pixel Jacobian and ``Q_p`` ``(4, 4)`` built from 9 sums per part
    (:func:`_blend_index`), and ``J^T r`` from 4 more.
    """

    def __init__(self, scene: _Scene, rows: Tensor, cols: Tensor, with_scale: bool = False):
        s = scene
        self.s = s
        self.n = n = rows.shape[0]
        c = s.num_cameras
        self.lm = s.landmarks[cols].reshape(n, -1, 3).permute(2, 1, 0).contiguous()  # (3, L, n)
        self.with_scale = with_scale
        self.dof = 7 if with_scale else 6
        base = (rows[None, :] * c + torch.arange(c, device=rows.device)[:, None]) * (
            s.H * s.W
        )  # (C, n)
        self.base = base[:, None, None, :]
        obs = s.obs[rows].permute(1, 3, 2, 0)  # (C, 2, M, n)
        self.ou = obs[:, 0, None].contiguous()  # (C, 1, M, n)
        self.ov = obs[:, 1, None].contiguous()
        self.obs_w = s.obs_w[rows].permute(1, 2, 0).contiguous()  # (C, M, n)
        self.h = s.height[rows].T.contiguous()  # (C, n) px
        self.cam = s.cam_w[rows].T / self.h.square()  # (C, n) weight of squared px
        st = s.settings
        # square roots of the silhouette pixels' weights (C, M, n): fixed during the fit
        self.unc_sw = (st.uncovered_weight * self.obs_w * self.cam[:, None]).sqrt_()
        self.kp = None
        if s.keypoints is not None:
            self.kp = s.keypoints[rows].permute(1, 3, 2, 0).contiguous()  # (C, 3, K, n)
            kx = s.joints[cols][:, s.kp_joints]  # (n, K, 3)
            self.kp_x = kx.permute(2, 1, 0).contiguous()  # (3, K, n)
            # the joints' weights and Cauchy scales (C, K, n), fixed during the fit
            conf = self.kp[:, 2].clamp_min(0) * s.cam_w[rows].T[:, None]
            norm = conf.sum(1, keepdim=True).clamp_min(1e-9)
            self.kp_sig2 = (st.keypoint_sigma * self.h).square()[:, None]  # (C, 1, n) px^2
            self.kp_w = st.keypoint_weight * conf / norm / self.h.square()[:, None]
            self.kp_wsig2 = self.kp_w * self.kp_sig2

    def _project(self, xr: list[Tensor], p: Tensor, jac: bool):
        """Points ``xr`` (3 components ``(L, n)``: rotated, scaled, relative to the root) at
        root ``p (3, n)``: pixels ``u, v`` ``(C, L, n)``, inverse depth (1 if orthographic)
        and ``d (u, v) / d theta`` ``(C, L, 2, D, n)`` (or ``None``)."""
        s = self.s
        rc, tc, k = s.R[..., None, None], s.t[..., None, None], s.K[..., None, None]
        xw = [xr[j] + p[j] for j in range(3)]
        xc = [
            torch.addcmul(
                torch.addcmul(rc[:, i, 0] * xw[0], rc[:, i, 1], xw[1]), rc[:, i, 2], xw[2]
            )
            + tc[:, i]
            for i in range(3)
        ]  # (C, L, n)
        fx, fy, cx, cy, sk = k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2], k[:, 0, 1]
        if s.orthographic:
            zi = torch.ones_like(xc[2])
            uc = torch.addcmul(fx * xc[0], sk, xc[1])
            vc = fy * xc[1]
        else:
            zi = xc[2].clamp_min(1e-3).reciprocal_()
            uc = torch.addcmul(fx * xc[0], sk, xc[1]).mul_(zi)
            vc = (fy * xc[1]).mul_(zi)
        u, v = uc + cx, vc + cy
        if not jac:
            return u, v, zi, None
        # d u / d X = (fx R0 + sk R1 - (u - cx) R2) / z; d v / d X = (fy R1 - (v - cy) R2) / z
        c, num, n = u.shape
        jl = torch.empty(c, num, 2, self.dof, n, dtype=u.dtype, device=u.device)
        x0, x1, x2 = xr
        rows = (
            (uc, [torch.addcmul(fx * rc[:, 0, j], sk, rc[:, 1, j]) for j in range(3)]),
            (vc, [fy * rc[:, 1, j] for j in range(3)]),
        )  # per pixel coordinate: its value minus the centre, and fx R0 + sk R1 or fy R1
        for row, (centred, base) in enumerate(rows):
            if s.orthographic:
                a = [b.expand(c, num, n) for b in base]
            else:
                a = [
                    torch.addcmul(base[j], centred, rc[:, 2, j], value=-1).mul_(zi)
                    for j in range(3)
                ]
            out = jl[:, :, row]
            torch.sub(x1 * a[2], x2 * a[1], out=out[:, :, 0])  # rotation (left increment)
            torch.sub(x2 * a[0], x0 * a[2], out=out[:, :, 1])
            torch.sub(x0 * a[1], x1 * a[0], out=out[:, :, 2])
            for j in range(3):  # translation
                out[:, :, 3 + j] = a[j]
            if self.with_scale:  # d X / d log s = X_rel
                out[:, :, 6] = torch.addcmul(torch.addcmul(x0 * a[0], x1, a[1]), x2, a[2])
        return u, v, zi, jl

    def _lookup(self, pair_map: Tensor, pu: Tensor, pv: Tensor, jac: bool):
        """Bilinear read of a paired map (:func:`_pair_map`) at pixels ``pu, pv`` ``(C, P, S,
        n)``, clamped to the image (outside points read the border): value, with ``jac`` its
        gradient ``(gu, gv)`` (or ``None``), and ``seen``, whether the point is in the image
        (unclamped). The gradient of an unseen point is that of the border pixel: the caller
        zeroes it."""
        s = self.s
        u = pu.clamp(0, s.W - 1)
        v = pv.clamp(0, s.H - 1)
        # in the image exactly where the clamp changed nothing (NaN compares unequal too)
        seen = (u == pu) & (v == pv)
        u0 = u.floor().clamp_(max=s.W - 2)
        v0 = v.floor().clamp_(max=s.H - 2)
        fu, fv = u - u0, v - v0
        i = (
            torch.addcmul(u0, v0, torch.tensor(float(s.W), dtype=u0.dtype, device=u0.device))
            .long()
            .add_(self.base)
        )
        shape = (*i.shape, 2)
        flat = i.reshape(-1)
        top = pair_map.index_select(0, flat).view(fu.dtype).view(shape)
        bottom = pair_map.index_select(0, flat + s.W).view(fu.dtype).view(shape)
        f00, f01 = top[..., 0], top[..., 1]
        f10, f11 = bottom[..., 0], bottom[..., 1]
        d_top = f01 - f00
        d_bottom = f11 - f10
        upper = torch.addcmul(f00, fu, d_top)
        gv = torch.addcmul(f10, fu, d_bottom).sub_(upper)
        val = torch.addcmul(upper, fv, gv)
        if not jac:
            return val, None, None, seen
        gu = torch.addcmul(d_top, fv, d_bottom.sub_(d_top))
        return val, gu, gv, seen

    def _points(self, canon, blend, pair_map, ends, radii, weight, cut, unseen, area, jac, acc):
        """Squared truncated map distances at sample points (interior or outline) of the
        capsules (ends and radii ``(C, P, n)`` px); adds the points' 9 + 4 normal-equation sums
        per part into ``acc (13, C, P, n)``. Returns the cost ``(n,)``. A point outside the
        image is not observed: its distance is ``unseen`` times the truncation ``cut``, with
        no gradient."""
        au, av, bu, bv = (e.unsqueeze(2) for e in ends)  # (C, P, 1, n)
        r1, r2 = (r.unsqueeze(2) for r in radii)
        s_ax, s_r, alpha, beta, c_len, c_rad = canon  # (S, 1) each
        du, dv = bu - au, bv - av
        length = torch.addcmul(du * du, dv, dv).clamp_min_(1e-12).sqrt_()
        eu, ev = du / length, dv / length
        r = torch.addcmul(r1, s_r, r2 - r1)  # (C, P, S, n)
        ra, rb = r * alpha, r * beta
        pu = torch.addcmul(torch.addcmul(au, s_ax, du), ra, eu).sub_(rb * ev)
        pv = torch.addcmul(torch.addcmul(av, s_ax, dv), ra, ev).add_(rb * eu)
        w = r * torch.addcmul(c_len * length, c_rad, r) if area else c_len * length + c_rad * r
        w = w / w.sum((1, 2), keepdim=True).clamp_min(1e-12)
        val, gu, gv, seen = self._lookup(pair_map, pu, pv, jac)
        sw = (w * (weight * self.cam)[:, None, None]).sqrt_()
        res = sw * torch.where(seen, val.minimum(cut), unseen * cut)
        if jac:
            # no gradient beyond the truncation, nor at unseen points (outside the image)
            live = sw * _step(cut - val) * seen
            gu, gv = gu.mul_(live), gv.mul_(live)
            quad, lin = blend
            for gg, (ga, gb) in enumerate(((gu, gu), (gu, gv), (gv, gv))):
                acc[3 * gg : 3 * gg + 3] += torch.matmul(quad, ga * gb).permute(2, 0, 1, 3)
            for kk, gk in enumerate((gu, gv)):
                acc[9 + 2 * kk : 11 + 2 * kk] += torch.matmul(lin, gk * res).permute(2, 0, 1, 3)
        return res.square().sum((0, 1, 2))

    def evaluate(self, rot: Tensor, p: Tensor, log_s: Tensor | None, jac: bool):
        """Cost ``(n,)`` at poses ``rot (n, 3, 3)``, ``p (n, 3)`` (and log-scale ``(n,)``), and
        with ``jac`` the normal equations ``J^T J (n, D, D)`` and gradient ``J^T r (n, D)``."""
        s, st = self.s, self.s.settings
        n, dof = self.n, self.dof
        r = rot.permute(1, 2, 0)  # (3, 3, n)
        sc = log_s.exp() if log_s is not None else None
        terms = []  # (cost (n,), J^T J (D, D, n), J^T r (D, n)) of each term that weighs
        # the capsules' projection is skipped where no image term weighs (2-D joints only)
        if (
            st.outside_weight > 0
            or st.uncovered_weight > 0
            or (s.edist is not None and st.edge_weight > 0)
        ):
            terms.append(self._image(r, p.T, sc, jac))
        if self.kp is not None and st.keypoint_weight > 0:
            terms.append(self._keypoints(r, p.T, sc, jac))
        cost = torch.zeros(n, dtype=rot.dtype, device=rot.device)
        jtj = g = None
        for t_cost, t_jtj, t_g in terms:
            cost = cost + t_cost
            if jac:
                jtj = t_jtj if jtj is None else jtj + t_jtj
                g = t_g if g is None else g + t_g
        if not jac:
            return cost, None, None
        if jtj is None:  # no term weighs: nothing moves the pose
            jtj, g = torch.zeros(dof, dof, n, dtype=rot.dtype), torch.zeros(dof, n, dtype=rot.dtype)
        return cost, jtj.permute(2, 0, 1), g.T

    def _image(self, r: Tensor, p: Tensor, sc: Tensor | None, jac: bool):
        """The silhouette and edge terms at rotation ``r (3, 3, n)``, root ``p (3, n)`` (and
        scale ``sc (n,)``): cost ``(n,)`` and ``J^T J (D, D, n)``, ``J^T r (D, n)`` (or
        ``None``)."""
        s, st = self.s, self.s.settings
        n, dof = self.n, self.dof
        c = s.num_cameras
        dt = r.dtype
        lm = self.lm if sc is None else self.lm * sc
        xr = [
            torch.addcmul(torch.addcmul(r[i, 0] * lm[0], r[i, 1], lm[1]), r[i, 2], lm[2])
            for i in range(3)
        ]  # (L, n)
        u, v, zi, jl = self._project(xr, p, jac)  # (C, L, n)
        num_p = u.shape[1] // 2
        u, v = u.view(c, num_p, 2, n), v.view(c, num_p, 2, n)
        ends = (u[:, :, 0], v[:, :, 0], u[:, :, 1], v[:, :, 1])  # a_u, a_v, b_u, b_v (C, P, n)
        px = s.radii.T[:, None, :, None] * s.K[:, 0, 0][:, None, None]  # (2, C, P, 1)
        if not s.orthographic:
            px = px * zi.view(c, num_p, 2, n).permute(2, 0, 1, 3)
        if sc is not None:
            px = px * sc
        radii = (px[0].expand(c, num_p, n), px[1].expand(c, num_p, n))
        cost = torch.zeros(n, dtype=dt, device=px.device)
        acc = torch.zeros(13, c, num_p, n, dtype=dt, device=px.device) if jac else None
        cut = (st.truncate * self.h)[:, None, None]  # (C, 1, 1, n) px
        if st.outside_weight > 0:
            cost = cost + self._points(
                s.interior,
                s.interior_blend,
                s.dout,
                ends,
                radii,
                st.outside_weight,
                cut,
                0.0,  # no silhouette evidence either way
                True,
                jac,
                acc,
            )
        if s.edist is not None and st.edge_weight > 0:
            cut_e = (st.edge_truncate * self.h)[:, None, None]
            cost = cost + self._points(
                s.outline,
                s.outline_blend,
                s.edist,
                ends,
                radii,
                st.edge_weight,
                cut_e,
                0.5,  # as a hidden stretch of outline costs in stage 2's Edges cue
                False,
                jac,
                acc,
            )
        if st.uncovered_weight > 0:
            cost = cost + self._uncovered(ends, radii, cut[:, 0], jac, acc)
        jtj = g = None
        if jac:
            x = c * num_p * 4
            q = acc[_BLEND].view(4, 4, c, num_p, n).permute(2, 3, 0, 1, 4)  # (C, P, 4, 4, n)
            b = acc[9:].view(2, 2, c, num_p, n).permute(2, 3, 1, 0, 4).reshape(x, 1, n)
            jl = jl.view(c, num_p, 4, dof, n)  # channels (a_u, a_v, b_u, b_v)
            t1 = q[:, :, :, 0:1] * jl[:, :, 0:1]
            for j in range(1, 4):
                t1 = torch.addcmul(t1, q[:, :, :, j : j + 1], jl[:, :, j : j + 1])
            jl = jl.reshape(x, dof, n)
            jtj = (jl.unsqueeze(2) * t1.reshape(x, 1, dof, n)).sum(0)  # (D, D, n)
            g = (jl * b).sum(0)  # (D, n)
        return cost, jtj, g

    @staticmethod
    def _to_axis(ou, ov, au, av, du, dv, inv):
        """Pixels ``ou, ov`` against segments from ``a`` along ``d`` (``inv = 1 / |d|^2``),
        broadcast: the nearest point's place ``t`` in [0, 1], the offset ``xu, xv`` from it and
        its length."""
        ru, rv = ou - au, ov - av
        t = torch.addcmul(ru * du, rv, dv).mul_(inv).clamp_(0, 1)
        xu = torch.addcmul(ru, t, du, value=-1)
        xv = torch.addcmul(rv, t, dv, value=-1)
        dist = torch.addcmul(xu * xu, xv, xv).clamp_min_(1e-12).sqrt_()
        return t, xu, xv, dist

    def _uncovered(self, ends, radii, cut, jac, acc):
        """Silhouette pixels (the fixed subsample) against their distance to the nearest
        capsule (0 when covered), truncated at ``cut (C, 1, n)`` px. Returns the cost."""
        au, av, bu, bv = ends  # (C, P, n)
        r1, r2 = radii
        c, p, n = au.shape
        du, dv = bu - au, bv - av
        inv = torch.addcmul(du * du, dv, dv).clamp_min_(1e-9).reciprocal_()
        seg = (au, av, du, dv, inv)
        t, _, _, dist = self._to_axis(self.ou, self.ov, *(x.unsqueeze(2) for x in seg))
        sd = dist - torch.addcmul(r1.unsqueeze(2), t, (r2 - r1).unsqueeze(2))  # (C, P, M, n)
        del t, dist
        near = sd.amin(1)  # (C, M, n)
        sw = self.unc_sw
        res = sw * near.clamp(0).minimum(cut)
        if jac:
            # the nearest part's index: parts - 1e6 (sd - near) peaks there (float arithmetic;
            # argmin over a leading dimension is far slower than amin here)
            parts = torch.arange(p, dtype=sd.dtype, device=sd.device)[:, None, None]
            k = torch.addcmul(
                parts, sd - near.unsqueeze(1), torch.tensor(-1e6, dtype=sd.dtype, device=sd.device)
            )
            k = k.amax(1).round_().long().clamp_(0, p - 1)  # (C, M, n)
            # flat index of (c, k, j) in (C, P, n): the nearest part's segment per pixel, and
            # the pixel's entry of acc's (C, P, n) block
            at = k.device
            col = (torch.arange(c, device=at)[:, None, None] * p + k) * n + torch.arange(
                n, device=at
            )
            col = col.reshape(-1)
            near_seg = (x.reshape(-1).index_select(0, col).view(k.shape) for x in seg)
            # its t, offset and distance again, from (C, M, n) inputs: the same operations on
            # the same numbers as above (gathering them from (C, P, M, n) is slower)
            t_k, xu, xv, dist = self._to_axis(self.ou[:, 0], self.ov[:, 0], *near_seg)
            # d sd / d (a, b) = -(1 - t) e, -t e (e the unit direction from the axis)
            scale = sw * _step(near) * _step(cut - near) / dist
            gu = xu.mul_(scale).neg_()
            gv = xv.mul_(scale).neg_()
            wa, wb = 1 - t_k, t_k
            vals = torch.empty(13, *res.shape, dtype=res.dtype, device=res.device)
            ww = (wa * wa, wa * wb, wb * wb)
            for gg, g2 in enumerate((gu * gu, gu * gv, gv * gv)):
                for j in range(3):
                    torch.mul(g2, ww[j], out=vals[3 * gg + j])
            for kk_, gk in enumerate((gu * res, gv * res)):
                torch.mul(gk, wa, out=vals[9 + 2 * kk_])
                torch.mul(gk, wb, out=vals[10 + 2 * kk_])
            # into (13, C, P, n): column (c P + k) n + j
            acc.view(13, -1).index_add_(1, col, vals.view(13, -1))
        return res.square().sum((0, 1))

    def _keypoints(self, r, p, sc, jac):
        """Cauchy-robust 2-D joint term at rotation ``r (3, 3, n)``, root ``p (3, n)``: cost
        ``(n,)`` and (IRLS) ``J^T J (D, D, n)``, ``J^T r (D, n)``."""
        x = self.kp_x if sc is None else self.kp_x * sc
        xr = [
            torch.addcmul(torch.addcmul(r[i, 0] * x[0], r[i, 1], x[1]), r[i, 2], x[2])
            for i in range(3)
        ]
        u, v, _, jj = self._project(xr, p, jac)  # (C, K, n)
        eu, ev = u - self.kp[:, 0], v - self.kp[:, 1]
        z = torch.addcmul(eu * eu, ev, ev).div_(self.kp_sig2)
        cost = (self.kp_wsig2 * torch.log1p(z)).sum((0, 1))
        if not jac:
            return cost, None, None
        irls = (self.kp_w / z.add_(1)).sqrt_()  # Cauchy weights at the current residuals
        jr = jj * irls[:, :, None, None]  # (C, K, 2, D, n)
        res = torch.stack([irls * eu, irls * ev], 2)[:, :, :, None]  # (C, K, 2, 1, n)
        jr = jr.reshape(-1, self.dof, jr.shape[-1])
        jtj = (jr.unsqueeze(2) * jr.unsqueeze(1)).sum(0)
        return cost, jtj, (jr * res.reshape(-1, 1, res.shape[-1])).sum(0)


def _levenberg_marquardt(
    batch: _Batch, rot: Tensor, p: Tensor, log_s: Tensor | None, iterations: int, damping: float
):
    """Batched LM from ``rot (n, 3, 3)``, ``p (n, 3)`` (``log_s (n,)``): each problem keeps a
    step only if it lowers its cost. Returns rot, p, log_s, cost ``(n,)``."""
    cost, jtj, g = batch.evaluate(rot, p, log_s, True)
    lam = torch.full_like(cost, damping)
    for it in range(iterations):
        diag = jtj.diagonal(dim1=-2, dim2=-1)
        floor = 1e-6 * diag.mean(-1, keepdim=True) + 1e-12
        a = jtj + torch.diag_embed(lam[:, None] * diag + floor)
        step = -torch.linalg.solve(a, g)
        rot_n = rotation_vector_to_matrix(step[:, :3]) @ rot
        p_n = p + step[:, 3:6]
        ls_n = log_s + step[:, 6] if log_s is not None else None
        last = it == iterations - 1
        cost_n, jtj_n, g_n = batch.evaluate(rot_n, p_n, ls_n, not last)
        better = cost_n < cost
        b3 = better[:, None, None]
        rot = torch.where(b3, rot_n, rot)
        p = torch.where(better[:, None], p_n, p)
        if log_s is not None:
            log_s = torch.where(better, ls_n, log_s)
        if not last:
            jtj = torch.where(b3, jtj_n, jtj)
            g = torch.where(better[:, None], g_n, g)
        gain = torch.where(better, cost - cost_n, torch.zeros_like(cost))
        cost = torch.where(better, cost_n, cost)
        lam = torch.where(better, lam * 0.3, lam * 10).clamp(1e-7, 1e7)
        # converged: an accepted step that barely helped, or damping so high steps vanish
        if bool(((better & (gain <= 1e-6 * cost + 1e-12)) | (lam >= 1e5)).all()):
            break
    return rot, p, log_s, cost


def pair_costs(
    reference: Reference,
    video: VideoFeatures,
    rows: Tensor,
    cols: Tensor,
    rotation: Tensor,
    translation: Tensor,
    scale: float = 1.0,
    settings: Stage1Settings | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """The image cost of given transforms (no fitting, no heading prior): what
    :func:`fit_rigid_pairs` minimises.

    Args:
        rows ``(R,)``, cols ``(R, W)``: pairs as :func:`fit_rigid_pairs`.
        rotation: ``(R, W, 3, 3)``; translation: ``(R, W, 3)`` metres (or one per row,
            ``(R, 3, 3)`` and ``(R, 3)``).
        scale, settings, generator: as :func:`fit_rigid_pairs` (the same generator seed
            draws the same silhouette subsample).

    Returns:
        ``(R, W)`` costs (settings dtype).
    """
    st = _settings(settings)
    scene = _build_scene(reference, video, scale, st, _generator(generator, video))
    rows, cols = _check_pairs(scene, rows, cols)
    rot, p = _as_pair_init((rotation, translation), rows, cols, st.dtype)
    r, w = cols.shape
    flat_rows = rows[:, None].expand(r, w).reshape(-1)
    out = [
        _Batch(scene, flat_rows[lo : lo + st.chunk], cols.reshape(-1)[lo : lo + st.chunk]).evaluate(
            rot.reshape(-1, 3, 3)[lo : lo + st.chunk],
            p.reshape(-1, 3)[lo : lo + st.chunk],
            None,
            False,
        )[0]
        for lo in range(0, r * w, st.chunk)
    ]
    return torch.cat(out).reshape(r, w)
