"""Stage 0 of registration: the cameras ``P_k``, three ways, the result saying which.

1. **given**: a calibrated :class:`motion.cameras.CameraRig` (e.g. from
   :func:`motion.cameras.load_pose2sim_calibration`), checked and passed through
   (:func:`check_rig`); with correspondences, their reprojection RMS is reported as a check.
2. **correspondences**: known intrinsics, extrinsics from 2D-3D correspondences
   (:func:`cameras_from_correspondences`): the project's batched pose solver
   :func:`motion.pose.solve_pose` (weak-perspective, rotated and DLT starts,
   Levenberg-Marquardt), all cameras in one call, then polished to a tight tolerance; missing
   correspondences (NaN rows) are masked out.
3. **focal estimated**: one uncalibrated camera per view set (:func:`estimate_focal_and_pose`):
   the focal length (square pixels, zero skew, principal point known) by a 1-D search over
   ``log f`` -- a coarse grid whose every focal is solved at once by one batched
   :func:`~motion.pose.solve_pose`, then Brent's method (golden section with parabolic steps)
   inside the best grid cell -- where each focal's cost is the total squared reprojection
   error with the poses at their optimum for that focal.

:func:`initialise_cameras` picks the way from what it is given and returns a
:class:`CameraInit`.

Conventions (as :mod:`motion.cameras`): world points in metres; a camera maps world to camera
frame by ``X_c = R X_w + t`` (OpenCV: x right, y down, z forward); pixels ``(u, v)``; focal
lengths and principal points in pixels; rotations as matrices (angles in radians). Routes 2
and 3 take undistorted pixels and return cameras without distortion. A correspondence is
missing when any of its coordinates is NaN; infinities are refused. Shapes: ``C`` cameras,
``N`` points, ``F`` frames (views of one camera), ``G`` focal grid.

The reprojection RMS is ``sqrt(mean_i ||x_i - proj(X_i)||^2)`` over the used correspondences
(pixels): the number OpenCV's ``calibrateCamera`` returns.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from motion.cameras import CameraRig, dlt
from motion.pose import PoseResult, dlt_pose, refine_pose, solve_pose
from motion.registration.types import RegistrationError

__all__ = [
    "MIN_POINTS",
    "SOURCES",
    "CameraInit",
    "FocalEstimate",
    "cameras_from_correspondences",
    "check_rig",
    "estimate_focal_and_pose",
    "initialise_cameras",
    "reprojection_rms",
]

#: The values of :attr:`CameraInit.source`, one per way of getting the cameras.
SOURCES = ("given", "correspondences", "focal estimated")

#: Correspondences a camera (or a view) needs: :func:`motion.pose.solve_pose`'s minimum.
MIN_POINTS = 6

#: Tolerance of the final pose polish (relative cost gain at which LM stops): far below
#: :data:`motion.pose.TOL`, so the cameras sit at the optimum, not near it (a few C problems
#: cost nothing to converge fully).
POLISH_TOL = 1e-12

#: Starts of every pose solved from scratch: :func:`motion.pose.solve_pose`'s weak-perspective
#: start and 3 rotated ones, plus the DLT's (which ``solve_pose`` tries only where a problem
#: fits worse than its batch, never in a batch of one). On nearly coplanar points the
#: weak-perspective start alone sometimes lands in a worse basin than the truth's; the other
#: starts make that rare (docs/decisions/004-tuning-evidence.md).
STARTS = 4

#: Default focal search of :func:`estimate_focal_and_pose`: focals from 0.3 to 5 times the
#: image width (fields of view of about 118 to 11 degrees across), a coarse grid of 41 focals
#: (7 % apart), then Brent to 1e-9 in ``log f``.
FOCAL_RANGE = (0.3, 5.0)
GRID = 41
XTOL = 1e-9

F64 = torch.float64


@dataclass
class CameraInit:
    """What stage 0 produced.

    Attributes:
        rig: the cameras (``C``), world to camera.
        source: how they were obtained, one of :data:`SOURCES`: ``"given"``,
            ``"correspondences"``, ``"focal estimated"``.
        rms_px: ``(C,)`` reprojection RMS of each camera on the correspondences, pixels;
            ``None`` when a given rig came without correspondences to check it on (NaN for
            a camera none of whose correspondences were present).
        note: one line for reports.
    """

    rig: CameraRig
    source: str
    rms_px: Tensor | None
    note: str


@dataclass
class FocalEstimate:
    """Focal length and poses of one camera from 2D-3D correspondences.

    Attributes:
        focal_px: the focal length, pixels (``fx = fy``).
        K: ``(3, 3)`` the intrinsics ``[[f, 0, cx], [0, f, cy], [0, 0, 1]]``.
        R: ``(F, 3, 3)`` per-view rotation, points to camera (``(3, 3)`` for unbatched input).
        t: ``(F, 3)`` per-view translation, metres (``(3,)`` for unbatched input).
        rms_px: reprojection RMS over all views' used correspondences, pixels.
        view_rms_px: ``(F,)`` the RMS of each view (``()`` for unbatched input), pixels.
        grid_focal_px: ``(G,)`` the coarse grid's focal lengths, pixels.
        grid_rms_px: ``(G,)`` the RMS at each of them with optimal poses (the cost curve, to
            judge how well the data pin the focal down), pixels.
        note: one line for reports.
    """

    focal_px: float
    K: Tensor
    R: Tensor
    t: Tensor
    rms_px: float
    view_rms_px: Tensor
    grid_focal_px: Tensor
    grid_rms_px: Tensor
    note: str


# ---------------------------------------------------------------------------------------------
# input checks
# ---------------------------------------------------------------------------------------------


def _tensor(value, name: str) -> Tensor:
    """``value`` as a floating tensor (integers become float64); else a one-line error."""
    if isinstance(value, Tensor):
        tensor = value
    else:
        try:
            tensor = torch.as_tensor(value)
        except (TypeError, ValueError, RuntimeError):
            raise RegistrationError(
                f"{name} must be an array of numbers; got {type(value).__name__}"
            ) from None
    if tensor.dtype == torch.bool or tensor.is_complex():
        raise RegistrationError(f"{name} must be real numbers; got dtype {tensor.dtype}")
    return tensor if tensor.is_floating_point() else tensor.to(F64)


def _shape(t: Tensor) -> tuple[int, ...]:
    return tuple(t.shape)


def _finite(t: Tensor, name: str) -> None:
    if not torch.isfinite(t).all():
        bad = int((~torch.isfinite(t)).sum())
        raise RegistrationError(f"{name} must be finite; got {bad} NaN or infinite values")


def _names(names, c: int) -> list[str]:
    """``C`` unique camera names (``cam1``, ``cam2``, ... by default)."""
    if names is None:
        return [f"cam{i + 1}" for i in range(c)]
    if isinstance(names, str) or not isinstance(names, Sequence):
        raise RegistrationError(f"names must be a list of {c} strings; got {type(names).__name__}")
    names = list(names)
    if len(names) != c or not all(isinstance(n, str) for n in names):
        raise RegistrationError(f"names must be {c} strings (one per camera); got {names!r}")
    if len(set(names)) != c:
        dup = sorted({n for n in names if names.count(n) > 1})
        raise RegistrationError(f"camera names must be unique; repeated: {dup}")
    return names


def _check_K(K: Tensor, c: int, names: list[str] | None = None) -> None:
    """``K (C, 3, 3)`` finite pinhole intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``,
    ``fx, fy > 0``."""
    if K.shape != (c, 3, 3):
        raise RegistrationError(f"K must be ({c}, 3, 3) intrinsics, pixels; got {_shape(K)}")
    _finite(K, "K")
    for i in range(c):
        k = K[i]
        structural = torch.stack([k[1, 0], k[2, 0], k[2, 1], k[2, 2] - 1]).abs().max()
        if not (k[0, 0] > 0 and k[1, 1] > 0) or structural > 1e-9:
            who = names[i] if names else f"camera {i}"
            raise RegistrationError(
                f"{who}: K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0; got "
                f"{k.tolist()}"
            )


def _check_size(size: Tensor, c: int) -> None:
    if size.shape != (c, 2):
        raise RegistrationError(
            f"size must be ({c}, 2) image [width, height] in pixels; got {_shape(size)}"
        )
    _finite(size, "size")
    if not (size >= 1).all():
        raise RegistrationError(
            f"image sizes must be at least 1 x 1 pixel; got {size.tolist()} ([width, height])"
        )


def check_rig(rig: CameraRig) -> CameraRig:
    """Check a given calibration and return it unchanged.

    Expected: ``K (C, 3, 3)`` finite pinhole intrinsics (``fx, fy > 0``, bottom row
    ``[0, 0, 1]``); ``R (C, 3, 3)`` proper rotations (orthonormal to 1e-6, 1e-4 in float32;
    ``det = +1``); ``t (C, 3)`` metres and ``dist (C, 5)`` finite; ``size (C, 2)`` at least
    1 x 1 pixel; ``C >= 1`` unique names.

    Raises:
        RegistrationError: naming the field (and the camera) and what it holds.
    """
    if not isinstance(rig, CameraRig):
        raise RegistrationError(f"rig must be a motion.cameras.CameraRig; got {type(rig).__name__}")
    K, R = _tensor(rig.K, "rig.K"), _tensor(rig.R, "rig.R")
    if K.dim() != 3 or K.shape[0] < 1:
        raise RegistrationError(f"rig.K must be (C, 3, 3) with C >= 1; got {_shape(K)}")
    c = K.shape[0]
    names = _names(rig.names, c)
    _check_K(K, c, names)
    expected = {"R": (c, 3, 3), "t": (c, 3), "dist": (c, 5)}
    for field, shape in expected.items():
        value = _tensor(getattr(rig, field), f"rig.{field}")
        if value.shape != shape:
            raise RegistrationError(f"rig.{field} must be {shape}; got {_shape(value)}")
        _finite(value, f"rig.{field}")
    _check_size(_tensor(rig.size, "rig.size"), c)
    tol = 1e-6 if R.dtype == F64 else 1e-4
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    off = (R @ R.transpose(-1, -2) - eye).abs().amax((-1, -2))
    det = torch.linalg.det(R)
    for i in range(c):
        if off[i] > tol or det[i] <= 0:
            raise RegistrationError(
                f"{names[i]}: rig.R must be a rotation (R R^T = I to {tol:g}, det +1); got "
                f"|R R^T - I| = {float(off[i]):.3g}, det {float(det[i]):.4g}"
            )
    return rig


def _points(
    points3d, points2d, c: int | None, what: str = "cameras"
) -> tuple[Tensor, Tensor, Tensor, torch.dtype]:
    """Correspondences for ``C`` cameras (or views): points3d ``(N, 3)`` or ``(C, N, 3)``,
    points2d ``(C, N, 2)`` -> both ``(C, N, .)`` float64 with NaN rows zeroed, the valid
    mask ``(C, N)`` (a row is missing when any of its 2-D or 3-D coordinates is NaN) and the
    inputs' promoted dtype."""
    x3, x2 = _tensor(points3d, "points3d"), _tensor(points2d, "points2d")
    if x2.dim() != 3 or x2.shape[-1] != 2 or (c is not None and x2.shape[0] != c):
        lead = "C" if c is None else str(c)
        raise RegistrationError(
            f"points2d must be ({lead}, N, 2) pixels, one row of points per {what[:-1]}; got "
            f"{_shape(x2)}"
        )
    c, n = x2.shape[:2]
    if x3.shape not in ((n, 3), (c, n, 3)):
        raise RegistrationError(
            f"points3d must be ({n}, 3) or ({c}, {n}, 3) metres to match points2d {_shape(x2)}; "
            f"got {_shape(x3)}"
        )
    for t, name in ((x3, "points3d"), (x2, "points2d")):
        if torch.isinf(t).any():
            raise RegistrationError(
                f"{name} must be finite or NaN (missing); got {int(torch.isinf(t).sum())} "
                "infinite values"
            )
    dtype = torch.promote_types(x3.dtype, x2.dtype)
    x3 = x3.to(F64).expand(c, n, 3)
    x2 = x2.to(F64)
    valid = ~(x3.isnan().any(-1) | x2.isnan().any(-1))
    zero = torch.zeros((), dtype=F64, device=x2.device)
    x3 = torch.where(valid[..., None], x3, zero)
    x2 = torch.where(valid[..., None], x2, zero)
    return x3, x2, valid, dtype


def _require_points(valid: Tensor, names: list[str]) -> None:
    count = valid.sum(-1)
    for i, k in enumerate(count.tolist()):
        if k < MIN_POINTS:
            raise RegistrationError(
                f"{names[i]}: needs at least {MIN_POINTS} 2D-3D correspondences without NaN; "
                f"got {k} of {valid.shape[-1]}"
            )


# ---------------------------------------------------------------------------------------------
# masked, batched pose
# ---------------------------------------------------------------------------------------------


def _pose(
    x3: Tensor,
    x2: Tensor,
    K: Tensor,
    valid: Tensor,
    start: tuple[Tensor, Tensor] | None = None,
    tol: float | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Poses of ``B`` problems with missing rows: ``x3 (B, N, 3)``, ``x2 (B, N, 2)``,
    ``K (B, 3, 3)``, ``valid (B, N)`` (each >= 6 true) -> ``R (B, 3, 3)``, ``t (B, 3)``,
    sum of squared pixel residuals ``(B,)``.

    Problems with the same number of present rows go to the solver together (their present
    rows gathered in order), so a batch without gaps is one call. ``start``: refine from these
    poses ``(B, 3, 3), (B, 3)`` by LM instead of solving from scratch; ``tol``: then polish
    with :func:`motion.pose.refine_pose` to this tolerance."""
    b = valid.shape[0]
    R = torch.empty(b, 3, 3, dtype=x2.dtype, device=x2.device)
    t = torch.empty(b, 3, dtype=x2.dtype, device=x2.device)
    sse = torch.empty(b, dtype=x2.dtype, device=x2.device)
    count = valid.sum(-1)
    for k in count.unique().tolist():
        idx = (count == k).nonzero().flatten()
        # present rows first, in their order (a stable sort of the missing flags)
        order = torch.sort((~valid[idx]).to(torch.int8), dim=-1, stable=True).indices[:, :k]
        g3 = x3[idx].gather(1, order[..., None].expand(-1, -1, 3))
        g2 = x2[idx].gather(1, order[..., None].expand(-1, -1, 2))
        if start is None:
            res = solve_pose(g3, g2, K[idx], starts=STARTS)
            r0, t0 = dlt_pose(g3, g2, K[idx])  # solve_pose tries it only where in doubt
            alt = refine_pose(g3, g2, K[idx], r0, t0)
            take = alt.cost < res.cost
            res = PoseResult(
                torch.where(take[:, None, None], alt.R, res.R),
                torch.where(take[:, None], alt.t, res.t),
                torch.where(take, alt.cost, res.cost),
                max(res.iterations, alt.iterations),
            )
            if tol is not None:
                res = refine_pose(g3, g2, K[idx], res.R, res.t, iterations=100, tol=tol)
        else:
            res = refine_pose(
                g3, g2, K[idx], start[0][idx], start[1][idx], iterations=100, tol=tol or 1e-7
            )
        R[idx], t[idx], sse[idx] = res.R, res.t, res.cost * k
    return R, t, sse


def _depth_check(
    x3: Tensor,
    valid: Tensor,
    R: Tensor,
    t: Tensor,
    names: list[str],
    where: str = "in the best pose found",
) -> None:
    """Every present point in front of its camera (depth > 0); else a one-line error. A pose
    the solver could not bring in front of the camera means no camera can see those points
    as given (e.g. points on both sides of it)."""
    depth = (x3 @ R.transpose(-1, -2) + t[:, None])[..., 2]
    behind = ((depth <= 0) & valid).sum(-1)
    for i, k in enumerate(behind.tolist()):
        if k:
            raise RegistrationError(
                f"{names[i]}: {k} of {int(valid[i].sum())} points are behind the camera "
                f"(depth <= 0) {where}; expected points a camera can see"
            )


def _mirror_check(x3: Tensor, x2: Tensor, valid: Tensor, sse: Tensor, names: list[str]) -> None:
    """Refuse correspondences that only a mirror-image camera explains.

    Points behind a camera, or pixels with one axis flipped, project like a camera whose
    ``P[:, :3]`` has a negative determinant at positive depths: no rotation reproduces them,
    so the pose solver settles on a poor fit. The unconstrained DLT
    (:func:`motion.cameras.dlt`, 11 parameters) still fits them; when it does, with a
    negative determinant, and the fitted camera's RMS (from ``sse (C,)``) is more than twice
    the DLT's plus 1 px, the data are refused. Coplanar or too few points make the DLT's sign
    meaningless, but then its fit is not much better than the camera's and nothing is said."""
    count = valid.sum(-1)
    ours = (sse / count).sqrt()
    for i in range(valid.shape[0]):
        if not ours[i] > 1.0:  # a camera fit of a pixel or better is no mirror image
            continue
        X, x = x3[i][valid[i]], x2[i][valid[i]]
        P = dlt(X, x)
        h = torch.cat([X, torch.ones_like(X[:, :1])], -1) @ P.T
        rms = ((h[:, :2] / h[:, 2:] - x).square().sum(-1).mean()).sqrt()
        if torch.linalg.det(P[:, :3]) < 0 and ours[i] > 2 * rms + 1.0:
            raise RegistrationError(
                f"{names[i]}: the correspondences fit only a mirror-image camera (DLT RMS "
                f"{float(rms):.3g} px, best real camera {float(ours[i]):.3g} px); expected points "
                "in front of the camera and pixels with x right, y down (points behind the "
                "camera, or an image axis flipped?)"
            )


# ---------------------------------------------------------------------------------------------
# route 1: a given calibration
# ---------------------------------------------------------------------------------------------


def reprojection_rms(rig: CameraRig, points3d, points2d) -> Tensor:
    """Reprojection RMS of each camera of ``rig`` on 2D-3D correspondences (distortion applied
    as :meth:`CameraRig.project`).

    Args:
        rig: ``C`` cameras.
        points3d: ``(N, 3)`` or ``(C, N, 3)`` world points, metres (NaN: missing).
        points2d: ``(C, N, 2)`` their pixels in each camera (NaN: missing).

    Returns:
        ``(C,)`` pixels, in the rig's dtype (NaN for a camera without any correspondence).

    Raises:
        RegistrationError: on shapes that do not match, or a present point behind a
            (perspective) camera.
    """
    x3, x2, valid, _ = _points(points3d, points2d, rig.num_cameras)
    R, t = rig.R.to(x3), rig.t.to(x3)
    if not rig.orthographic:
        _depth_check(x3, valid, R, t, rig.names, "of the given calibration")
    # project each camera's own points: the rig projects all points into all cameras
    cam = CameraRig(
        rig.K.to(x3), R, t, rig.dist.to(x3), rig.size.to(x3), rig.names, rig.orthographic
    )
    uv, _ = cam.project(x3)  # (C, C, N, 2): points of camera i in camera j
    own = uv.diagonal(dim1=0, dim2=1).permute(2, 0, 1)  # (C, N, 2)
    sq = ((own - x2).square().sum(-1) * valid).sum(-1)
    return (sq / valid.sum(-1)).sqrt().to(rig.K.dtype)


# ---------------------------------------------------------------------------------------------
# route 2: known intrinsics, extrinsics from correspondences
# ---------------------------------------------------------------------------------------------


def cameras_from_correspondences(
    points3d, points2d, K, size, names: list[str] | None = None
) -> CameraRig:
    """Extrinsics of ``C`` cameras with known intrinsics from 2D-3D correspondences.

    All cameras are solved in one batched :func:`motion.pose.solve_pose` call (cameras with
    missing rows grouped by how many they have; :data:`STARTS` starts and the DLT's, the
    lowest cost kept), then polished by Levenberg-Marquardt to :data:`POLISH_TOL`: each
    camera's pose minimises its own squared reprojection error.

    Args:
        points3d: ``(N, 3)`` world points seen by every camera, or ``(C, N, 3)`` per camera,
            metres. NaN rows: missing.
        points2d: ``(C, N, 2)`` undistorted pixels. NaN rows: not seen.
        K: ``(C, 3, 3)`` intrinsics, pixels.
        size: ``(C, 2)`` image width and height, pixels.
        names: ``C`` unique names (default ``cam1`` ... ``camC``).

    Returns:
        :class:`motion.cameras.CameraRig` without distortion, in the inputs' (promoted)
        floating dtype. Its reprojection RMS: :func:`reprojection_rms`.

    Raises:
        RegistrationError: on wrong shapes, non-finite values, invalid intrinsics, fewer
            than :data:`MIN_POINTS` present correspondences for a camera (naming it),
            points the best pose still has behind the camera, or correspondences only a
            mirror-image camera fits (points behind it, an image axis flipped).
    """
    x3, x2, valid, dtype = _points(points3d, points2d, None)
    c = x2.shape[0]
    K = _tensor(K, "K")
    size = _tensor(size, "size")
    names = _names(names, c)
    _check_K(K, c, names)
    _check_size(size, c)
    _require_points(valid, names)
    dtype = torch.promote_types(dtype, K.dtype)
    R, t, sse = _pose(x3, x2, K.to(F64), valid, tol=POLISH_TOL)
    _mirror_check(x3, x2, valid, sse, names)
    _depth_check(x3, valid, R, t, names)
    dist = torch.zeros(c, 5, dtype=dtype, device=R.device)
    return CameraRig(K.to(dtype), R.to(dtype), t.to(dtype), dist, size.to(dtype), names)


# ---------------------------------------------------------------------------------------------
# route 3: one uncalibrated camera
# ---------------------------------------------------------------------------------------------


def _brent(
    f: Callable[[float], float], a: float, b: float, x: float, fx: float, xtol: float
) -> tuple[float, float]:
    """Brent's minimisation of ``f`` on ``[a, b]`` from an interior ``x`` (``f(x) = fx``
    below the ends): golden-section steps, parabolic where they are safe, to an absolute
    ``xtol`` (Numerical Recipes' ``brent``). Returns the minimiser and its value."""
    golden = 0.3819660112501051
    w = v = x
    fw = fv = fx
    d = e = 0.0
    for _ in range(200):
        m = 0.5 * (a + b)
        tol1 = xtol
        tol2 = 2 * tol1
        if abs(x - m) <= tol2 - 0.5 * (b - a):
            break
        golden_step = True
        if abs(e) > tol1:  # try a parabola through x, w, v
            r = (x - w) * (fx - fv)
            q = (x - v) * (fx - fw)
            p = (x - v) * q - (x - w) * r
            q = 2 * (q - r)
            if q > 0:
                p = -p
            q = abs(q)
            e_old, e = e, d
            if abs(p) < abs(0.5 * q * e_old) and q * (a - x) < p < q * (b - x):
                d = p / q
                golden_step = False
                if (x + d) - a < tol2 or b - (x + d) < tol2:
                    d = math.copysign(tol1, m - x)
        if golden_step:
            e = (a - x) if x >= m else (b - x)
            d = golden * e
        u = x + d if abs(d) >= tol1 else x + math.copysign(tol1, d)
        fu = f(u)
        if fu <= fx:
            if u >= x:
                a = x
            else:
                b = x
            v, w, x = w, x, u
            fv, fw, fx = fw, fx, fu
        else:
            if u < x:
                a = u
            else:
                b = u
            if fu <= fw or w == x:
                v, w, fv, fw = w, u, fw, fu
            elif fu <= fv or v in (x, w):
                v, fv = u, fu
    return x, fx


def _intrinsics(focal: Tensor, pp: Tensor) -> Tensor:
    """``(G,)`` focal lengths and a principal point ``(2,)`` -> ``(G, 3, 3)`` K (fx = fy)."""
    K = torch.zeros(focal.shape[0], 3, 3, dtype=focal.dtype, device=focal.device)
    K[:, 0, 0] = K[:, 1, 1] = focal
    K[:, 0, 2], K[:, 1, 2] = pp[0], pp[1]
    K[:, 2, 2] = 1
    return K


def estimate_focal_and_pose(
    points3d,
    points2d,
    size,
    principal_point=None,
    focal_range: tuple[float, float] = FOCAL_RANGE,
    grid: int = GRID,
    xtol: float = XTOL,
) -> FocalEstimate:
    """Focal length of one camera (square pixels, no skew, known principal point, no
    distortion) and its pose in each of ``F`` views, from 2D-3D correspondences.

    The focal minimises the total squared reprojection error over all views, each view's
    pose at its optimum for that focal (the profile cost; the same objective as OpenCV's
    ``calibrateCamera`` with the principal point, aspect ratio and distortion fixed):

    1. a grid of ``grid`` focals spaced evenly in ``log f`` over ``focal_range`` times the
       image width, every (focal, view) pose problem solved in one batched
       :func:`motion.pose.solve_pose` call;
    2. Brent's method on ``log f`` inside the best grid point's neighbours, each cost
       evaluated by LM from the poses at the best focal so far, polished to
       :data:`POLISH_TOL` (so the cost curve is smooth and the minimum sharp).

    Views: each row of points is one view with its own pose (a pattern or a body moved in
    front of the camera, as ``calibrateCamera``'s views). For one static camera seeing world
    points over several frames, pass them as one view, flattened to ``(F * N, 3)``.

    Args:
        points3d: ``(N, 3)`` points (the same in every view) or ``(F, N, 3)``, metres, in
            each view's own frame. NaN rows: missing.
        points2d: ``(N, 2)`` or ``(F, N, 2)`` undistorted pixels. NaN rows: not seen.
        size: ``(2,)`` image width and height, pixels.
        principal_point: ``(2,)`` pixels (default the image centre ``(W / 2, H / 2)``, as
            :mod:`motion.synth`'s cameras).
        focal_range: the focals searched, as multiples of the image width (``0 < lo < hi``).
        grid: number of coarse grid focals (>= 5).
        xtol: absolute tolerance of the search on ``log f`` (relative tolerance on ``f``).

    Returns:
        :class:`FocalEstimate` (float64 results cast to the inputs' floating dtype).

    Raises:
        RegistrationError: on wrong shapes, non-finite sizes, a view with fewer than
            :data:`MIN_POINTS` present correspondences, points the best pose still has
            behind the camera, correspondences only a mirror-image camera fits, or a best
            focal at either end of the range (the data do not pin it down inside it).
    """
    x2_in = _tensor(points2d, "points2d")
    x3_in = _tensor(points3d, "points3d")
    unbatched = x2_in.dim() == 2
    if x2_in.dim() not in (2, 3) or x2_in.shape[-1] != 2:
        raise RegistrationError(
            f"points2d must be (N, 2) or (F, N, 2) pixels of one camera; got {_shape(x2_in)}"
        )
    x2_b = x2_in.unsqueeze(0) if unbatched else x2_in
    if x3_in.dim() not in (2, 3):
        raise RegistrationError(f"points3d must be (N, 3) or (F, N, 3) metres; got {_shape(x3_in)}")
    x3, x2, valid, dtype = _points(x3_in, x2_b, None, what="views")
    f_views, _ = valid.shape
    views = [f"view {i}" for i in range(f_views)]
    _require_points(valid, views)

    size = _tensor(size, "size")
    if size.shape != (2,):
        raise RegistrationError(
            f"size must be (2,) image [width, height] in pixels; got {_shape(size)}"
        )
    _check_size(size[None], 1)
    size = size.to(F64)
    if principal_point is None:
        pp = size / 2
    else:
        pp = _tensor(principal_point, "principal_point").to(F64)
        if pp.shape != (2,):
            raise RegistrationError(
                f"principal_point must be (2,) pixels [cx, cy]; got {_shape(pp)}"
            )
        _finite(pp, "principal_point")
    lo, hi = (float(v) for v in focal_range)
    if not (0 < lo < hi < math.inf):
        raise RegistrationError(
            f"focal_range must be (lo, hi) multiples of the image width with 0 < lo < hi; got "
            f"{focal_range}"
        )
    if int(grid) != grid or grid < 5:
        raise RegistrationError(f"grid must be an integer >= 5; got {grid}")
    grid = int(grid)

    est = _search_focal(x3, x2, valid, float(size[0]), pp, lo, hi, grid, xtol, views)
    if unbatched:
        est.R, est.t, est.view_rms_px = est.R[0], est.t[0], est.view_rms_px[0]
    for field in ("K", "R", "t", "view_rms_px", "grid_focal_px", "grid_rms_px"):
        setattr(est, field, getattr(est, field).to(dtype))
    return est


def _search_focal(
    x3: Tensor,
    x2: Tensor,
    valid: Tensor,
    width: float,
    pp: Tensor,
    lo: float,
    hi: float,
    grid: int,
    xtol: float,
    views: list[str],
    who: str = "",
) -> FocalEstimate:
    """:func:`estimate_focal_and_pose` on checked float64 inputs ``x3 (F, N, 3)``,
    ``x2 (F, N, 2)``, ``valid (F, N)``; ``views`` names the views in messages, ``who``
    (e.g. ``"cam1: "``) starts those about all of them."""
    f_views = valid.shape[0]
    # 1. coarse grid: G x F problems in one batch (grid-major)
    log_f = torch.linspace(math.log(lo * width), math.log(hi * width), grid, dtype=F64)
    focals = log_f.exp()
    Kg = _intrinsics(focals, pp).repeat_interleave(f_views, 0)
    rep = (grid, 1, 1)
    R, t, sse = _pose(x3.repeat(rep), x2.repeat(rep), Kg, valid.repeat(grid, 1))
    total = sse.view(grid, f_views).sum(1)
    points = int(valid.sum())
    grid_rms = (total / points).sqrt()
    best = int(total.argmin())
    if best in (0, grid - 1):
        _mirror_check(x3, x2, valid, sse.view(grid, f_views)[best], views)
        edge = "lower" if best == 0 else "upper"
        raise RegistrationError(
            f"{who}focal length at the {edge} end of the search range "
            f"{lo:g}-{hi:g} x the image width ({float(focals[best]):.1f} px); expected a minimum "
            "inside it (widen focal_range, or the correspondences do not determine the focal)"
        )

    # 2. Brent on log f between the best grid point's neighbours, LM from the best poses
    state = {"R": R.view(grid, f_views, 3, 3)[best], "t": t.view(grid, f_views, 3)[best]}
    cache: dict[float, tuple[float, Tensor, Tensor, Tensor]] = {}

    def cost(x: float) -> float:
        K = _intrinsics(torch.tensor([math.exp(x)], dtype=F64), pp).expand(f_views, 3, 3)
        r, tt, s = _pose(x3, x2, K, valid, start=(state["R"], state["t"]), tol=POLISH_TOL)
        value = float(s.sum())
        if not cache or value <= min(v[0] for v in cache.values()):
            state.update(R=r, t=tt)  # later evaluations start from the best poses so far
        cache[x] = (value, r, tt, s)
        return value

    x0 = float(log_f[best])
    x_best, _ = _brent(cost, float(log_f[best - 1]), float(log_f[best + 1]), x0, cost(x0), xtol)
    value, R, t, sse = cache[x_best]
    _mirror_check(x3, x2, valid, sse, views)
    _depth_check(x3, valid, R, t, views)

    focal = math.exp(x_best)
    rms = math.sqrt(value / points)
    note = (
        f"focal {focal:.1f} px ({focal / width:.3f} x width {width:.0f}) estimated with the "
        f"pose from {points} correspondences in {f_views} view(s): reprojection RMS "
        f"{rms:.3g} px"
    )
    K = _intrinsics(torch.tensor([focal], dtype=F64), pp)[0]
    view_rms = (sse / valid.sum(-1)).sqrt()
    return FocalEstimate(focal, K, R, t, rms, view_rms, focals, grid_rms, note)


# ---------------------------------------------------------------------------------------------
# the stage
# ---------------------------------------------------------------------------------------------


def _rms_text(rms: Tensor, names: list[str]) -> str:
    """``RMS 0.51 px (max 0.62, cam3)`` for a report line."""
    finite = torch.isfinite(rms)
    if not finite.any():
        return "no correspondences present to check"
    worst = int(torch.where(finite, rms, -math.inf).argmax())
    if len(rms) == 1:
        return f"reprojection RMS {float(rms[0]):.3g} px"
    return (
        f"reprojection RMS mean {float(rms[finite].mean()):.3g} px, max "
        f"{float(rms[worst]):.3g} ({names[worst]})"
    )


def initialise_cameras(
    rig: CameraRig | None = None,
    points3d=None,
    points2d=None,
    K=None,
    size=None,
    names: list[str] | None = None,
) -> CameraInit:
    """Stage 0: the cameras, by the first way that what is given allows.

    1. ``rig`` given: checked (:func:`check_rig`) and passed through, ``source="given"``;
       with ``points3d``/``points2d`` their reprojection RMS is reported (else
       ``rms_px=None``). ``K``, ``size`` and ``names`` must then be left out (the rig has
       them).
    2. ``points3d``, ``points2d``, ``K`` and ``size``: extrinsics from the correspondences
       (:func:`cameras_from_correspondences`), ``source="correspondences"``.
    3. ``points3d``, ``points2d`` and ``size`` without ``K``: each camera's focal length and
       pose from its own correspondences, as one view of world points
       (:func:`estimate_focal_and_pose`, principal point at the image centre),
       ``source="focal estimated"``.

    Args:
        rig: a calibrated rig (``C`` cameras).
        points3d: ``(N, 3)`` world points, or ``(C, N, 3)`` per camera, metres (NaN: missing).
        points2d: ``(C, N, 2)`` their pixels in each camera (NaN: not seen).
        K: ``(C, 3, 3)`` known intrinsics, pixels.
        size: ``(C, 2)`` image width and height, pixels.
        names: ``C`` camera names (default ``cam1`` ... ``camC``).

    Returns:
        :class:`CameraInit`; ``rms_px`` ``(C,)`` pixels.

    Raises:
        RegistrationError: when nothing sufficient is given (saying what was), when a rig
            comes with ``K``/``size``/``names`` as well, or from the route taken.
    """
    has_points = points3d is not None or points2d is not None
    if has_points and (points3d is None or points2d is None):
        missing = "points2d" if points2d is None else "points3d"
        raise RegistrationError(
            f"correspondences need both points3d and points2d; got no {missing}"
        )
    if rig is not None:
        extra = [n for n, v in (("K", K), ("size", size), ("names", names)) if v is not None]
        if extra:
            raise RegistrationError(
                f"a given rig carries its own intrinsics, sizes and names; expected none of "
                f"K, size, names beside it, got {', '.join(extra)}"
            )
        rig = check_rig(rig)
        what = f"given calibration of {rig.num_cameras} camera(s) ({', '.join(rig.names)})"
        if not has_points:
            return CameraInit(rig, "given", None, f"{what}; no correspondences to check it on")
        rms = reprojection_rms(rig, points3d, points2d)
        return CameraInit(rig, "given", rms, f"{what}; {_rms_text(rms, rig.names)}")
    if not has_points or size is None:
        given = [
            n
            for n, v in (("K", K), ("size", size), ("points3d", points3d), ("points2d", points2d))
            if v is not None
        ]
        raise RegistrationError(
            "initialise_cameras needs a calibrated rig, or 2D-3D correspondences (points3d, "
            "points2d) with the image size (and K when the intrinsics are known); got "
            f"{', '.join(given) if given else 'nothing'}"
        )
    if K is not None:
        rig = cameras_from_correspondences(points3d, points2d, K, size, names)
        rms = reprojection_rms(rig, points3d, points2d)
        note = (
            f"extrinsics of {rig.num_cameras} camera(s) from 2D-3D correspondences with known "
            f"intrinsics (solve_pose); {_rms_text(rms, rig.names)}"
        )
        return CameraInit(rig, "correspondences", rms, note)

    x3, x2, valid, dtype = _points(points3d, points2d, None)
    c = x2.shape[0]
    names = _names(names, c)
    size = _tensor(size, "size")
    _check_size(size, c)
    _require_points(valid, names)
    pp = size.to(F64) / 2
    estimates = [
        _search_focal(
            x3[i, None],
            x2[i, None],
            valid[i, None],
            float(size[i, 0]),
            pp[i],
            *FOCAL_RANGE,
            GRID,
            XTOL,
            [names[i]],
            f"{names[i]}: ",
        )
        for i in range(c)
    ]
    rig = CameraRig(
        torch.stack([e.K for e in estimates]).to(dtype),
        torch.cat([e.R for e in estimates]).to(dtype),
        torch.cat([e.t for e in estimates]).to(dtype),
        torch.zeros(c, 5, dtype=dtype),
        size.to(dtype),
        names,
    )
    rms = torch.tensor([e.rms_px for e in estimates], dtype=dtype)
    focal = ", ".join(f"{n} f={e.focal_px:.1f} px" for n, e in zip(names, estimates, strict=True))
    note = (
        f"focal length and pose of {c} camera(s) estimated from 2D-3D correspondences "
        f"({focal}); {_rms_text(rms, names)}"
    )
    return CameraInit(rig, "focal estimated", rms, note)
